"""Neighbour selection for a batch of pixel rays of one pinhole camera, by the model's configured method."""
from __future__ import annotations

import torch

from core.points import neighbors


def select_neighbors(points: torch.Tensor, method: str, k: int, c2w: torch.Tensor, height: int, width: int,
                     focal: float, query_px: torch.Tensor, origins: torch.Tensor, dirs: torch.Tensor,
                     radius_scale: float = 1.0) -> torch.Tensor:
    """K neighbours per ray. points [N, 3] (detached; non-finite = absent), query_px [R, 2] pixel coords
    (col, row), origins/dirs [R, 3]. radius_scale: screen metrics' automatic pixel radius cap times this (> 1
    where the points were stretched apart). Returns idx [R, K] int64, -1 where a ray has fewer than K candidates."""
    pts = points.detach()
    if method == "perpendicular":
        idx, _ = neighbors.rays_knn_perpendicular(pts, origins, dirs, k)
        return idx
    depth = method == "screen_depth"
    index = neighbors.ScreenIndex(pts, c2w, height, width, focal, depth_factor=depth)
    if radius_scale != 1.0:
        cap = index.radius_px(k) * float(radius_scale)
        index = neighbors.ScreenIndex(pts, c2w, height, width, focal, depth_factor=depth, max_radius_px=cap)
    idx, _ = index.query(query_px, k)
    return idx
