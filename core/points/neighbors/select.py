"""Neighbour selection for a batch of pixel rays of one pinhole camera, by the model's configured method
(`ModelConfig.neighbors`, `.k`, `.neighbor_radius_px`)."""
from __future__ import annotations

import torch

from core.points.neighbors.base import METHODS
from core.points.neighbors.index import ScreenIndex, rays_knn_perpendicular
from core.util.errors import InputError


def select_neighbors(points: torch.Tensor, method: str, k: int, c2w: torch.Tensor, height: int, width: int,
                     focal: float, query_px: torch.Tensor, origins: torch.Tensor, dirs: torch.Tensor,
                     max_radius_px: float | str = "auto", backend: str = "auto",
                     radius_scale: float = 1.0) -> torch.Tensor:
    """K neighbours per ray. points [N, 3] (detached; non-finite = absent), query_px [R, 2] pixel coords
    (col, row), origins/dirs [R, 3] the rays through those pixels. max_radius_px: the screen metrics' pixel radius
    cap ("auto" or 0 = from the projected density, a number of pixels, or inf / < 0 = no cap; unused by
    "perpendicular"). radius_scale: that cap times this (> 1 where the points were stretched apart, see
    core/edits/deformation.py). Returns idx [R, K] int64, -1 where a ray has fewer than K candidates."""
    if method not in METHODS:
        raise InputError(f"neighbour search: method must be one of {METHODS}, got {method!r}")
    pts = points.detach()
    if method == "perpendicular":
        idx, _ = rays_knn_perpendicular(pts, origins, dirs, k, backend=backend)
    else:
        index = ScreenIndex(pts, c2w, height, width, focal, depth_factor=(method == "screen_depth"),
                            backend=backend, max_radius_px=max_radius_px)
        if radius_scale != 1.0:
            index.radius = index.radius_px(k) * float(radius_scale)  # no cap (inf) stays none
        idx, _ = index.query(query_px, k)
    return idx
