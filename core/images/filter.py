"""Anti-aliased texture lookups: several surface points per pixel, filtered like the renderer's pixel filter.

Why: a texture lookup at the one surface point of a pixel's centre ray samples the texture, it does not filter it.
Cycles (the ground truth here, and what an artist compares against) averages the radiance over a pixel footprint
with a Blackman-Harris filter (default width setting 1.5; a 3-pixel support reproduces its frames), in linear
light. Fine stripes and painted strokes alias without it: the true texture on the true mesh, sampled at pixel
centres or filtered this way, is measured in docs/atlas.md ("One lookup per pixel vs the pixel filter").

How: the ray surface points of a frame form a map [H, W, 3]; S x S sub-pixel points per pixel are interpolated
bilinearly from it (only across neighbours on the same surface: depth within a few pixel footprints), looked up,
turned to linear light, and filtered down with a separable Blackman-Harris kernel over the sub-pixel grid,
renormalised over the sub-pixels that lie on the object. For the atlas the chart networks run once per pixel and
their outputs (P(c|x), t_c(x)) are interpolated the same way (`subpixel_chart_uv`): S² times fewer network
evaluations, equal to second order because the maps are smooth.
"""
from __future__ import annotations

import math

import torch
import torch.nn.functional as F

# pixels: Cycles' Blackman-Harris at its default width setting (1.5) — a 3-pixel support matches its frames best
# (`python -m tools.bench.pixel_filter_bound`, docs/atlas.md)
FILTER_WIDTH = 3.0


def blackman_harris_taps(sub: int, width: float = FILTER_WIDTH) -> torch.Tensor:
    """1-D filter weights [M] (sum 1) at the sub-pixel centres within `width` pixels, M = round(width * sub).
    Tap j sits at ((j + 0.5) / M - 0.5) * width pixels from the pixel centre."""
    if sub < 1:
        raise ValueError(f"sub-pixels per side must be >= 1, got {sub}")
    m = max(int(round(width * sub)), 1)
    t = (torch.arange(m, dtype=torch.float64) + 0.5) / m  # position across the support, (0, 1)
    v = 2.0 * math.pi * t
    w = 0.35875 - 0.48829 * torch.cos(v) + 0.14128 * torch.cos(2 * v) - 0.01168 * torch.cos(3 * v)
    return (w / w.sum()).float()


