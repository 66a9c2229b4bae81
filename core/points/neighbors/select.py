"""Neighbour selection for a batch of pixel rays of one pinhole camera, by the model's configured method
(`ModelConfig.neighbors`, `.k`, `.neighbor_radius_px`)."""
from __future__ import annotations

import math

import torch

from core.images.cameras import Intrinsics, focal_scale, project_points
from core.points.neighbors.base import METHODS
from core.points.neighbors.index import ScreenIndex, rays_knn_perpendicular
from core.util.errors import InputError


def select_neighbors(points: torch.Tensor, method: str, k: int, c2w: torch.Tensor, height: int, width: int,
                     focal: float, query_px: torch.Tensor, origins: torch.Tensor, dirs: torch.Tensor,
                     max_radius_px: float | str = "auto", backend: str = "auto",
                     radius_scale: float = 1.0, index: ScreenIndex | None = None,
                     reach: torch.Tensor | None = None, reach_gate: float = 0.0,
                     reach_surround: bool = False, reach_gate_own: bool = False,
                     reach_between: bool = False, reach_perspective: float = 0.0) -> torch.Tensor:
    """K neighbours per ray. points [N, 3] (detached; non-finite = absent), query_px [R, 2] pixel coords
    (col, row), origins/dirs [R, 3] the rays through those pixels. max_radius_px: the screen metrics' pixel radius
    cap ("auto" or 0 = from the projected density, a number of pixels, or inf / < 0 = no cap; unused by
    "perpendicular"). radius_scale: that cap times this (> 1 where the points were stretched apart, see
    core/edits/deformation.py). index: a `screen_index` of these points, camera, method, cap and K to query
    instead of building one (its cap is already resolved: max_radius_px, radius_scale and reach are then not
    used). reach [N] (>= 1) or None: point n is a candidate within the cap × reach[n] (`ScreenIndex`);
    reach_gate > 0: with reach, a ray with no point within reach_gate × the cap gets none, unless reach_surround and
    its candidates surround it; reach_gate_own: each point's gate at most its own reach; reach_between: beyond
    the plain cap the gate opens only between points; reach_perspective: a near reaching point's reach widened by
    the perspective, at most this factor (`ScreenIndex`).
    Returns idx [R, K] int64, -1 where a ray has fewer than K candidates."""
    if method not in METHODS:
        raise InputError(f"neighbour search: method must be one of {METHODS}, got {method!r}")
    pts = points.detach()
    if method == "perpendicular":
        idx, _ = rays_knn_perpendicular(pts, origins, dirs, k, backend=backend)
    else:
        if index is None:
            index = ScreenIndex(pts, c2w, height, width, focal, depth_factor=(method == "screen_depth"),
                                backend=backend, max_radius_px=max_radius_px, reach=reach,
                                reach_gate=reach_gate, reach_surround=reach_surround,
                                reach_gate_own=reach_gate_own, reach_between=reach_between,
                                reach_perspective=reach_perspective)
            if radius_scale != 1.0:
                index.radius = index.radius_px(k) * float(radius_scale)  # no cap (inf) stays none
        idx, _ = index.query(query_px, k)
    return idx


def screen_index(points: torch.Tensor, method: str, k: int, c2w: torch.Tensor, height: int, width: int, focal,
                 max_radius_px: float | str = "auto", radius_scale: float = 1.0,
                 backend: str = "auto", reach: torch.Tensor | None = None,
                 reach_gate: float = 0.0, reach_surround: bool = False,
                 reach_gate_own: bool = False, reach_between: bool = False,
                 reach_perspective: float = 0.0) -> ScreenIndex | None:
    """The ScreenIndex `select_neighbors` builds for these arguments (points [N, 3], non-finite = absent; reach [N]
    or None, reach_gate, reach_surround, reach_gate_own, reach_between and reach_perspective as there), with its
    pixel radius cap resolved for K = k (times radius_scale), so that
    queries for more candidates than K (a second search of some rays) stay within the same cap and reuse its grid.
    None for "perpendicular" (no screen)."""
    if method not in METHODS:
        raise InputError(f"neighbour search: method must be one of {METHODS}, got {method!r}")
    if method == "perpendicular":
        return None
    index = ScreenIndex(points.detach(), c2w, height, width, focal, depth_factor=(method == "screen_depth"),
                        backend=backend, max_radius_px=max_radius_px, reach=reach, reach_gate=reach_gate,
                        reach_surround=reach_surround, reach_gate_own=reach_gate_own,
                        reach_between=reach_between, reach_perspective=reach_perspective)
    index.radius = index.radius_px(k) * float(radius_scale)  # no cap (inf) stays none
    return index


