"""Neighbour search for rays: the K points each ray attends to (method.md §1), the hot path of PAPR.

Three metrics, all returning `Neighbors(idx [R, K] int64, dist [R, K] float32)`, sorted ascending, where a ray
with fewer than K candidates is padded with idx -1 and dist +inf (`.valid` [R, K] bool says which are real):

- "perpendicular" (paper / PAPR): ‖(p−o) − ((p−o)·d) d‖, only points in front of the origin ((p−o)·d > 0).
- "screen" (reference "knn_frustum"): project with the camera, keep points in front and inside the frame ± 1 px,
  K nearest in pixel space to each query pixel. dist in pixels.
- "screen_depth" (reference "d2r_z"): as "screen" but ranked by pixel distance × depth / focal, which is ≈ the
  perpendicular distance (world units).

Points with a non-finite coordinate are absent; so is any candidate whose distance is not finite.
Indices are not differentiable and `dist` is detached: gather the points with `idx` to get gradients.

Fast path (CPU tensors, backend "kdtree"): a scipy k-d tree over keys x_j (pixel coords, or unit directions from
the shared origin) and an exact re-rank. Every metric here is w_j · φ(‖q − x_j‖) with a per-point weight w_j > 0
(1, depth / focal, or |p − o|) and φ increasing, so once K candidates give an upper bound r on the K-th distance,
every closer point has key distance < φ⁻¹(r / w_min): a ball query of that radius is complete, hence exact.
The few points with the smallest weights (a stray point next to the camera would blow the ball up) are checked
by brute force instead. Other devices (backend "torch") use chunked brute force, which is also the reference the
benchmark (`python -m tools.bench.neighbors`) times the fast path against.
"""
from __future__ import annotations

import math
import numbers
from dataclasses import dataclass
from typing import NamedTuple

import numpy as np
import torch

from core.config import opt
from core.images.cameras import project_points
from core.util.errors import InputError

METHODS = ("screen", "screen_depth", "perpendicular")
BACKENDS = ("auto", "kdtree", "torch")
_CHUNK_ELEMS = 1 << 22  # rays × points per brute-force chunk (~16 MB of float32 distances)
_NEAR_POINTS = 32  # smallest-weight points handled by brute force in the weighted tree search
_LAYERS = 4  # weight layers of the weighted tree search (see _WeightedTree)
_MIN_TREE_RAYS = 64  # fewer rays than this from one origin: brute force beats building a tree
_MAX_COORD = 1e18  # beyond this a point has diverged; squared distances would overflow float32 on the torch path


@dataclass
class NeighborConfig:
    """Neighbour search: which metric ranks the K points a ray attends to."""

    method: str = opt("screen_depth", "neighbour metric: screen | screen_depth | perpendicular", choices=METHODS)
    k: int = opt(20, "neighbours per ray K")
    backend: str = opt("auto", "auto = k-d tree for CPU tensors, chunked torch brute force elsewhere",
                       choices=BACKENDS)


class Neighbors(NamedTuple):
    """idx [R, K] int64 (-1 = none) and dist [R, K] float32 (+inf = none), sorted ascending per ray."""

    idx: torch.Tensor
    dist: torch.Tensor

    @property
    def valid(self) -> torch.Tensor:
        """[R, K] bool: True where a real neighbour was found."""
        return self.idx >= 0


# ----------------------------------------------------------------------------------------------- validation
def _check_k(k) -> int:
    if isinstance(k, bool) or not isinstance(k, (int, np.integer)) or k < 1:
        raise InputError(f"neighbour search: k must be a positive integer, got {k!r}")
    return int(k)


def _check_matrix(name: str, t, cols: int) -> torch.Tensor:
    if not isinstance(t, torch.Tensor):
        raise InputError(f"neighbour search: {name} must be a torch.Tensor, got {type(t).__name__}")
    if t.dim() != 2 or t.shape[1] != cols:
        raise InputError(f"neighbour search: {name} must have shape [n, {cols}], got {list(t.shape)}")
    if not (t.is_floating_point() or t.dtype in (torch.int32, torch.int64)):
        raise InputError(f"neighbour search: {name} must be a real-valued tensor, got {t.dtype}")
    return t


