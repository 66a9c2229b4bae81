"""Neighbour search for rays: the K points each ray attends to (method.md §1), the hot path of PAPR.

Three metrics, all returning `Neighbors(idx [R, K] int64, dist [R, K] float32)`, sorted ascending, where a ray
with fewer than K candidates is padded with idx -1 and dist +inf (`.valid` [R, K] bool says which are real):

- "perpendicular" (paper / PAPR): ‖(p−o) − ((p−o)·d) d‖, only points in front of the origin ((p−o)·d > 0).
- "screen" (reference "knn_frustum"): project with the camera, keep points in front and inside the frame ± 1 px,
  K nearest in pixel space to each query pixel. dist in pixels.
- "screen_depth" (reference "d2r_z"): as "screen" but ranked by pixel distance × depth / focal, which is ≈ the
  perpendicular distance (world units).

Pixel radius cap (screen metrics): a point is a candidate for a query pixel only if its projected distance is
≤ max_radius_px. A ray whose nearest projected point is farther than a few pixels misses the object: the
attention's background slot takes it, and the renderer can skip shading it. "auto" (the default) sets the cap to
2 × the radius of a disc holding K points at the median projected density (at least 1.5 px), so an interior pixel
sees ≈ 4 K candidates; inf means no cap (the reference's behaviour).

Points with a non-finite coordinate are absent; so is any candidate whose distance is not finite.
Indices are not differentiable and `dist` is detached: gather the points with `idx` to get gradients.

Backends, all exact w.r.t. the definition above (tests compare each with a plain-torch brute force):
- "grid" (capped screen metrics, any device, pure torch): a pixel-space cell grid, see _CellGrid.
- "kdtree" (uncapped, CPU tensors): a scipy k-d tree over keys x_j (pixel coords, or unit directions from the
  shared origin) and an exact re-rank. Every metric here is w_j · φ(‖q − x_j‖) with a per-point weight w_j > 0
  (1, depth / focal, or |p − o|) and φ increasing, so once K candidates give an upper bound r on the K-th
  distance, every closer point has key distance < φ⁻¹(r / w_min): a ball query of that radius is complete. The
  few points with the smallest weights (a stray point next to the camera would blow the ball up) are checked by
  brute force instead.
- "torch": chunked brute force (with the cap applied), the reference the benchmark times the fast paths
  against (`python -m tools.bench.neighbors`); "auto" picks grid / kdtree / torch in that order of fit.
"""
from __future__ import annotations

import contextlib
import math
import numbers
from dataclasses import dataclass
from typing import NamedTuple

import numpy as np
import torch

from core.config import opt
from core.images.cameras import Intrinsics, focal_scale, project_points
from core.points import grid_kernel
from core.util.errors import InputError

METHODS = ("screen", "screen_depth", "perpendicular")
BACKENDS = ("auto", "compiled", "grid", "kdtree", "torch")
_CHUNK_ELEMS = 1 << 22  # rays × points per brute-force chunk (~16 MB of float32 distances)
_NEAR_POINTS = 32  # smallest-weight points handled by brute force in the weighted tree search
_LAYERS = 4  # weight layers of the weighted tree search (see _WeightedTree)
_MIN_TREE_RAYS = 64  # fewer rays than this from one origin: brute force beats building a tree
_MAX_COORD = 1e18  # beyond this a point has diverged; squared distances would overflow float32 on the torch path
_AUTO_FACTOR = 2.0  # "auto" cap = this × the radius holding K points at the median projected density ...
_AUTO_MIN_PX = 1.5  # ... and at least this many pixels
_DENSITY_CELL_POINTS = 16  # density cells hold this many points on average if spread over the whole frame
_GRID_BANDS = 4  # grid bands per cap radius: more bands hug the search disc tighter but cost more runs
_BINS_PER_SIDE = 4  # grid cells are this many times narrower than tall: runs overshoot the disc by < 1 cell
_MAX_BANDS = 1 << 16  # bounds the cell table for tiny caps ...
_MAX_CELLS = 1 << 21  # ... (2 × 16 MB of int64 prefix counts at most)
_STAGE1_FACTOR = 1.25  # stage-1 disc radius / radius holding K points at the query's density (pixel distance)
_STAGE1_MIN_COUNT = 2.5  # queries with at most this many × K points around them skip stage 1
_STAGE1_FACTOR_WEIGHTED = 1.5  # the same for depth-weighted ranks: far layers (e.g. a back side) fill the disc
_OUTSIDE = 1e30  # rank penalty per pixel beyond the search radius (finite: 0 × inf would be nan)
_GROUP_MIN_WIDTH = 16  # narrower query groups are merged: per-group overhead beats padding there
_GRID_BUDGET = 1 << 15  # candidate slots per table chunk: the working set stays in cache, one dense spot in memory


