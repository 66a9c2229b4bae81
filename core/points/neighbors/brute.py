"""Brute force: every point against every ray, in chunks (any device). The reference the fast paths are timed
against (`python -m tools.bench.neighbors`) and the "torch" backend."""
from __future__ import annotations

import math

import torch

from core.points.neighbors.base import Neighbors, empty, finalize, present

_CHUNK_ELEMS = 1 << 22  # rays × points per brute-force chunk (~16 MB of float32 distances)


def _topk_chunked(dist_fn, num_rays: int, num_points: int, k: int, device) -> tuple[torch.Tensor, torch.Tensor]:
    """Run dist_fn(ray_slice) -> [r, num_points] chunk by chunk and keep the k smallest per row (inf = absent)."""
    kk = min(k, num_points)
    idx = torch.empty((num_rays, kk), dtype=torch.int64, device=device)
    dist = torch.empty((num_rays, kk), dtype=torch.float32, device=device)
    step = max(1, _CHUNK_ELEMS // max(num_points, 1))
    for s in range(0, num_rays, step):
        d = dist_fn(slice(s, s + step))
        vals, ids = torch.topk(d, kk, dim=1, largest=False, sorted=True)
        idx[s:s + step], dist[s:s + step] = ids, vals
    return idx, dist


def perpendicular_brute(points: torch.Tensor, origins: torch.Tensor, dirs: torch.Tensor, k: int) -> Neighbors:
    """points [N, 3] (finite), origins/dirs [R, 3] (dirs unit, finite). Per-ray origins allowed."""
    def dist_fn(sl):
        v = points[None, :, :] - origins[sl, None, :]  # [r, N, 3]
        along = (v * dirs[sl, None, :]).sum(-1)  # [r, N]
        d = torch.linalg.vector_norm(torch.linalg.cross(v, dirs[sl, None, :].expand_as(v), dim=-1), dim=-1)
        return d.masked_fill(~(along > 0), math.inf)
    idx, dist = _topk_chunked(dist_fn, origins.shape[0], points.shape[0], k, points.device)
    return finalize(idx, dist, k, points.device)


def screen_brute(px: torch.Tensor, weight: torch.Tensor | None, query: torch.Tensor, k: int,
                  cap: float = math.inf) -> Neighbors:
    """px [M, 2] projected candidates, weight [M] or None, query [R, 2]; ranks by weight × pixel distance among
    the points within `cap` pixels."""
    def dist_fn(sl):
        d = torch.cdist(query[sl], px, compute_mode="donot_use_mm_for_euclid_dist")  # mm form loses ~0.01 px
        far = d > cap
        if weight is not None:
            d = d * weight[None, :]
        return d.masked_fill(far, math.inf)
    idx, dist = _topk_chunked(dist_fn, query.shape[0], px.shape[0], k, px.device)
    return Neighbors(idx, dist)



def perpendicular_brute_any(points, origins, dirs, k) -> Neighbors:
    """Brute force with per-ray origins: points [N, 3], origins/dirs [R, 3] -> Neighbors [R, K]."""
    device = points.device
    ids = torch.nonzero(present(points)).squeeze(1)
    pts = points.detach()[ids].to(torch.float32)
    d = dirs.detach().to(device, torch.float32)
    n = torch.linalg.vector_norm(d, dim=1)
    ok = torch.isfinite(n) & (n > 0)
    d = torch.where(ok[:, None], d / torch.where(ok, n, 1.0)[:, None], 0.0)
    if pts.shape[0] == 0:
        return empty(origins.shape[0], k, device)
    li, ld = perpendicular_brute(pts, origins.detach().to(device, torch.float32), d, k)
    ld = ld.masked_fill(~ok[:, None], math.inf)
    return finalize(torch.where(li >= 0, ids[li.clamp(min=0)], -1), ld, k, device)