def _check_backend(backend: str, device: torch.device) -> str:
    if backend not in BACKENDS:
        raise InputError(f"neighbour search: backend must be one of {BACKENDS}, got {backend!r}")
    if backend == "auto":
        return "kdtree" if device.type == "cpu" else "torch"
    return backend


def _check_camera(c2w, height, width, focal) -> None:
    if not isinstance(c2w, torch.Tensor) or tuple(c2w.shape) not in ((4, 4), (3, 4)):
        shape = list(c2w.shape) if isinstance(c2w, torch.Tensor) else type(c2w).__name__
        raise InputError(f"neighbour search: c2w must be a [4, 4] or [3, 4] tensor, got {shape}")
    if not bool(torch.isfinite(c2w).all()):
        raise InputError("neighbour search: c2w has non-finite entries")
    for name, v in (("height", height), ("width", width)):
        if isinstance(v, bool) or not isinstance(v, (int, np.integer)) or v < 1:
            raise InputError(f"neighbour search: {name} must be a positive integer, got {v!r}")
    if isinstance(focal, bool) or not (isinstance(focal, numbers.Real) and math.isfinite(focal) and focal > 0):
        raise InputError(f"neighbour search: focal must be a finite positive number of pixels, got {focal!r}")


def _present(points: torch.Tensor) -> torch.Tensor:
    """points [N, 3] -> [N] bool: finite and not diverged (|coord| <= _MAX_COORD); the rest are absent."""
    return (torch.isfinite(points) & (points.abs() <= _MAX_COORD)).all(dim=1)


def _empty(r: int, k: int, device) -> Neighbors:
    return Neighbors(torch.full((r, k), -1, dtype=torch.int64, device=device),
                     torch.full((r, k), math.inf, dtype=torch.float32, device=device))


def _finalize(idx: torch.Tensor, dist: torch.Tensor, k: int, device) -> Neighbors:
    """Pad to K columns, mark non-finite distances as absent, cast: idx [R, k'] and dist [R, k'] sorted."""
    r = idx.shape[0]
    if idx.shape[1] < k:
        pad = k - idx.shape[1]
        idx = torch.cat([idx, idx.new_full((r, pad), -1)], dim=1)
        dist = torch.cat([dist, dist.new_full((r, pad), math.inf)], dim=1)
    dist = dist.to(torch.float32)
    absent = ~torch.isfinite(dist) | (idx < 0)
    idx = idx.masked_fill(absent, -1)
    dist = dist.masked_fill(absent, math.inf)
    return Neighbors(idx.to(device), dist.to(device))


# ------------------------------------------------------------------------------------- brute force (any device)
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


def _perpendicular_brute(points: torch.Tensor, origins: torch.Tensor, dirs: torch.Tensor, k: int) -> Neighbors:
    """points [N, 3] (finite), origins/dirs [R, 3] (dirs unit, finite). Per-ray origins allowed."""
    def dist_fn(sl):
        v = points[None, :, :] - origins[sl, None, :]  # [r, N, 3]
        along = (v * dirs[sl, None, :]).sum(-1)  # [r, N]
        d = torch.linalg.vector_norm(torch.linalg.cross(v, dirs[sl, None, :].expand_as(v), dim=-1), dim=-1)
        return d.masked_fill(~(along > 0), math.inf)
    idx, dist = _topk_chunked(dist_fn, origins.shape[0], points.shape[0], k, points.device)
    return _finalize(idx, dist, k, points.device)


def _screen_brute(px: torch.Tensor, weight: torch.Tensor | None, query: torch.Tensor, k: int) -> Neighbors:
    """px [M, 2] projected candidates, weight [M] or None, query [R, 2]; ranks by weight × pixel distance."""
    def dist_fn(sl):
        d = torch.cdist(query[sl], px, compute_mode="donot_use_mm_for_euclid_dist")  # mm form loses ~0.01 px
        return d if weight is None else d * weight[None, :]
    idx, dist = _topk_chunked(dist_fn, query.shape[0], px.shape[0], k, px.device)
    return Neighbors(idx, dist)


