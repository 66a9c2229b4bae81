"""Bake any 3-D colour function into the atlas (retextures, decals).

By default (`source` "fit") the texels are fitted so that every stored surface sample reads fn at itself: the
least-squares change of the image whose bilinear lookups at the samples' own chart coordinates give fn there
(`core.atlas.sample_lookup.fit_texels`); frames that look up through the samples (EditConfig `lookup` samples)
then return fn of the surface next to each point, with edges as sharp as the samples are dense.

The splat sources: texels with a surface point (the texel map) get a colour from fn; unused texels inside a chart
are then filled from their nearest baked texel (so bilinear lookups at the edge of the used region do not pull in
stale colours).

Where the atlas keeps its surface samples (models fitted since they are stored), fn is evaluated at the samples
and splatted into the texels with the texture's own kernel — a texel gets the mean of fn over the surface points
that look it up, as the fitted texture holds the mean colour. Evaluating fn at the texel's single point (the
mean position of those samples, the fallback for older files) is sharper in 3-D but off by how far the views'
surface points scatter (measured in docs/atlas.md, "Texel map").
"""
from __future__ import annotations

from typing import Callable

import torch

from core.atlas.packing import dilate_unused, pack, unpack
from core.atlas.sample_lookup import fit_texels, keeps_samples, sample_lookup
from core.atlas.texture import kernel_texture
from core.util.errors import InputError

SOURCES = ("auto", "fit", "samples", "points")


@torch.no_grad()
def bake(atlas, fn: Callable[[torch.Tensor], tuple[torch.Tensor, torch.Tensor | None]],
         base_image: torch.Tensor | None = None, source: str = "auto") -> torch.Tensor:
    """Return a new packed atlas image [H, W, 3].

    fn(points [M, 3]) -> (rgb [M, 3], mask [M] or None): colour at canonical surface points and where it applies
    (None = everywhere, a global retexture; a mask composites a local decal over `base_image`).
    base_image: [H, W, 3] to paint over (default: the fitted atlas).
    source: "fit" (texels fitted to fn at the stored surface samples, module doc), "samples" (fn splatted from
    the stored surface samples), "points" (fn at each texel's point) or "auto" (fit when the atlas has samples,
    else points).
    """
    if source not in SOURCES:
        raise InputError(f"bake source must be one of {', '.join(SOURCES)}, got {source!r}")
    have_samples = keeps_samples(atlas)
    if source in ("samples", "fit") and not have_samples:
        raise InputError("this atlas keeps no surface samples (an older model file); `pointgt atlas MODEL DATA "
                         "--texel-map-only` stores them")
    base = atlas.packed_image() if base_image is None else torch.as_tensor(base_image).float().to(atlas.device)
    if source == "fit" or (source == "auto" and have_samples):
        return _fit_bake(atlas, fn, base)
    texels = atlas.texel_points().to(base.device)
    valid = torch.isfinite(texels).all(-1)                                  # [H, W]
    out = base.clone()
    if not bool(valid.any()):
        return out
    if have_samples and source != "points":
        rgb_img, m_img = splat_function(atlas, fn)
        rgb, m = rgb_img.to(out.device)[valid], m_img.to(out.device)[valid]
    else:
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


def _fit_bake(atlas, fn, base: torch.Tensor) -> torch.Tensor:
    """source "fit": the samples' targets (fn composited over what they read of base by fn's mask), then the
    texels fitted to them."""
    lk = sample_lookup(atlas)
    rgb, mask = fn(lk.samples.to(atlas.device))
    rgb = torch.nan_to_num(rgb.float().to(base.device), nan=0.5).clamp(0, 1)
    target = rgb
    if mask is not None:
        m = torch.nan_to_num(mask.float().to(base.device), nan=0.0).clamp(0, 1)[:, None]
        target = m * rgb + (1 - m) * lk.read(unpack(base, atlas.layout)).to(base.dtype)
    return fit_texels(atlas, base, target)


@torch.no_grad()
def splat_function(atlas, fn) -> tuple[torch.Tensor, torch.Tensor]:
    """fn evaluated at the atlas's stored surface samples and kernel-averaged into its texels, packed:
    (rgb [H, W, 3] in [0, 1], mask [H, W] in [0, 1]); rgb is the mask-weighted mean colour. Texels no sample
    reaches get rgb 0.5, mask 0 (bake only reads texels of the texel map, which the same kernel covers)."""
    samples = atlas.bake_samples.to(atlas.device)
    rgb, mask = fn(samples)
    rgb = torch.nan_to_num(rgb.float().to(atlas.device), nan=0.5).clamp(0, 1)
    m = torch.ones(samples.shape[0], device=atlas.device) if mask is None \
        else torch.nan_to_num(mask.float().to(atlas.device), nan=0.0).clamp(0, 1)
    probs, uv = atlas.chart_uv(samples, own_chart_only=True)  # islands: one-hot, only the own chart is splatted
    R = atlas.layout.R
    labels = getattr(atlas, "blur_labels", None)   # island atlases: kernels stay inside one island
    num, covered, _ = kernel_texture(probs, uv, rgb * m[:, None], R, atlas.bake_sigma,
                                     labels=labels)   # mean of m·rgb
    if mask is None:
        tex, m_tex = num, covered.float()
    else:
        den, _, _ = kernel_texture(probs, uv, m[:, None].expand(-1, 3), R, atlas.bake_sigma,
                                   labels=labels)     # mean of m
        m_tex = torch.where(covered, den[:, 0], torch.zeros_like(den[:, 0]))
        tex = torch.where(m_tex[:, None] > 1e-6, num / m_tex[:, None].clamp_min(1e-6), torch.full_like(num, 0.5))
    rgb_img = pack(tex.clamp(0, 1), atlas.layout)
    m_img = pack(m_tex[:, None].expand(-1, 3, -1, -1).contiguous(), atlas.layout)[..., 0]
    return rgb_img, m_img.clamp(0, 1)