def select_neighbors_soft(points: torch.Tensor, method: str, k: int, c2w: torch.Tensor, height: int, width: int,
                          focal, query_px: torch.Tensor, origins: torch.Tensor, dirs: torch.Tensor,
                          max_radius_px: float | str = "auto", width_px: float = 0.0,
                          radius_scale: float = 1.0, extra: int | None = None) -> tuple[torch.Tensor, torch.Tensor]:
    """K neighbours per ray with anti-aliased edges: the K-nearest rule and the pixel-radius cap as windows that fall
    from 1 to 0 over `width_px` pixels instead of steps (core/points/resolution.py, mode "footprint").

    Same arguments as `select_neighbors` (screen metrics; "perpendicular" has no soft form and returns
    select_neighbors' answer with a zero log-window), plus width_px >= 0: the transition width in pixels (a
    ranking by pixel distance × depth / focal measures it at each point's depth) and extra: candidates beyond K
    (default K) that the window may still reach. A neighbour's window is clamp(0.5 + (b − r) / width) with r its
    ranking distance and b the midpoint between the K-th and (K+1)-th ranking distances of its ray, times
    clamp(0.5 + (cap − d) / width) with d its pixel distance (the search reaches cap + width / 2).
    Returns idx [R, K + extra] int64 (-1 = none or a window of 0) and log_window [R, K + extra] (0 where idx is
    -1). With width_px = 0 the kept neighbours are exactly select_neighbors' K (ties aside)."""
    if method not in METHODS:
        raise InputError(f"neighbour search: method must be one of {METHODS}, got {method!r}")
    if method == "perpendicular":
        idx = select_neighbors(points, method, k, c2w, height, width, focal, query_px, origins, dirs,
                               max_radius_px, radius_scale=radius_scale)
        return idx, torch.zeros(idx.shape, dtype=torch.float32, device=idx.device)
    extra = k if extra is None else int(extra)
    wpx = float(width_px) if math.isfinite(float(width_px)) and float(width_px) > 0 else 0.0
    pts = points.detach()
    depth_factor = method == "screen_depth"
    index = ScreenIndex(pts, c2w, height, width, focal, depth_factor=depth_factor, max_radius_px=max_radius_px)
    cap = index.radius_px(k) * float(radius_scale)
    index.radius = cap + 0.5 * wpx if math.isfinite(cap) else cap
    nb = index.query(query_px, k + extra)
    idx, dist = nb.idx, nb.dist.to(torch.float64)
    valid = idx >= 0
    p = torch.nan_to_num(pts.to(torch.float64)[idx.clamp_min(0)], nan=0.0, posinf=0.0, neginf=0.0)
    cam = focal if isinstance(focal, Intrinsics) else float(focal)
    px, depth = project_points(p.reshape(-1, 3), c2w.detach().to(p.device, torch.float64), height, width, cam)
    px, depth = px.reshape(*idx.shape, 2), depth.reshape(idx.shape)
    d_px = (px - query_px.detach().to(px.device, torch.float64)[:, None, :]).norm(dim=-1)
    unit = (depth / float(focal_scale(cam))).clamp_min(1e-30) if depth_factor else torch.ones_like(depth)
    kth = dist[:, k - 1:k]
    nxt = dist[:, k:k + 1] if dist.shape[1] > k else torch.full_like(kth, math.inf)
    both = torch.isfinite(kth) & torch.isfinite(nxt)
    b = torch.where(both, 0.5 * (kth + nxt), torch.full_like(kth, math.inf))  # fewer than K + 1: no K edge
    ones = torch.ones_like(dist)
    if wpx > 0:
        with torch.no_grad():
            rank_w = torch.where(torch.isfinite(b), (0.5 + (b - dist) / (wpx * unit)).clamp(0, 1), ones)
            cap_w = (0.5 + (cap - d_px) / wpx).clamp(0, 1) if math.isfinite(cap) else ones
    else:  # the steps themselves
        rank_w = torch.where(torch.isfinite(b), (dist < b).to(dist.dtype), ones)
        cap_w = (d_px <= cap).to(dist.dtype) if math.isfinite(cap) else ones
        rank_w[:, :k] = 1.0  # the K nearest, whatever the ties
        cap_w[:, :k] = 1.0
    w = torch.nan_to_num(rank_w * cap_w, nan=0.0)
    keep = valid & (w > 0)
    idx = torch.where(keep, idx, torch.full_like(idx, -1))
    log_w = torch.where(keep, torch.log(w.clamp_min(1e-30)), torch.zeros_like(w)).to(torch.float32)
    return idx, log_w