# ----------------------------------------------------------------------------------------- k-d tree (CPU)
class _WeightedTree:
    """K smallest w_j · φ(‖q − x_j‖) over keys x [M, D] (float64) with weights w [M] > 0 (or None = all 1).

    `phi` maps key distances -> metric factor (inf where a point can never be a neighbour; None = identity) and
    `phi_inv` maps a bound on the factor to a bound on the key distance. Exact, in three steps:
    1. the `_NEAR_POINTS` smallest weights are checked by brute force, the rest is split into `_LAYERS` layers by
       weight, one tree each; the K nearest keys of every layer give an upper bound r on each ray's K-th value;
    2. in layer l every point better than r has key distance < φ⁻¹(r / min w_l); a ball count tells whether
       step 1 already saw all of them;
    3. where it did not, that layer is queried for exactly that many keys and merged.
    Layers keep the balls small: a pixel far from the object gets a wide ball only in the front layer.
    """

    def __init__(self, keys: np.ndarray, weight: np.ndarray | None, phi=None, phi_inv=None):
        from scipy.spatial import cKDTree  # heavy import kept local

        self.m = keys.shape[0]
        self.keys, self.weight, self.phi, self.phi_inv = keys, weight, phi, phi_inv
        ids = np.arange(self.m)
        near = np.empty(0, dtype=np.int64)
        self.layers: list[tuple[np.ndarray, float, object]] = []  # (point ids, min weight, tree)
        self.layer_of = np.full(self.m, -1, dtype=np.int64)
        if weight is not None and self.m > 2 * _NEAR_POINTS:
            order = np.argsort(weight, kind="stable")
            near, ids = order[:_NEAR_POINTS], order[_NEAR_POINTS:]
            for l, chunk in enumerate(np.array_split(ids, min(_LAYERS, ids.size))):
                self.layers.append((chunk, float(weight[chunk[0]]), cKDTree(keys[chunk], balanced_tree=False)))
                self.layer_of[chunk] = l
        elif weight is not None:
            near, ids = ids, ids[:0]  # tiny sets: brute force is all there is
        self.near, self.tree_ids = near, ids
        self.tree = cKDTree(keys[ids], balanced_tree=False) if ids.size and not self.layers else None

    def _exact(self, key_dist: np.ndarray, cand: np.ndarray) -> np.ndarray:
        """key_dist/cand [r, c] (cand indexes self.keys, -1 = none) -> metric [r, c] float64, inf = none."""
        with np.errstate(invalid="ignore", over="ignore"):
            f = key_dist if self.phi is None else self.phi(key_dist)
            if self.weight is not None:
                f = f * self.weight[np.maximum(cand, 0)]
        return np.where((cand >= 0) & ~np.isnan(f), f, np.inf)

    def _tree_query(self, tree, ids: np.ndarray, q: np.ndarray, k: int) -> tuple[np.ndarray, np.ndarray]:
        """k nearest keys of one tree: (key dist [r, k], cand [r, k] indexing self.keys, -1 = none)."""
        kd, ki = tree.query(q, k=k, workers=-1)
        kd, ki = kd.reshape(q.shape[0], k), ki.reshape(q.shape[0], k)
        cand = np.where(ki < ids.size, ids[np.minimum(ki, ids.size - 1)], -1)
        return kd, cand

    def query(self, q: np.ndarray, k: int) -> tuple[np.ndarray, np.ndarray]:
        """q [R, D] float64 -> (idx [R, k'] into keys, -1 = none; dist [R, k'] float64 ascending), k' = min(k, M)."""
        r = q.shape[0]
        kk = min(k, self.m)
        if kk == 0 or r == 0:
            return np.full((r, kk), -1, dtype=np.int64), np.full((r, kk), np.inf)
        parts = []  # (key dist, cand) blocks of step 1
        if self.layers:
            for ids, _, tree in self.layers:
                parts.append(self._tree_query(tree, ids, q, min(kk, ids.size)))
        elif self.tree is not None:
            parts.append(self._tree_query(self.tree, self.tree_ids, q, min(kk, self.tree_ids.size)))
        cand_k = np.concatenate([p[0] for p in parts], axis=1) if parts else np.empty((r, 0))
        cand_i = np.concatenate([p[1] for p in parts], axis=1) if parts else np.full((r, 0), -1, dtype=np.int64)
        cand_d = self._exact(cand_k, cand_i)
        if self.near.size:
            nk = np.linalg.norm(q[:, None, :] - self.keys[self.near][None, :, :], axis=-1)  # [R, m]
            near_i = np.broadcast_to(self.near, nk.shape)
            cand_i = np.concatenate([cand_i, near_i], axis=1)
            cand_k = np.concatenate([cand_k, nk], axis=1)
            cand_d = np.concatenate([cand_d, self._exact(nk, near_i)], axis=1)
        extras = []  # (rows, exact [rows, n], cand [rows, n]) of step 3, merged after the base top-k
        if self.layers:
            r_k = np.partition(cand_d, kk - 1, axis=1)[:, kk - 1]  # upper bound on the K-th best
            layer = np.where(cand_i >= 0, self.layer_of[np.maximum(cand_i, 0)], -1)
            for l, (ids, w_min, tree) in enumerate(self.layers):  # steps 2 and 3
                with np.errstate(divide="ignore", invalid="ignore", over="ignore"):
                    b = r_k / w_min if self.phi_inv is None else self.phi_inv(r_k / w_min)
                b = np.minimum(b * (1 + 1e-9) + 1e-12, 1e300)  # margin for rounding; inf -> huge
                seen = ((layer == l) & (cand_k <= b[:, None])).sum(axis=1)
                count = tree.query_ball_point(q, b, return_length=True, workers=-1)
                rows = np.nonzero(count > seen)[0]
                if rows.size == 0:
                    continue
                need = np.minimum(2 ** np.ceil(np.log2(count[rows])).astype(np.int64), ids.size)
                for n_q in np.unique(need):  # a few power-of-two buckets, not a loop over rays
                    sub = rows[need == n_q]
                    ek, ei = self._tree_query(tree, ids, q[sub], int(n_q))
                    extras.append((sub, self._exact(ek, ei), ei))
                drop = layer[rows] == l  # the layer query returns these again: avoid duplicates
                cand_d[rows] = np.where(drop, np.inf, cand_d[rows])
                cand_i[rows] = np.where(drop, -1, cand_i[rows])
        best_d, best_i = _smallest(cand_d, cand_i, kk)
        for rows, ed, ei in extras:
            best_d[rows], best_i[rows] = _smallest(np.concatenate([best_d[rows], ed], 1),
                                                   np.concatenate([best_i[rows], ei], 1), kk)
        srt = np.argsort(best_d, axis=1, kind="stable")
        best_d, best_i = np.take_along_axis(best_d, srt, 1), np.take_along_axis(best_i, srt, 1)
        return np.where(np.isfinite(best_d), best_i, -1), best_d


