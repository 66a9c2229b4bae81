"""Atlas lookups at sub-pixel positions: the chart networks once per pixel, their outputs interpolated like the
surface points (`core.images.filter.subpixel_points`)."""
from __future__ import annotations

import torch

from core.images.filter import subpixel_points


def subpixel_chart_uv(atlas, points: torch.Tensor, valid: torch.Tensor, depth: torch.Tensor, sub: int,
                      max_depth_step: torch.Tensor | float) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Chart probabilities and texture coordinates at the S x S sub-pixel positions of a frame.

    The atlas networks run once per pixel (points [H, W, 3] where valid) and their outputs are interpolated to
    the sub-pixels like `subpixel_points` interpolates the points: t_c and c are smooth, so this equals evaluating
    them at the interpolated points up to second-order terms, at 1/S² of the cost. The raw outputs are
    interpolated and then placed (`Atlas.place`): an island atlas places neighbouring pixels of one chart in
    different islands where the chart was cut, and coordinates interpolated between two islands would land in
    neither. Returns (probs [K, n], uv [K, n, 2] of the K sub-pixels that are on the object, on [S*H, S*W] bool
    marking them, row-major); an island atlas's uv holds each sub-pixel's own chart in every slot (what its one-hot
    probs read, `Atlas.place`)."""
    H, W, _ = points.shape
    n = atlas.n
    feat = torch.zeros(H, W, 3 * n, dtype=points.dtype, device=points.device)
    finite = True
    if bool(valid.any()):
        probs, uv = atlas.chart_uv(points[valid], placed=False)
        out = torch.cat([probs, uv.reshape(-1, 2 * n)], 1).to(points.dtype)
        finite = bool(torch.isfinite(out).all())
        feat[valid] = out
    sp = subpixel_points(feat, valid, depth, sub, max_depth_step)
    if finite:  # NaN exactly on the sub-pixels of pixels off the object
        on = valid.repeat_interleave(sub, 0).repeat_interleave(sub, 1)
    else:  # a non-finite network output spreads to the sub-pixels that blend it: leave those out too
        on = torch.isfinite(sp).all(-1)
    v = sp[on]
    probs, uv = atlas.place(v[:, :n], v[:, n:].reshape(-1, n, 2), own_chart_only=True)
    return probs, uv, on