def subpixel_points(points: torch.Tensor, valid: torch.Tensor, depth: torch.Tensor, sub: int,
                    max_depth_step: torch.Tensor | float) -> torch.Tensor:
    """Surface points (or any per-pixel values) at S x S sub-pixel positions, interpolated from the per-pixel map.

    points [H, W, C] (any values where not valid; C = 3 for points), valid [H, W] bool, depth [H, W] distance
    along each ray, max_depth_step: scalar or [H, W]; a neighbour joins the interpolation of pixel p's sub-pixels
    only if it is valid and its depth differs from p's by at most this (same surface, not across an occlusion
    edge). Returns [S*H, S*W, C]: sub-pixel (a, b) of pixel (r, c) at row S*r + a, column S*c + b, i.e. at
    (r + (a + 0.5) / S, c + (b + 0.5) / S) in pixel units; NaN where the owning pixel is not valid.
    """
    H, W, C = points.shape
    dev, dt = points.device, points.dtype
    step = torch.as_tensor(max_depth_step, dtype=dt, device=dev).expand(H, W)
    pts = torch.where(valid[..., None], points, torch.zeros_like(points))
    dep = torch.where(valid, depth, torch.zeros_like(depth))
    out = torch.empty((sub * H, sub * W, C), dtype=dt, device=dev)
    # neighbours by shifted views of edge-padded maps (no gathers); the validity map is padded with False, so a
    # neighbour outside the image never counts
    pts_p = F.pad(pts.permute(2, 0, 1)[None], (1, 1, 1, 1), mode="replicate")[0].permute(1, 2, 0).contiguous()
    dep_p = F.pad(dep[None, None], (1, 1, 1, 1), mode="replicate")[0, 0]
    val_p = F.pad(valid[None, None].to(dt), (1, 1, 1, 1))[0, 0] > 0.5

    def shifted(m, oy, ox):
        return m[1 + oy:1 + oy + H, 1 + ox:1 + ox + W]
    ok: dict = {}  # per neighbour offset (at most 9): 1 where that neighbour joins, else 0 [H, W]

    def joins(oy, ox):
        if (oy, ox) not in ok:
            ok[oy, ox] = (shifted(val_p, oy, ox) & ((shifted(dep_p, oy, ox) - dep).abs() <= step)).to(dt)
        return ok[oy, ox]
    invalid = ~valid[..., None]
    for a in range(sub):
        fy = (a + 0.5) / sub - 0.5  # offset from the pixel centre, in (-0.5, 0.5)
        dy = 1 if fy >= 0 else -1
        wy = abs(fy)
        for b in range(sub):
            fx = (b + 0.5) / sub - 0.5
            dx = 1 if fx >= 0 else -1
            wx = abs(fx)
            num = torch.zeros_like(pts)
            den = torch.zeros(H, W, dtype=dt, device=dev)
            for oy, oyw in ((0, 1 - wy), (dy, wy)):
                for ox, oxw in ((0, 1 - wx), (dx, wx)):
                    if oyw * oxw == 0.0:  # a tap of weight 0 (sub-pixels on the pixel centre's row or column)
                        continue
                    w = joins(oy, ox)
                    num.addcmul_(w[..., None], shifted(pts_p, oy, ox), value=oyw * oxw)
                    den.add_(w, alpha=oyw * oxw)
            sp = num.div_(den.clamp_min_(1e-12)[..., None])  # the pixel itself always counts (weight >= 1/4)
            out[a::sub, b::sub] = sp.masked_fill_(invalid, float("nan"))
    return out


def _taps(x: torch.Tensor, k: torch.Tensor, sub: int, n: int, dim: int) -> torch.Tensor:
    """Strided 1-D filter along dim (-1 or -2) of x [..., A, B]: out_j = Σ_t k[t] x[j * sub + t], j < n, as one
    scaled strided view added per tap (the same sums as a strided conv2d with a 1 x M kernel, several times
    faster on a CPU, where a one-channel convolution is a poor fit)."""
    out = None
    span = (n - 1) * sub + 1
    for t in range(k.numel()):
        s = x.narrow(dim, t, span)
        s = s[..., ::sub] if dim == -1 else s[..., ::sub, :]
        out = s * k[t] if out is None else out.add_(s * k[t])
    return out


def filter_down(values: torch.Tensor, on: torch.Tensor, sub: int, width: float = FILTER_WIDTH) -> torch.Tensor:
    """Pixel values from sub-pixel values with the Blackman-Harris footprint, renormalised over `on`.

    values [C, S*H, S*W], on [S*H, S*W] bool (sub-pixels on the object). Returns [C, H, W]: for every pixel the
    filter-weighted mean of the `on` sub-pixels in its footprint (NaN where none is).
    """
    C, SH, SW = values.shape
    k = blackman_harris_taps(sub, width).to(values.device, values.dtype)
    m = k.numel()
    if (m - sub) % 2:
        raise ValueError(f"a {width:g}-pixel filter with {sub} sub-pixels per side is not centred on the pixel; "
                         "choose width * sub - sub even")
    pad = (m - sub) // 2  # the footprint is centred on the pixel: taps from S*r - pad
    w = on.to(values.dtype)[None]
    stack = torch.cat([torch.where(on[None], values, torch.zeros_like(values)) * w, w], 0)[:, None]  # [C+1,1,SH,SW]
    stack = F.pad(stack, (pad, pad, pad, pad))[:, 0]
    y = _taps(_taps(stack, k, sub, SW // sub, -1), k, sub, SH // sub, -2)  # [C+1, H, W]
    den = y[-1]
    return torch.where(den > 1e-8, y[:-1] / den.clamp_min(1e-12), torch.full_like(y[:-1], float("nan")))