def _smallest(d: np.ndarray, i: np.ndarray, k: int) -> tuple[np.ndarray, np.ndarray]:
    """The k smallest entries per row (unsorted): d, i [r, c] -> [r, min(k, c)]."""
    if d.shape[1] <= k:
        return d.copy(), i.copy()
    part = np.argpartition(d, k - 1, axis=1)[:, :k]
    return np.take_along_axis(d, part, 1), np.take_along_axis(i, part, 1)


def _chord_to_sin(c: np.ndarray) -> np.ndarray:
    """Chord length between unit vectors -> sin of their angle; inf at or beyond 90° (point not in front)."""
    with np.errstate(invalid="ignore"):
        s = c * np.sqrt(np.clip(1.0 - 0.25 * c * c, 0.0, None))
    return np.where(c < math.sqrt(2.0), s, np.inf)


def _sin_to_chord(s: np.ndarray) -> np.ndarray:
    """Bound on sin(angle) -> bound on the chord, capped at the whole front hemisphere (chord √2)."""
    s = np.asarray(s, dtype=np.float64)
    with np.errstate(invalid="ignore"):
        c = 2.0 * np.sin(0.5 * np.arcsin(np.clip(s, 0.0, 1.0)))
    return np.where(s < 1.0, c, math.sqrt(2.0))