@dataclass
class NeighborConfig:
    """Neighbour search: which metric ranks the K points a ray attends to."""

    method: str = opt("screen_depth", "neighbour metric: screen | screen_depth | perpendicular", choices=METHODS)
    k: int = opt(20, "neighbours per ray K")
    max_radius_px: float = opt(0.0, "screen metrics: a point is a candidate only within this many pixels of the "
                                    "ray's pixel (rays with none hit the background); 0 = auto from the projected "
                                    "point density, -1 = no cap")
    backend: str = opt("auto", "auto = compiled grid (numba, CPU) or torch pixel grid for capped screen metrics, "
                               "else k-d tree for CPU tensors and chunked torch brute force elsewhere",
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


def _check_backend(backend: str, device: torch.device, capped: bool = False) -> str:
    """Resolve "auto": for capped screen searches the compiled grid on CPU (when numba is installed) else the torch
    grid; uncapped, the k-d tree on CPU and brute force elsewhere."""
    if backend not in BACKENDS:
        raise InputError(f"neighbour search: backend must be one of {BACKENDS}, got {backend!r}")
    cpu = device.type == "cpu"
    if backend == "auto":
        if capped:
            return "compiled" if cpu and grid_kernel.available() else "grid"
        return "kdtree" if cpu else "torch"
    if backend == "compiled":
        if not capped:
            raise InputError("neighbour search: backend 'compiled' needs a finite max_radius_px (screen metrics "
                             "only); use backend 'auto', 'kdtree' or 'torch'")
        if not cpu:
            raise InputError(f"neighbour search: backend 'compiled' runs on CPU tensors, got {device}; "
                             "use backend 'grid' (any device) or 'auto'")
        if not grid_kernel.available():
            raise InputError("neighbour search: backend 'compiled' needs numba (pip install numba); "
                             "use backend 'grid' or 'auto'")
    if backend == "grid" and not capped:
        raise InputError("neighbour search: backend 'grid' needs a finite max_radius_px (screen metrics only); "
                         "use backend 'auto', 'kdtree' or 'torch'")
    if backend == "kdtree" and capped:
        raise InputError("neighbour search: backend 'kdtree' searches without a radius cap; set max_radius_px to "
                         "-1 (no cap) or use backend 'auto' / 'grid'")
    return backend


def _check_radius(value) -> float | str:
    """max_radius_px -> "auto", a positive float, or inf (no cap). 0 also means auto and a negative number no cap
    (the config spelling: JSON has no infinity)."""
    if isinstance(value, str):
        if value != "auto":
            raise InputError(f"neighbour search: max_radius_px must be 'auto' or a number of pixels, got {value!r}")
        return value
    if isinstance(value, bool) or not isinstance(value, numbers.Real) or math.isnan(value):
        raise InputError(f"neighbour search: max_radius_px must be 'auto' or a number of pixels, got {value!r}")
    if value == 0:
        return "auto"
    return math.inf if value < 0 else float(value)


def _check_camera(c2w, height, width, focal) -> None:
    if not isinstance(c2w, torch.Tensor) or tuple(c2w.shape) not in ((4, 4), (3, 4)):
        shape = list(c2w.shape) if isinstance(c2w, torch.Tensor) else type(c2w).__name__
        raise InputError(f"neighbour search: c2w must be a [4, 4] or [3, 4] tensor, got {shape}")
    if not bool(torch.isfinite(c2w).all()):
        raise InputError("neighbour search: c2w has non-finite entries")
    for name, v in (("height", height), ("width", width)):
        if isinstance(v, bool) or not isinstance(v, (int, np.integer)) or v < 1:
            raise InputError(f"neighbour search: {name} must be a positive integer, got {v!r}")
    if isinstance(focal, Intrinsics):
        return  # validated when it was made: finite, positive focal lengths
    if isinstance(focal, bool) or not (isinstance(focal, numbers.Real) and math.isfinite(focal) and focal > 0):
        raise InputError(f"neighbour search: focal must be a finite positive number of pixels (or Intrinsics), "
                         f"got {focal!r}")


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


def _screen_brute(px: torch.Tensor, weight: torch.Tensor | None, query: torch.Tensor, k: int,
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


# --------------------------------------------------------------------------------- pixel-space grid (any device)
def _median_density(px: torch.Tensor, height: int, width: int) -> float:
    """Projected points per square pixel where the object is: px [M, 2] (col, row) -> the median over points of
    the density of the grid cell holding the point. Weighting by points, not cells, lets interior cells outvote
    the partial cells along the silhouette. Cells are sized to hold ~_DENSITY_CELL_POINTS points: first at the
    density of the whole frame, then once more at the density this first pass found (objects smaller than the
    frame)."""
    m = px.shape[0]
    if m == 0:
        return 0.0
    density = m / ((width + 2.0) * (height + 2.0))  # candidates lie inside the frame ± 1 px
    for _ in range(2):
        side = min(math.sqrt(_DENSITY_CELL_POINTS / density), width + 2.0, height + 2.0)
        cols = int((width + 2.0) // side) + 1
        cell = ((px[:, 1] + 1.0) // side).long() * cols + ((px[:, 0] + 1.0) // side).long()
        counts = torch.bincount(cell.clamp(min=0))
        density = float(counts[cell].to(torch.float64).median()) / (side * side)
    return density


def auto_radius_px(density: float, k: int) -> float:
    """The "auto" pixel radius cap: _AUTO_FACTOR × the radius of a disc holding k points at `density` points per
    square pixel, at least _AUTO_MIN_PX. An interior pixel then sees ≈ _AUTO_FACTOR² · k candidates."""
    if not density > 0:
        return _AUTO_MIN_PX
    return max(_AUTO_MIN_PX, _AUTO_FACTOR * math.sqrt(k / (math.pi * density)))


class _CellGrid:
    """Candidates within `cap` pixels of a query, exact, in pure torch (CPU or GPU).

    Cells are `side` = cap / _GRID_BANDS tall and side / _BINS_PER_SIDE wide; points are sorted by cell, row-major,
    and an exclusive prefix count per cell turns "the points of one band between two columns" into one contiguous
    run, found by two table lookups. A disc of radius ρ around a query touches ≤ ρ / side + 2 bands, each with
    the disc's column half-width in that band, so its runs cover little more than the disc. Runs are laid side by
    side in a padded [queries, width] table, queries grouped by candidate count (narrow tables, and one dense spot
    costs its own queries time, not everyone's memory), then an exact distance test and a top-k.

    Two stages keep the tables narrow. Stage 1 searches a disc expected to hold ≈ _STAGE1_FACTOR² · K points at
    the query's density; its answer is final where it proves that nothing outside the disc does better: the K-th
    value ≤ ρ₁ · (smallest weight near the query; 1 for plain pixel distance). Otherwise stage 2 searches the disc
    of radius min(cap, K-th value / smallest weight), which that bound shows complete.
    """

    def __init__(self, px: torch.Tensor, weight: torch.Tensor | None, ids: torch.Tensor, cap: float, density: float,
                 height: int, width: int):
        """px [M, 2] float64 projected points, weight [M] or None, ids [M] int64 what query() returns for each."""
        self.cap, self.density = float(cap), float(density)
        self.side = max(self.cap / _GRID_BANDS, (height + 2.0) / _MAX_BANDS)
        self.bands = int((height + 2.0) // self.side) + 1
        self.bin = self.side / _BINS_PER_SIDE
        self.bins = int((width + 2.0) // self.bin) + 2
        if self.bands * self.bins > _MAX_CELLS:  # wide frame with a tiny cap: coarser columns
            self.bins = max(2, _MAX_CELLS // self.bands)
            self.bin = (width + 2.0) / (self.bins - 2)
        self.slack = 1e-5 * (self.cap + height + width + 2.0)  # ≫ float32 rounding of pixel coordinates
        band = ((px[:, 1] + 1.0) // self.side).clamp(0, self.bands - 1).long()
        col = ((px[:, 0] + 1.0) // self.bin).clamp(0, self.bins - 1).long()
        cell, order = torch.sort(band * self.bins + col)
        counts = torch.bincount(cell, minlength=self.bands * self.bins).view(self.bands, self.bins)
        self.table = torch.nn.functional.pad(counts.cumsum(0).cumsum(1), (1, 0, 1, 0))  # [bands+1, bins+1] summed area
        # run lookups use the cell grid framed by empty bands and columns, so that runs of a disc reaching past
        # the frame need no masks: indices are clamped into the empty frame
        self.pad_bands = 3 * _GRID_BANDS + 4
        framed = torch.nn.functional.pad(counts, (1, 1, self.pad_bands, self.pad_bands))
        self.cols = framed.shape[1]
        self.prefix = torch.nn.functional.pad(framed.view(-1).cumsum(0), (1, 0))  # [cells + 1] points before a cell
        self.m = m = order.numel()
        pad = (0, m)  # slots M.. are sentinels at infinity: a query's table is padded with them
        self.order = torch.nn.functional.pad(ids[order], pad, value=-1)  # [2M] sorted slot -> id, -1 = sentinel
        self.x = torch.nn.functional.pad(px[order, 0].to(torch.float32), pad, value=math.inf)  # [2M] sorted
        self.y = torch.nn.functional.pad(px[order, 1].to(torch.float32), pad, value=math.inf)
        self.weight = None if weight is None else torch.nn.functional.pad(weight[order].to(torch.float32), pad,
                                                                          value=1.0)
        self.wmin = None  # [bands, coarse cols] smallest weight within the cap of any query in that coarse cell
        if weight is not None:
            per = _BINS_PER_SIDE
            coarse_cols = (self.bins + per - 1) // per
            wcell = torch.full((self.bands * coarse_cols,), math.inf, dtype=torch.float32, device=px.device)
            wcell.scatter_reduce_(0, band * coarse_cols + col // per, weight.to(torch.float32), "amin")
            reach = int(math.ceil(self.cap / min(self.side, self.bin * per))) + 1  # cells a cap disc spans each way
            self.wmin = -torch.nn.functional.max_pool2d(-wcell.view(1, self.bands, coarse_cols), 2 * reach + 1,
                                                         stride=1, padding=reach)[0]

    def _square_count(self, q: torch.Tensor) -> torch.Tensor:
        """q [R, 2] float64 finite -> [R] int64: points in the cells meeting the square of half-side cap around q,
        a superset of the cap disc (0 = certainly no candidate)."""
        lo = ((q + (1.0 - self.cap)) / torch.tensor([self.bin, self.side], device=q.device, dtype=q.dtype)).floor()
        hi = ((q + (1.0 + self.cap)) / torch.tensor([self.bin, self.side], device=q.device, dtype=q.dtype)).floor()
        c0 = lo[:, 0].clamp(0, self.bins).long()
        c1 = (hi[:, 0] + 1).clamp(0, self.bins).long().maximum(c0)
        b0 = lo[:, 1].clamp(0, self.bands).long()
        b1 = (hi[:, 1] + 1).clamp(0, self.bands).long().maximum(b0)
        t = self.table
        return t[b1, c1] - t[b0, c1] - t[b1, c0] + t[b0, c0]

    def _runs(self, q: torch.Tensor, radius: torch.Tensor):
        """q [R, 2] float32 finite, radius [R] float32 (≤ cap) -> start, length [R, S] int64: one run per band,
        a superset of the points within `radius` of the query (inside the frame ± 1 px)."""
        side, rad = self.side, radius[:, None]
        slack = self.slack  # rounding margin: runs may hold a few extra points, the exact test drops them
        y1 = q[:, 1:2] + 1.0
        first = torch.floor((y1 - rad - slack) / side)  # [R, 1]
        span = int(math.ceil(2.0 * float(radius.max()) / side)) + 2 if radius.numel() else 1  # bands a disc meets
        band = first + torch.arange(span, device=q.device, dtype=q.dtype)  # [R, S]
        below = band * side - y1  # band covers shifted rows [band·side, band·side + side): query to its lower edge
        dy = torch.maximum(below, -side - below).clamp_(min=0.0)
        half2 = (rad + slack) ** 2 - dy * dy
        half = half2.clamp(min=0.0).sqrt_().add_(slack)
        x1 = q[:, 0:1] * (1.0 / self.bin) + (1.0 / self.bin + 1.0)  # shifted column in bins, + 1 for the frame
        hb = half * (1.0 / self.bin)
        c_lo = (x1 - hb).floor_().clamp_(0, self.cols - 1).long()
        c_hi = (x1 + hb).floor_().clamp_(0, self.cols - 1).long()
        base = (band + self.pad_bands).clamp_(0, self.bands + 2 * self.pad_bands - 1).long() * self.cols
        start = self.prefix.take(base + c_lo)
        return start, (self.prefix.take(base + c_hi + 1) - start) * (half2 >= 0)

    def _select(self, q: torch.Tensor, radius: torch.Tensor, k: int):
        """K best among the points within `radius` pixels: q [r, 2] float32, radius [r] float32 -> (slot [r, k]
        into the sorted points, value [r, k] float32 ascending, inf = none)."""
        r = q.shape[0]
        start, length = self._runs(q, radius)
        count_s, srt = torch.sort(length.sum(dim=1))  # grouped by candidate count; results in this order
        start, length = start.index_select(0, srt), length.index_select(0, srt)
        q32 = q.index_select(0, srt)
        rad32 = radius.index_select(0, srt)[:, None]
        slot = torch.zeros((r, k), dtype=torch.int64, device=q.device)
        value = torch.full((r, k), math.inf, dtype=torch.float32, device=q.device)
        for a, b, wid in _groups(count_s, _GRID_BUDGET):  # each group writes its rows a..b
            n = b - a
            pos = _run_positions(start[a:b], length[a:b], wid, self.m).view(-1)  # [n * wid], padding -> sentinels
            qs, rs = q32[a:b], rad32[a:b]
            dx = self.x.index_select(0, pos).view(n, wid).sub_(qs[:, 0:1])
            dy = self.y.index_select(0, pos).view(n, wid).sub_(qs[:, 1:2])
            d = dx.mul_(dx).add_(dy.mul_(dy)).sqrt_()  # pixel distance [n, wid], inf for sentinels
            v = d.sub(rs).clamp_(min=0.0).mul_(_OUTSIDE)  # beyond the radius: ranks after every candidate
            v.add_(d if self.weight is None else self.weight.index_select(0, pos).view(n, wid).mul_(d))
            kk = min(k, wid)
            vals, col = torch.topk(v, kk, dim=1, largest=False, sorted=True)
            inside = torch.gather(d, 1, col) <= rs  # (boolean masks on the whole table are slow on CPU)
            slot[a:b, :kk] = torch.gather(pos.view(n, wid), 1, col)
            value[a:b, :kk] = torch.where(inside, vals, math.inf)
        inverse = torch.empty_like(srt)
        inverse[srt] = torch.arange(r, device=q.device)
        return slot.index_select(0, inverse), value.index_select(0, inverse)

    def query(self, q: torch.Tensor, k: int) -> tuple[torch.Tensor, torch.Tensor]:
        """q [R, 2] float64 (non-finite rows = no neighbours) -> (idx [R, k] of the ids given to __init__, -1
        = none; dist [R, k] float32 ascending, inf = none)."""
        r = q.shape[0]
        idx = torch.full((r, k), -1, dtype=torch.int64, device=q.device)
        dist = torch.full((r, k), math.inf, dtype=torch.float32, device=q.device)
        q = torch.where(torch.isfinite(q).all(dim=1, keepdim=True), q, -1e9)  # far outside: no runs
        count = self._square_count(q)
        rows = torch.nonzero(count > 0).squeeze(1)
        if rows.numel() == 0:
            return idx, dist
        q = q.index_select(0, rows).to(torch.float32)  # within a cap of the frame: float32 is plenty
        count = count.index_select(0, rows).to(torch.float32)
        cap = torch.full_like(count, self.cap)
        # stage 1: a disc holding ≈ factor² · k points at the density around the query
        density = count / (2.0 * self.cap + self.side) ** 2
        factor = _STAGE1_FACTOR if self.weight is None else _STAGE1_FACTOR_WEIGHTED
        rad1 = torch.minimum(density.reciprocal_().mul_(k / math.pi).sqrt_().mul_(factor), cap)
        rad1 = torch.where(count <= _STAGE1_MIN_COUNT * k, cap, rad1)  # few candidates: one stage is cheaper
        slot, value = self._select(q, rad1, k)
        wmin = torch.ones_like(rad1)
        if self.wmin is not None:
            band = ((q[:, 1] + 1.0) // self.side).clamp(0, self.wmin.shape[0] - 1).long()
            col = ((q[:, 0] + 1.0) // (self.bin * _BINS_PER_SIDE)).clamp(0, self.wmin.shape[1] - 1).long()
            wmin = self.wmin[band, col]
        kth = value[:, -1]
        # outside the disc every value is ≥ rad1 · wmin (rounding is monotone): where the K-th is within, it's final
        done = torch.isfinite(kth) & (kth <= rad1 * wmin)
        done |= rad1 >= cap  # stage 1 already searched the whole cap disc
        redo = torch.nonzero(~done).squeeze(1)
        if redo.numel():  # stage 2: the disc that the stage-1 K-th value shows complete
            bound = kth[redo] / wmin[redo] * (1 + 1e-5)
            rad2 = torch.where(torch.isfinite(bound), torch.minimum(bound, cap[redo]), cap[redo])
            slot[redo], value[redo] = self._select(q[redo], rad2, k)
        idx[rows] = torch.where(torch.isfinite(value), self.order[slot], -1)  # sentinels are never finite
        dist[rows] = value
        return idx, dist


@contextlib.contextmanager
def _one_cpu_thread(device: torch.device):
    """Run torch CPU ops single-threaded inside: the grid search is hundreds of small ops, and on a shared CPU
    each multi-threaded op can wait a scheduler tick for its second thread (measured here under load: a 128²
    frame took 0.2–2 s with 2 threads, 50 ms with 1). Python threads over the groups did not help either."""
    if device.type != "cpu":
        yield
        return
    threads = torch.get_num_threads()
    torch.set_num_threads(1)
    try:
        yield
    finally:
        torch.set_num_threads(threads)


def _groups(count: torch.Tensor, budget: int):
    """count [R] ascending candidates per query -> (a, b, width) slices, width = count[b − 1] > 0, whose widths
    differ by at most ~50 % (padding vs. per-slice overhead) and whose padded tables (b − a) × width stay within
    budget."""
    c = count.cpu()
    n = c.shape[0]
    a = int(torch.searchsorted(c, 1))  # skip queries without candidates
    while a < n:
        limit = max(int(c[a]) * 3 // 2, _GROUP_MIN_WIDTH)
        b = int(torch.searchsorted(c, limit, right=True))
        b = max(a + 1, min(b, a + budget // max(int(c[b - 1]), 1)))
        yield a, b, int(c[b - 1])
        a = b


def _run_positions(start: torch.Tensor, length: torch.Tensor, width: int, tail: int) -> torch.Tensor:
    """Runs laid side by side: start/length [r, S] -> pos [r, width] with pos[i, t] = start[i, j] + (t − first
    slot of run j) for the run j holding slot t, and tail + (t − run total) past the last run. Built as a
    cumulative sum of jumps at the run boundaries (empty runs telescope away)."""
    r = start.shape[0]
    start = torch.cat([start, start.new_full((r, 1), tail)], dim=1)
    length = torch.cat([length, length.new_full((r, 1), width)], dim=1)
    first = torch.cumsum(length, dim=1) - length  # [r, S] first slot of each run
    offset = start - first  # pos = t + offset inside run j
    jump = offset - torch.nn.functional.pad(offset[:, :-1], (1, 0))
    acc = torch.zeros((r, width + 1), dtype=torch.int64, device=start.device)
    acc.scatter_add_(1, first.clamp(max=width), jump)
    return torch.cumsum(acc[:, :width], dim=1) + torch.arange(width, device=start.device)


# -------------------------------------------------------------------------------------------- public indexes
class ScreenIndex:
    """Projected points of one camera, built once and queried many times (e.g. every chunk of a frame).

    points [N, 3]; c2w [4, 4] or [3, 4]; height, width in pixels; focal in pixels or Intrinsics. depth_factor=False
    ranks by pixel distance (pixels), True by pixel distance × depth / focal (world units, ≈ perpendicular
    distance; with Intrinsics the focal is sqrt(fx * fy)).
    max_radius_px: candidates lie within this many pixels of the query; "auto" (or 0) derives it from the
    projected density and K (`radius_px(k)`), inf (or a negative number) means no cap.
    """

    def __init__(self, points: torch.Tensor, c2w: torch.Tensor, height: int, width: int, focal,
                 depth_factor: bool = False, backend: str = "auto", max_radius_px: float | str = "auto"):
        _check_matrix("points", points, 3)
        _check_camera(c2w, height, width, focal)
        self.radius = _check_radius(max_radius_px)
        self.device = points.device
        self.backend = _check_backend(backend, self.device, capped=self.radius != math.inf)
        self.depth_factor = depth_factor
        self.height, self.width = int(height), int(width)
        p = points.detach().to(torch.float64)
        cam = focal if isinstance(focal, Intrinsics) else float(focal)
        px, depth = project_points(p, c2w.detach().to(p.device, torch.float64), height, width, cam)
        keep = _present(p) & torch.isfinite(px).all(dim=1) & (depth > 0)
        keep &= (px[:, 0] >= -1) & (px[:, 0] <= width + 1) & (px[:, 1] >= -1) & (px[:, 1] <= height + 1)
        self.ids = torch.nonzero(keep).squeeze(1)  # [M] original point index of each candidate
        self.px = px[keep]  # [M, 2] (col, row)
        self.weight = depth[keep] / float(focal_scale(cam)) if depth_factor else None  # [M]
        self._density: float | None = None
        self._grids: dict[float, _CellGrid] = {}  # one per resolved cap (the auto cap depends on K)
        self._tree = None
        self._compiled: dict[float, grid_kernel.CompiledGrid] = {}
        if self.backend == "kdtree":
            w = None if self.weight is None else self.weight.cpu().numpy()
            self._tree = _WeightedTree(self.px.cpu().numpy(), w)
        elif self.backend == "torch":
            self._px32 = self.px.to(torch.float32)
            self._w32 = None if self.weight is None else self.weight.to(torch.float32)

    def radius_px(self, k: int) -> float:
        """The pixel radius cap a query with K = k uses (inf = no cap)."""
        if self.radius != "auto":
            return self.radius
        return auto_radius_px(self._median_density(), _check_k(k))

    def _median_density(self) -> float:
        if self._density is None:
            self._density = _median_density(self.px, self.height, self.width)
        return self._density

    def query(self, query_px: torch.Tensor, k: int) -> Neighbors:
        """query_px [R, 2] (col, row) pixel coords (pixel (r, c) centre = (c + 0.5, r + 0.5)) -> Neighbors [R, K]."""
        _check_matrix("query_px", query_px, 2)
        k = _check_k(k)
        r = query_px.shape[0]
        if r == 0 or self.ids.numel() == 0:
            return _empty(r, k, self.device)
        if self.backend == "grid":
            with _one_cpu_thread(self.device):
                cap = self.radius_px(k)
                if cap not in self._grids:
                    self._grids[cap] = _CellGrid(self.px, self.weight, self.ids, cap, self._median_density(),
                                                 self.height, self.width)
                return Neighbors(*self._grids[cap].query(query_px.detach().to(self.device, torch.float64), k))
        if self.backend == "compiled":  # already final: ids, -1 / inf padding, ascending, non-finite rows empty
            cap = self.radius_px(k)
            if cap not in self._compiled:
                w = None if self.weight is None else self.weight.numpy()
                self._compiled[cap] = grid_kernel.CompiledGrid(self.px.numpy(), w, self.ids.numpy(), cap,
                                                               self.height, self.width)
            idx, dist = self._compiled[cap].query(query_px.detach().to(torch.float64).numpy(), k)
            return Neighbors(torch.from_numpy(idx), torch.from_numpy(dist))
        ok = torch.isfinite(query_px).all(dim=1)
        if self._tree is not None:
            q = query_px.detach().to("cpu", torch.float64).numpy()
            q = np.where(ok.cpu().numpy()[:, None], q, 0.0)
            li, ld = self._tree.query(q, k)
            li, ld = torch.from_numpy(li), torch.from_numpy(ld)
        else:
            q = torch.where(ok[:, None], query_px.detach().to(self.device, torch.float32), 0.0)
            li, ld = _screen_brute(self._px32, self._w32, q, k, self.radius_px(k))
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
               query_px: torch.Tensor, k: int, depth_factor: bool = False, backend: str = "auto",
               max_radius_px: float | str = "auto") -> Neighbors:
    """K nearest projected points to each query pixel, among those within max_radius_px pixels of it.

    points [N, 3] world; c2w [4, 4]; query_px [R, 2] (col, row) pixel coords. Keeps points in front of the camera
    and inside the frame ± 1 px. max_radius_px: "auto" (or 0) = from the projected density (see
    ScreenIndex.radius_px), a number of pixels, or inf (or < 0) = no cap. Returns Neighbors(idx [R, K] int64
    (-1 = none), dist [R, K] float32 (+inf = none)) sorted ascending; dist in pixels, or pixel distance × depth /
    focal with depth_factor=True.
    """
    return ScreenIndex(points, c2w, height, width, focal, depth_factor, backend, max_radius_px).query(query_px, k)


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
                          depth_factor=cfg.method == "screen_depth", backend=cfg.backend,
                          max_radius_px=cfg.max_radius_px)
    _check_camera(c2w, height, width, focal)
    _check_matrix("query_px", query_px, 2)
    m = c2w.detach().to(points.device, torch.float32)
    q = query_px.detach().to(points.device, torch.float32)
    fx, fy, cx, cy = (focal, focal, 0.5 * width, 0.5 * height) if not isinstance(focal, Intrinsics) else \
        (focal.fx, focal.fy, focal.cx, focal.cy)
    d_cam = torch.stack([(q[:, 0] - cx) / fx, -(q[:, 1] - cy) / fy, -torch.ones_like(q[:, 0])], dim=-1)
    dirs = d_cam @ m[:3, :3].T
    return rays_knn_perpendicular(points, m[:3, 3].expand_as(dirs), dirs, cfg.k, backend=cfg.backend)
