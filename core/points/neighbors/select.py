"""Neighbour selection for a batch of pixel rays of one pinhole camera, by the model's configured method."""
from __future__ import annotations

import torch

from core.points import neighbors


def select_neighbors(points: torch.Tensor, method: str, k: int, c2w: torch.Tensor, height: int, width: int,
                     focal: float, query_px: torch.Tensor, origins: torch.Tensor, dirs: torch.Tensor) -> torch.Tensor:
    """K neighbours per ray. points [N, 3] (detached; non-finite = absent), query_px [R, 2] pixel coords
    (col, row), origins/dirs [R, 3]. Returns idx [R, K] int64, -1 where a ray has fewer than K candidates."""
    pts = points.detach()
    if method == "perpendicular":
        idx, _ = neighbors.rays_knn_perpendicular(pts, origins, dirs, k)
    else:
        idx, _ = neighbors.screen_knn(pts, c2w, height, width, focal, query_px, k,
                                      depth_factor=(method == "screen_depth"))
    return idx