# -------------------------------------------------------------------------------------------- public indexes
class ScreenIndex:
    """Projected points of one camera, built once and queried many times (e.g. every chunk of a frame).

    points [N, 3]; c2w [4, 4] or [3, 4]; height, width in pixels; focal in pixels. depth_factor=False ranks by
    pixel distance (pixels), True by pixel distance × depth / focal (world units, ≈ perpendicular distance).
    """

    def __init__(self, points: torch.Tensor, c2w: torch.Tensor, height: int, width: int, focal: float,
                 depth_factor: bool = False, backend: str = "auto"):
        _check_matrix("points", points, 3)
        _check_camera(c2w, height, width, focal)
        self.device = points.device
        self.backend = _check_backend(backend, self.device)
        self.depth_factor = depth_factor
        p = points.detach().to(torch.float64)
        px, depth = project_points(p, c2w.detach().to(p.device, torch.float64), height, width, float(focal))
        keep = _present(p) & torch.isfinite(px).all(dim=1) & (depth > 0)
        keep &= (px[:, 0] >= -1) & (px[:, 0] <= width + 1) & (px[:, 1] >= -1) & (px[:, 1] <= height + 1)
        self.ids = torch.nonzero(keep).squeeze(1)  # [M] original point index of each candidate
        self.px = px[keep]  # [M, 2] (col, row)
        self.weight = depth[keep] / float(focal) if depth_factor else None  # [M]
        self._tree = None
        if self.backend == "kdtree":
            w = None if self.weight is None else self.weight.cpu().numpy()
            self._tree = _WeightedTree(self.px.cpu().numpy(), w)
        else:
            self._px32 = self.px.to(torch.float32)
            self._w32 = None if self.weight is None else self.weight.to(torch.float32)

    def query(self, query_px: torch.Tensor, k: int) -> Neighbors:
        """query_px [R, 2] (col, row) pixel coords (pixel (r, c) centre = (c + 0.5, r + 0.5)) -> Neighbors [R, K]."""
        _check_matrix("query_px", query_px, 2)
        k = _check_k(k)
        r = query_px.shape[0]
        if r == 0 or self.ids.numel() == 0:
            return _empty(r, k, self.device)
        ok = torch.isfinite(query_px).all(dim=1)
        if self._tree is not None:
            q = query_px.detach().to("cpu", torch.float64).numpy()
            q = np.where(ok.cpu().numpy()[:, None], q, 0.0)
            li, ld = self._tree.query(q, k)
            li, ld = torch.from_numpy(li), torch.from_numpy(ld)
        else:
            q = torch.where(ok[:, None], query_px.detach().to(self.device, torch.float32), 0.0)
            li, ld = _screen_brute(self._px32, self._w32, q, k)
        ids = self.ids.to(li.device)
        idx = torch.where(li >= 0, ids[li.clamp(min=0)], -1)
        ld = ld.masked_fill(~ok.to(ld.device)[:, None], math.inf)
        return _finalize(idx, ld, k, self.device)


