"""Bake any 3-D colour function into the atlas through the texel→surface map (retextures, decals).

Texels with a surface point get fn(point); unused texels inside a chart are then filled from their nearest baked
texel (so bilinear lookups at the edge of the used region do not pull in stale colours).
"""
from __future__ import annotations

from typing import Callable

import torch

from core.atlas.packing import dilate_unused, pack, unpack


@torch.no_grad()
def bake(atlas, fn: Callable[[torch.Tensor], tuple[torch.Tensor, torch.Tensor | None]],
         base_image: torch.Tensor | None = None) -> torch.Tensor:
    """Return a new packed atlas image [H, W, 3].

    fn(points [M, 3]) -> (rgb [M, 3], mask [M] or None): colour at canonical surface points and where it applies
    (None = everywhere, a global retexture; a mask composites a local decal over `base_image`).
    base_image: [H, W, 3] to paint over (default: the fitted atlas).
    """
    base = atlas.packed_image() if base_image is None else torch.as_tensor(base_image).float().to(atlas.device)
    texels = atlas.texel_points().to(base.device)
    valid = torch.isfinite(texels).all(-1)                                  # [H, W]
    out = base.clone()
    if not bool(valid.any()):
        return out
    pts = texels[valid]
    rgb, mask = fn(pts)
    rgb = rgb.to(out.dtype).clamp(0, 1)
    m = torch.ones(pts.shape[0], dtype=out.dtype, device=out.device) if mask is None \
        else mask.to(out.dtype).clamp(0, 1)
    out[valid] = m[:, None] * rgb + (1 - m[:, None]) * out[valid]
    used = unpack(valid[..., None].float().expand(-1, -1, 3), atlas.layout)[:, 0] > 0.5   # [n, R, R]
    filled = pack(dilate_unused(unpack(out, atlas.layout), used), atlas.layout)
    # Texels that changed: baked ones with m > 0, and unused ones whose nearest baked texel changed.
    changed = torch.zeros_like(base)
    changed[valid] = (m > 0).to(out.dtype)[:, None].expand(-1, 3)
    changed = pack(dilate_unused(unpack(changed, atlas.layout), used), atlas.layout)[..., 0] > 0.5
    return torch.where(changed[..., None], filled, base)
