"""The packed atlas image: n chart textures of R x R texels laid out on a fixed grid, each with `pad` texels of
edge-replicated border, so that one image can be painted and read back exactly.

Why a fixed grid rather than xatlas: the learned charts are squares whose used region already fills most of the
square (the 2D->3D->2D cycle maps every u to the surface), and a grid keeps the chart <-> image map a pure integer
offset, which makes the round trip bitwise exact and the padding trivial. docs/atlas.md has the measured utilisation.

Conventions: chart texel (row i, col j) has its centre at u = (j + 0.5) / R, v = (i + 0.5) / R; row 0 is the top
row of the image (PNG convention). Pixel coordinates are (col, row) with pixel (r, c) centred at (c + 0.5, r + 0.5).
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import torch
import torch.nn.functional as F

from core.util.errors import InputError


@dataclass(frozen=True)
class GridLayout:
    """n charts of R x R texels in `cols` x `rows` cells of side R + 2 * pad."""

    n: int
    R: int
    pad: int

    kind = "grid"

    @property
    def cols(self) -> int:
        return int(math.ceil(math.sqrt(self.n))) if self.n != 8 else 4  # 8 charts: 4 x 2, no empty cell

    @property
    def rows(self) -> int:
        return int(math.ceil(self.n / self.cols))

    @property
    def cell(self) -> int:
        return self.R + 2 * self.pad

    @property
    def shape(self) -> tuple[int, int]:
        """(H, W) of the packed image."""
        return self.rows * self.cell, self.cols * self.cell

    def origin(self, c: int) -> tuple[int, int]:
        """(row, col) of chart c's texel (0, 0) in the packed image."""
        return (c // self.cols) * self.cell + self.pad, (c % self.cols) * self.cell + self.pad

    def origins(self, device=None) -> torch.Tensor:
        """[n, 2] (row, col) of every chart's texel (0, 0)."""
        return torch.tensor([self.origin(c) for c in range(self.n)], device=device, dtype=torch.float32)


def pack(textures: torch.Tensor, layout: GridLayout) -> torch.Tensor:
    """Chart textures [n, 3, R, R] -> packed image [H, W, 3]; borders replicate chart edges, unused cells are 0.
    An island layout (core/atlas/islands.py) takes each pixel from the chart that owns it."""
    if getattr(layout, "kind", "grid") == "islands":
        return layout.pack(textures)
    n, ch, R, R2 = textures.shape
    if (n, R, R2) != (layout.n, layout.R, layout.R):
        raise InputError(f"textures {tuple(textures.shape)} do not match the layout ({layout.n} charts of {layout.R}^2)")
    H, W = layout.shape
    img = torch.zeros(ch, H, W, dtype=textures.dtype, device=textures.device)
    padded = F.pad(textures, (layout.pad,) * 4, mode="replicate") if layout.pad > 0 else textures
    for c in range(n):  # n <= 8 charts: a loop over charts, not over texels
        r0, c0 = layout.origin(c)
        img[:, r0 - layout.pad:r0 + R + layout.pad, c0 - layout.pad:c0 + R + layout.pad] = padded[c]
    return img.permute(1, 2, 0).contiguous()


def unpack(image: torch.Tensor, layout: GridLayout, source: str = "atlas image") -> torch.Tensor:
    """Packed image [H, W, 3] -> chart textures [n, 3, R, R] (interiors only, bit-exact copies); for an island
    layout n views of the image itself (R = its side)."""
    if image.dim() != 3 or tuple(image.shape[:2]) != layout.shape or image.shape[2] < 3:
        raise InputError(f"{source}: expected an image of {layout.shape[0]}x{layout.shape[1]} pixels with 3 "
                         f"channels, got shape {tuple(image.shape)}")
    if not torch.isfinite(image[..., :3]).all():
        raise InputError(f"{source}: contains NaN or infinite values")
    if getattr(layout, "kind", "grid") == "islands":
        return layout.unpack(image[..., :3])
    R = layout.R
    out = []
    for c in range(layout.n):
        r0, c0 = layout.origin(c)
        out.append(image[r0:r0 + R, c0:c0 + R, :3].permute(2, 0, 1))
    return torch.stack(out)


def sample_charts(textures: torch.Tensor, uv: torch.Tensor) -> torch.Tensor:
    """Bilinear lookup with clamp-to-edge. textures [n, 3, R, R], uv [M, n, 2] (chart c at uv[:, c]) -> rgb [M, n, 3]."""
    grid = (uv * 2 - 1).permute(1, 0, 2)[:, None]  # [n, 1, M, 2], x = u (columns), y = v (rows)
    out = F.grid_sample(textures, grid, mode="bilinear", padding_mode="border", align_corners=False)
    return out[:, :, 0].permute(2, 0, 1)


def bilinear_entries(sid: torch.Tensor, chart: torch.Tensor, p: torch.Tensor, uv: torch.Tensor, R: int):
    """Sparse rows of chart lookups: lookup sid [K] reads chart[K] at uv [K, 2] with weight p [K] -> (lookup ids,
    texel ids (chart R + row) R + col, weights = bilinear x p), as sample_charts interpolates (texel centres at
    (j + 0.5) / R, clamp to edge). Entries in input order, then corner (row-major); zero weights left out."""
    f = uv.clamp(0, 1) * R - 0.5  # [K, 2]
    base = f.floor()
    frac = f - base
    base = base.long()
    fx, fy = frac[:, 0], frac[:, 1]
    # corner (dr, dc) in row-major order; weights as bilinear x p
    w = torch.stack([(1 - fx) * (1 - fy), fx * (1 - fy), (1 - fx) * fy, fx * fy], -1) * p[:, None]  # [K, 4]
    col = torch.stack([base[:, 0], base[:, 0] + 1, base[:, 0], base[:, 0] + 1], -1).clamp(0, R - 1)
    row = torch.stack([base[:, 1], base[:, 1], base[:, 1] + 1, base[:, 1] + 1], -1).clamp(0, R - 1)
    keep = w > 0
    cols = chart[:, None] * R * R + row * R + col
    return sid[:, None].expand_as(cols)[keep], cols[keep], w[keep]


def chart_coords(uv: torch.Tensor, chart: torch.Tensor) -> torch.Tensor:
    """Each point's coordinates in one chart: uv [M, n, 2], chart [M] long -> [M, 2]."""
    return uv.gather(1, chart[:, None, None].expand(-1, 1, 2))[:, 0]


def blend_charts(textures: torch.Tensor, uv: torch.Tensor, probs: torch.Tensor) -> torch.Tensor:
    """Chart lookups blended by the chart probabilities: Σ_c probs[:, c] · sample_charts(textures, uv)[:, c].
    textures [n, C, R, R], uv [M, n, 2], probs [M, n] -> [M, C] (summed over the charts in the lookup's own layout,
    without the [M, n, C] array). One chart per point (probs one-hot, as island atlases give them): each point
    is looked up in its own chart only, the same numbers at 1/n of the cost."""
    n = textures.shape[0]
    if n > 1 and uv.shape[0] and bool(((probs == 0) | (probs == 1)).all()) and bool((probs.sum(-1) == 1).all()):
        chart = probs.argmax(-1)
        out = torch.empty(uv.shape[0], textures.shape[1], dtype=textures.dtype, device=textures.device)
        for c in range(n):
            idx = torch.nonzero(chart == c)[:, 0]
            if idx.numel():
                g = (uv[idx, c] * 2 - 1)[None, None].to(textures.dtype)  # [1, 1, M_c, 2]
                out[idx] = F.grid_sample(textures[c:c + 1], g, mode="bilinear", padding_mode="border",
                                         align_corners=False)[0, :, 0].t()
        return out
    grid = (uv * 2 - 1).permute(1, 0, 2)[:, None]  # [n, 1, M, 2]
    out = F.grid_sample(textures, grid, mode="bilinear", padding_mode="border", align_corners=False)[:, :, 0]
    return (out * probs.t().to(out.dtype)[:, None]).sum(0).t()  # [n, C, M] -> [M, C]


def uv_to_pixel(uv: torch.Tensor, chart: torch.Tensor, layout: GridLayout) -> torch.Tensor:
    """uv [M, 2] in chart[M] -> packed-image pixel coordinates [M, 2] as (col, row), continuous."""
    o = layout.origins(uv.device)[chart]  # [M, 2] (row, col)
    uvc = uv.clamp(0, 1) * layout.R
    return torch.stack([o[:, 1] + uvc[:, 0], o[:, 0] + uvc[:, 1]], dim=-1)


def texel_uv(R: int, device=None) -> torch.Tensor:
    """Texel-centre coordinates of an R x R chart, row-major: [R * R, 2] as (u, v)."""
    t = (torch.arange(R, device=device, dtype=torch.float32) + 0.5) / R
    v, u = torch.meshgrid(t, t, indexing="ij")
    return torch.stack([u.reshape(-1), v.reshape(-1)], dim=-1)


def dilate_unused(textures: torch.Tensor, used: torch.Tensor) -> torch.Tensor:
    """Fill texels no sample reads with their nearest used texel's colour, so bilinear lookups near the edge of
    the used region (and paint previews) never see the initial grey. textures [n, 3, R, R], used [n, R, R] bool."""
    from scipy.ndimage import distance_transform_edt

    out = textures.clone()
    for c in range(textures.shape[0]):
        m = used[c].cpu().numpy()
        if m.all() or not m.any():
            continue
        _, (ri, ci) = distance_transform_edt(~m, return_indices=True)
        idx = torch.from_numpy((ri * m.shape[1] + ci).reshape(-1)).to(textures.device)
        out[c] = textures[c].reshape(3, -1)[:, idx].reshape(textures[c].shape)
    return out


def utilisation(pixels: np.ndarray, shape: tuple[int, int]) -> float:
    """Fraction of packed-image pixels that some sample lands in. pixels [M, 2] (col, row)."""
    H, W = shape
    c = np.clip(np.floor(pixels[:, 0]).astype(np.int64), 0, W - 1)
    r = np.clip(np.floor(pixels[:, 1]).astype(np.int64), 0, H - 1)
    hit = np.zeros(H * W, dtype=bool)
    hit[r * W + c] = True
    return float(hit.mean())