class PerpendicularIndex:
    """Points seen from one shared ray origin, built once and queried with many ray directions.

    points [N, 3]; origin [3]. Points at the origin or with non-finite coordinates are absent.
    """

    def __init__(self, points: torch.Tensor, origin: torch.Tensor, backend: str = "auto"):
        _check_matrix("points", points, 3)
        origin = torch.as_tensor(origin)
        if origin.shape != (3,) or not bool(_present(origin[None]).all()):
            raise InputError(f"neighbour search: origin must be a finite [3] tensor, got {origin.tolist()}")
        self.device = points.device
        self.backend = _check_backend(backend, self.device)
        self.points = points.detach()
        self.origin = origin.detach().to(self.device)
        if self.backend == "kdtree":
            p = self.points.to("cpu", torch.float64)
            v = (torch.where(_present(p)[:, None], p, 0.0) - self.origin.to("cpu", torch.float64)).numpy()
            norm = np.linalg.norm(v, axis=1)
            keep = _present(p).numpy() & (norm > 0)
            self.ids = np.nonzero(keep)[0]
            keys = v[keep] / norm[keep, None]  # unit directions [M, 3]
            self._tree = _WeightedTree(keys, norm[keep], phi=_chord_to_sin, phi_inv=_sin_to_chord)
        else:
            self._ids_t = torch.nonzero(_present(self.points)).squeeze(1)

    def query(self, dirs: torch.Tensor, k: int) -> Neighbors:
        """dirs [R, 3] ray directions (normalised here; zero or non-finite = a ray with no neighbours)."""
        _check_matrix("dirs", dirs, 3)
        k = _check_k(k)
        r = dirs.shape[0]
        if self.backend == "kdtree":
            d = dirs.detach().to("cpu", torch.float64).numpy()
            with np.errstate(invalid="ignore", over="ignore", divide="ignore"):
                n = np.linalg.norm(d, axis=1)
                ok = np.isfinite(n) & (n > 0)
                d = np.where(ok[:, None], d / np.where(ok, n, 1.0)[:, None], 0.0)
            li, ld = self._tree.query(d, k)
            ld[~ok] = np.inf
            li, ld = torch.from_numpy(li), torch.from_numpy(ld)
            idx = torch.where(li >= 0, torch.from_numpy(self.ids)[li.clamp(min=0)], -1)
            return _finalize(idx, ld, k, self.device)
        d = dirs.detach().to(self.device, torch.float32)
        n = torch.linalg.vector_norm(d, dim=1)
        ok = torch.isfinite(n) & (n > 0)
        d = torch.where(ok[:, None], d / torch.where(ok, n, 1.0)[:, None], 0.0)
        pts = self.points[self._ids_t].to(torch.float32)
        if r == 0 or pts.shape[0] == 0:
            return _empty(r, k, self.device)
        o = self.origin.to(torch.float32).expand(r, 3)
        li, ld = _perpendicular_brute(pts, o, d, k)
        ld = ld.masked_fill(~ok[:, None], math.inf)
        idx = torch.where(li >= 0, self._ids_t[li.clamp(min=0)], -1)
        return _finalize(idx, ld, k, self.device)


# ------------------------------------------------------------------------------------------ public functions
def screen_knn(points: torch.Tensor, c2w: torch.Tensor, height: int, width: int, focal: float,
               query_px: torch.Tensor, k: int, depth_factor: bool = False, backend: str = "auto") -> Neighbors:
    """K nearest projected points to each query pixel.

    points [N, 3] world; c2w [4, 4]; query_px [R, 2] (col, row) pixel coords. Keeps points in front of the camera
    and inside the frame ± 1 px. Returns Neighbors(idx [R, K] int64 (-1 = none), dist [R, K] float32 (+inf =
    none)) sorted ascending; dist in pixels, or pixel distance × depth / focal with depth_factor=True.
    """
    return ScreenIndex(points, c2w, height, width, focal, depth_factor, backend).query(query_px, k)


def rays_knn_perpendicular(points: torch.Tensor, origins: torch.Tensor, dirs: torch.Tensor, k: int,
                           backend: str = "auto") -> Neighbors:
    """K nearest points to each ray by perpendicular distance, among points in front of its origin.

    points [N, 3]; origins [R, 3]; dirs [R, 3] (need not be unit). Returns Neighbors(idx [R, K] int64 (-1 = none),
    dist [R, K] float32 (+inf = none)) sorted ascending. Rays are grouped by origin: each group of at least
    _MIN_TREE_RAYS rays shares one k-d tree (fast path); smaller groups use brute force.
    """
    _check_matrix("points", points, 3)
    _check_matrix("origins", origins, 3)
    _check_matrix("dirs", dirs, 3)
    k = _check_k(k)
    if origins.shape[0] != dirs.shape[0]:
        raise InputError(f"neighbour search: origins {list(origins.shape)} and dirs {list(dirs.shape)} differ in R")
    device = points.device
    backend = _check_backend(backend, device)
    r = origins.shape[0]
    out = _empty(r, k, device)
    o_ok = _present(origins)
    if r == 0 or not bool(o_ok.any()):
        return out
    if backend == "torch":  # brute force handles per-ray origins directly
        sel = torch.nonzero(o_ok.to(device)).squeeze(1)
        res = _perpendicular_brute_any(points, origins[sel.to(origins.device)], dirs[sel.to(dirs.device)], k)
        out.idx[sel], out.dist[sel] = res.idx, res.dist
        return out
    uniq, group = torch.unique(origins.detach()[o_ok].to(device), dim=0, return_inverse=True)
    rays = torch.nonzero(o_ok.to(device)).squeeze(1)
    counts = torch.bincount(group, minlength=uniq.shape[0])
    small = torch.zeros(r, dtype=torch.bool, device=device)
    for g in range(uniq.shape[0]):  # one tree per camera origin (a handful per batch), not per point
        sel = rays[group == g]
        if backend == "kdtree" and int(counts[g]) < _MIN_TREE_RAYS:
            small[sel] = True
            continue
        res = PerpendicularIndex(points, uniq[g], backend).query(dirs[sel.to(dirs.device)], k)
        out.idx[sel], out.dist[sel] = res.idx, res.dist
    if bool(small.any()):
        sel = torch.nonzero(small).squeeze(1)
        res = _perpendicular_brute_any(points, origins[sel.to(origins.device)], dirs[sel.to(dirs.device)], k)
        out.idx[sel], out.dist[sel] = res.idx, res.dist
    return out


def _perpendicular_brute_any(points, origins, dirs, k) -> Neighbors:
    """Brute force with per-ray origins: points [N, 3], origins/dirs [R, 3] -> Neighbors [R, K]."""
    device = points.device
    ids = torch.nonzero(_present(points)).squeeze(1)
    pts = points.detach()[ids].to(torch.float32)
    d = dirs.detach().to(device, torch.float32)
    n = torch.linalg.vector_norm(d, dim=1)
    ok = torch.isfinite(n) & (n > 0)
    d = torch.where(ok[:, None], d / torch.where(ok, n, 1.0)[:, None], 0.0)
    if pts.shape[0] == 0:
        return _empty(origins.shape[0], k, device)
    li, ld = _perpendicular_brute(pts, origins.detach().to(device, torch.float32), d, k)
    ld = ld.masked_fill(~ok[:, None], math.inf)
    return _finalize(torch.where(li >= 0, ids[li.clamp(min=0)], -1), ld, k, device)


def knn_for_pixels(cfg: NeighborConfig, points: torch.Tensor, c2w: torch.Tensor, height: int, width: int,
                   focal: float, query_px: torch.Tensor) -> Neighbors:
    """The configured search for pixel rays of one camera: points [N, 3], query_px [R, 2] (col, row) ->
    Neighbors [R, K]. "perpendicular" uses the rays through those pixel positions (as cameras.pixel_rays)."""
    if cfg.method not in METHODS:
        raise InputError(f"neighbour search: method must be one of {METHODS}, got {cfg.method!r}")
    if cfg.method != "perpendicular":
        return screen_knn(points, c2w, height, width, focal, query_px, cfg.k,
                          depth_factor=cfg.method == "screen_depth", backend=cfg.backend)
    _check_camera(c2w, height, width, focal)
    _check_matrix("query_px", query_px, 2)
    m = c2w.detach().to(points.device, torch.float32)
    q = query_px.detach().to(points.device, torch.float32)
    d_cam = torch.stack([(q[:, 0] - 0.5 * width) / focal, -(q[:, 1] - 0.5 * height) / focal,
                         -torch.ones_like(q[:, 0])], dim=-1)
    dirs = d_cam @ m[:3, :3].T
    return rays_knn_perpendicular(points, m[:3, 3].expand_as(dirs), dirs, cfg.k, backend=cfg.backend)
