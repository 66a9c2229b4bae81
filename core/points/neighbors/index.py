"""The searches: a camera's projected points (`ScreenIndex`) or one origin's points (`PerpendicularIndex`), built
once and queried many times, and the one-call forms `screen_knn` / `rays_knn_perpendicular`. They check the inputs,
pick a backend ("auto": compiled grid, torch grid, k-d tree or brute force, in that order of fit) and map the
backend's answer back to the caller's point indices."""
from __future__ import annotations

import math

import numpy as np
import torch

from core.images.cameras import Intrinsics, focal_scale, project_points
from core.points.neighbors import compiled
from core.points.neighbors.base import (BACKENDS, Neighbors, check_camera, check_k, check_matrix, empty, finalize,
                                        present)
from core.points.neighbors.brute import perpendicular_brute, perpendicular_brute_any, screen_brute
from core.points.neighbors.grid import CellGrid, one_cpu_thread
from core.points.neighbors.kdtree import WeightedTree, chord_to_sin, sin_to_chord
from core.points.neighbors.radius import auto_radius_px, check_radius, median_density
from core.util.errors import InputError

_MIN_TREE_RAYS = 64  # fewer rays than this from one origin: brute force beats building a tree


def check_backend(backend: str, device: torch.device, capped: bool = False) -> str:
    """Resolve "auto": for capped screen searches the compiled grid on CPU (when numba is installed) else the torch
    grid; uncapped, the k-d tree on CPU and brute force elsewhere."""
    if backend not in BACKENDS:
        raise InputError(f"neighbour search: backend must be one of {BACKENDS}, got {backend!r}")
    cpu = device.type == "cpu"
    if backend == "auto":
        if capped:
            return "compiled" if cpu and compiled.available() else "grid"
        return "kdtree" if cpu else "torch"
    if backend == "compiled":
        if not capped:
            raise InputError("neighbour search: backend 'compiled' needs a finite max_radius_px (screen metrics "
                             "only); use backend 'auto', 'kdtree' or 'torch'")
        if not cpu:
            raise InputError(f"neighbour search: backend 'compiled' runs on CPU tensors, got {device}; "
                             "use backend 'grid' (any device) or 'auto'")
        if not compiled.available():
            raise InputError("neighbour search: backend 'compiled' needs numba (pip install numba); "
                             "use backend 'grid' or 'auto'")
    if backend == "grid" and not capped:
        raise InputError("neighbour search: backend 'grid' needs a finite max_radius_px (screen metrics only); "
                         "use backend 'auto', 'kdtree' or 'torch'")
    if backend == "kdtree" and capped:
        raise InputError("neighbour search: backend 'kdtree' searches without a radius cap; set max_radius_px to "
                         "-1 (no cap) or use backend 'auto' / 'grid'")
    return backend


def surrounded(offsets: torch.Tensor, valid: torch.Tensor) -> torch.Tensor:
    """offsets [R, M, 2] from each query to candidate points, valid [R, M] bool (which count) -> [R] bool: the
    candidates surround the query — of the 8 45° sectors around it (counter-clockwise from +x), no 3 consecutive
    ones (around the turn) lack a candidate (the compiled kernel's rule, `compiled._ringed`). A candidate at the
    query itself is in no sector."""
    sector = torch.floor(torch.atan2(offsets[..., 1], offsets[..., 0]) / (0.25 * math.pi)).long() % 8
    use = valid & (offsets != 0).any(dim=-1) & torch.isfinite(offsets).all(dim=-1)
    occupied = torch.zeros(offsets.shape[0], 8, dtype=torch.bool, device=offsets.device)
    for t in range(8):
        occupied[:, t] = (use & (sector == t)).any(dim=1)
    gap = ~occupied & ~occupied.roll(-1, dims=1) & ~occupied.roll(-2, dims=1)
    return ~gap.any(dim=1)


class ScreenIndex:
    """Projected points of one camera, built once and queried many times (e.g. every chunk of a frame).

    points [N, 3]; c2w [4, 4] or [3, 4]; height, width in pixels; focal in pixels or Intrinsics. depth_factor=False
    ranks by pixel distance (pixels), True by pixel distance × depth / focal (world units, ≈ perpendicular
    distance; with Intrinsics the focal is sqrt(fx * fy)).
    max_radius_px: candidates lie within this many pixels of the query; "auto" (or 0) derives it from the
    projected density and K (`radius_px(k)`), inf (or a negative number) means no cap.
    reach [N] (>= 1) or None: point n is a candidate within the cap × reach[n] pixels (a point whose surroundings a
    deformation stretched reaches farther). The compiled backend applies it per point, with cells still sized by
    the cap; the others, which have one cap per index, use the cap × the largest reach.
    reach_gate: with reach, a query that has no point within reach_gate × the cap gets no neighbours (1: the reach
    adds far points only to queries the plain cap already gives one; the empty queries around the object stop
    there instead of walking the largest reach); 0 (or False) = no gate. reach_surround (with a gate): such a query
    keeps its K neighbours all the same when its candidates (the points whose reach covers it) surround it
    (`surrounded`: no 3 consecutive of 8 45° sectors around it lack one) — a hole inside the object's screen
    outline, not a ray beside it (such a query then walks its whole reach). reach_gate_own: each point gates at
    reach_gate × the cap but at most its own reach × the cap (a wider gate only where the points were pulled
    that far apart). reach_between (reach_gate > 1): beyond the plain cap, the gate opens only for two points
    within it whose directions from the query are more than 120° apart (the query lies between the points of a
    sparse surface, not beside an outline). reach_perspective (> 1, with reach): a candidate whose reach exceeds 1
    and that lies nearer the camera than the median candidate reaches farther by the ratio of that median depth to
    its own, at most this factor (perspective spreads a near stretched part's points farther apart on the screen
    than the frame's one cap, set from the median density, allows); its gate and its plain cap for
    `reach_between` widen by the same ratio. 0 (or <= 1) = off.
    """

    def __init__(self, points: torch.Tensor, c2w: torch.Tensor, height: int, width: int, focal,
                 depth_factor: bool = False, backend: str = "auto", max_radius_px: float | str = "auto",
                 reach: torch.Tensor | None = None, reach_gate: float = 0.0, reach_surround: bool = False,
                 reach_gate_own: bool = False, reach_between: bool = False, reach_perspective: float = 0.0):
        check_matrix("points", points, 3)
        check_camera(c2w, height, width, focal)
        self.radius = check_radius(max_radius_px)
        self.device = points.device
        self.backend = check_backend(backend, self.device, capped=self.radius != math.inf)
        self.depth_factor = depth_factor
        self.height, self.width = int(height), int(width)
        p = points.detach().to(torch.float64)
        cam = focal if isinstance(focal, Intrinsics) else float(focal)
        px, depth = project_points(p, c2w.detach().to(p.device, torch.float64), height, width, cam)
        keep = present(p) & torch.isfinite(px).all(dim=1) & (depth > 0)
        keep &= (px[:, 0] >= -1) & (px[:, 0] <= width + 1) & (px[:, 1] >= -1) & (px[:, 1] <= height + 1)
        self.ids = torch.nonzero(keep).squeeze(1)  # [M] original point index of each candidate
        self.px = px[keep]  # [M, 2] (col, row)
        self.reach = None  # [M] float64 >= 1: each candidate's cap factor (None: 1)
        if reach is not None:
            r = torch.as_tensor(reach).detach().to(p.device, torch.float64).reshape(-1)
            if r.shape[0] != p.shape[0]:
                raise InputError(f"neighbour search: reach must have one value per point ({p.shape[0]}), got "
                                 f"{r.shape[0]}")
            r = torch.nan_to_num(r, nan=1.0, posinf=1.0).clamp_min(1.0)[keep]
            self.reach = r if bool((r > 1.0).any()) else None
        g = float(reach_gate)
        self.reach_gate = g if self.reach is not None and math.isfinite(g) and g > 0 else 0.0
        self.reach_surround = bool(reach_surround) and self.reach_gate > 0
        self.reach_gate_own = bool(reach_gate_own) and self.reach_gate > 0
        self.reach_between = bool(reach_between) and self.reach_gate > 0
        self.perspective = None  # [M] float64 >= 1: each reaching candidate's perspective factor (None: 1)
        persp = float(reach_perspective)
        if self.reach is not None and math.isfinite(persp) and persp > 1.0:
            dk = depth[keep]
            ratio = float(dk.median()) / dk  # > 1: nearer than the median candidate, sparser on the screen
            ratio = torch.nan_to_num(ratio, nan=1.0, posinf=persp).clamp(1.0, persp)
            ratio = torch.where(self.reach > 1.0, ratio, torch.ones_like(ratio))
            if bool((ratio > 1.0).any()):
                self.perspective = ratio
                self.reach = self.reach * ratio  # its reach covers it (every backend's uniform cap too)
        self.weight = depth[keep] / float(focal_scale(cam)) if depth_factor else None  # [M]
        self._density: float | None = None
        self._grids: dict[float, CellGrid] = {}  # one per resolved cap (the auto cap depends on K)
        self._tree = None
        self._compiled: dict[float, compiled.CompiledGrid] = {}
        if self.backend == "kdtree":
            w = None if self.weight is None else self.weight.cpu().numpy()
            self._tree = WeightedTree(self.px.cpu().numpy(), w)
        elif self.backend == "torch":
            self._px32 = self.px.to(torch.float32)
            self._w32 = None if self.weight is None else self.weight.to(torch.float32)

    def radius_px(self, k: int) -> float:
        """The pixel radius cap a query with K = k uses (inf = no cap); with `reach`, that of a point of reach 1."""
        if self.radius != "auto":
            return self.radius
        return auto_radius_px(self._median_density(), check_k(k))

    def _uniform_cap(self, k: int) -> float:
        """The one cap of the backends without per-point reach: the cap × the largest reach."""
        cap = self.radius_px(k)
        return cap if self.reach is None else cap * float(self.reach.max())

    def _median_density(self) -> float:
        if self._density is None:
            self._density = median_density(self.px, self.height, self.width)
        return self._density

    def query(self, query_px: torch.Tensor, k: int) -> Neighbors:
        """query_px [R, 2] (col, row) pixel coords (pixel (r, c) centre = (c + 0.5, r + 0.5)) -> Neighbors [R, K]."""
        check_matrix("query_px", query_px, 2)
        k = check_k(k)
        r = query_px.shape[0]
        if r == 0 or self.ids.numel() == 0:
            return empty(r, k, self.device)
        if self.backend == "compiled":  # already final: ids, -1 / inf padding, ascending, non-finite rows empty
            cap = self.radius_px(k)
            if cap not in self._compiled:
                w = None if self.weight is None else self.weight.numpy()
                reach = None if self.reach is None else self.reach.cpu().numpy()
                self._compiled[cap] = compiled.CompiledGrid(self.px.numpy(), w, self.ids.numpy(), cap,
                                                               self.height, self.width, reach=reach,
                                                               gate=self.reach_gate,
                                                               surround=self.reach_surround,
                                                               gate_own=self.reach_gate_own,
                                                               between=self.reach_between,
                                                               perspective=None if self.perspective is None
                                                               else self.perspective.cpu().numpy())
            idx, dist = self._compiled[cap].query(query_px.detach().to(torch.float64).numpy(), k)
            return Neighbors(torch.from_numpy(idx), torch.from_numpy(dist))
        out = self._query_capped(query_px, k, self._uniform_cap(k))
        cap = self.radius_px(k)
        if self.reach_gate and math.isfinite(cap):  # the gate from a plain query of the nearest point
            ps = self.perspective  # [M] or None: each point's gate and plain cap widened by it (as the compiled)
            widest = self.reach_gate * (1.0 if ps is None else float(ps.max()))
            near = (self._query_capped(query_px, 1, cap * widest).idx[:, 0] >= 0).to(out.idx.device)[:, None]
            if ((self.reach_gate_own or self.reach_between) and self.reach_gate > 1) or ps is not None:
                # brute force beyond the plain cap: each point's own gate (and plain cap, for the between rule)
                plain = (self._query_capped(query_px, 1, cap).idx[:, 0] >= 0).to(near.device)
                ask = torch.nonzero(near[:, 0] & ~plain).squeeze(1)
                widen = torch.ones_like(self.reach) if ps is None else ps  # [M] each point's perspective factor
                gate = cap * (self.reach.clamp_max(self.reach_gate) if self.reach_gate_own
                              else self.reach_gate * widen)  # [M] each point's gate
                qd = query_px.detach().to(self.px)
                for a in range(0, ask.numel(), 256):
                    rows = ask[a:a + 256].to(self.px.device)
                    off = self.px[None] - qd[rows][:, None]
                    d = off.norm(dim=-1)
                    inside = d <= gate[None]
                    ok = inside.any(dim=1)
                    if self.reach_between:  # within its own plain cap, or two more than 120° apart
                        ok = (inside & (d <= cap * widen[None])).any(dim=1)
                        for i in torch.nonzero(inside.any(dim=1) & ~ok).squeeze(1).tolist():
                            u = off[i][inside[i]] / d[i][inside[i]][:, None]
                            ok[i] = bool(((u @ u.T) < -0.5).any())
                    near[rows.to(near.device), 0] = ok.to(near.device)
            if self.reach_surround:  # brute force over the candidates of the rays the gate would empty
                ask = torch.nonzero(~near[:, 0] & (out.idx[:, 0] >= 0).to(near.device)).squeeze(1)
                reach = self._uniform_cap(k)
                qd = query_px.detach().to(self.px)
                for a in range(0, ask.numel(), 256):
                    rows = ask[a:a + 256].to(self.px.device)
                    off = self.px[None] - qd[rows][:, None]
                    ring = surrounded(off, off.norm(dim=-1) <= reach)
                    near[rows.to(near.device), 0] = ring.to(near.device)
            out = Neighbors(torch.where(near, out.idx, -1), torch.where(near, out.dist, math.inf))
        return out

    def _query_capped(self, query_px: torch.Tensor, k: int, cap: float) -> Neighbors:
        """query for the backends with one cap per query (grid, brute force; the k-d tree has none)."""
        if self.backend == "grid":
            with one_cpu_thread(self.device):
                if cap not in self._grids:
                    self._grids[cap] = CellGrid(self.px, self.weight, self.ids, cap, self._median_density(),
                                                 self.height, self.width)
                return Neighbors(*self._grids[cap].query(query_px.detach().to(self.device, torch.float64), k))
        ok = torch.isfinite(query_px).all(dim=1)
        if self._tree is not None:
            q = query_px.detach().to("cpu", torch.float64).numpy()
            q = np.where(ok.cpu().numpy()[:, None], q, 0.0)
            li, ld = self._tree.query(q, k)
            li, ld = torch.from_numpy(li), torch.from_numpy(ld)
        else:
            q = torch.where(ok[:, None], query_px.detach().to(self.device, torch.float32), 0.0)
            li, ld = screen_brute(self._px32, self._w32, q, k, cap)
        ids = self.ids.to(li.device)
        idx = torch.where(li >= 0, ids[li.clamp(min=0)], -1)
        ld = ld.masked_fill(~ok.to(ld.device)[:, None], math.inf)
        return finalize(idx, ld, k, self.device)


class PerpendicularIndex:
    """Points seen from one shared ray origin, built once and queried with many ray directions.

    points [N, 3]; origin [3]. Points at the origin or with non-finite coordinates are absent.
    """

    def __init__(self, points: torch.Tensor, origin: torch.Tensor, backend: str = "auto"):
        check_matrix("points", points, 3)
        origin = torch.as_tensor(origin)
        if origin.shape != (3,) or not bool(present(origin[None]).all()):
            raise InputError(f"neighbour search: origin must be a finite [3] tensor, got {origin.tolist()}")
        self.device = points.device
        self.backend = check_backend(backend, self.device)
        self.points = points.detach()
        self.origin = origin.detach().to(self.device)
        if self.backend == "kdtree":
            p = self.points.to("cpu", torch.float64)
            v = (torch.where(present(p)[:, None], p, 0.0) - self.origin.to("cpu", torch.float64)).numpy()
            norm = np.linalg.norm(v, axis=1)
            keep = present(p).numpy() & (norm > 0)
            self.ids = np.nonzero(keep)[0]
            keys = v[keep] / norm[keep, None]  # unit directions [M, 3]
            self._tree = WeightedTree(keys, norm[keep], phi=chord_to_sin, phi_inv=sin_to_chord)
        else:
            self._ids_t = torch.nonzero(present(self.points)).squeeze(1)

    def query(self, dirs: torch.Tensor, k: int) -> Neighbors:
        """dirs [R, 3] ray directions (normalised here; zero or non-finite = a ray with no neighbours)."""
        check_matrix("dirs", dirs, 3)
        k = check_k(k)
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
            return finalize(idx, ld, k, self.device)
        d = dirs.detach().to(self.device, torch.float32)
        n = torch.linalg.vector_norm(d, dim=1)
        ok = torch.isfinite(n) & (n > 0)
        d = torch.where(ok[:, None], d / torch.where(ok, n, 1.0)[:, None], 0.0)
        pts = self.points[self._ids_t].to(torch.float32)
        if r == 0 or pts.shape[0] == 0:
            return empty(r, k, self.device)
        o = self.origin.to(torch.float32).expand(r, 3)
        li, ld = perpendicular_brute(pts, o, d, k)
        ld = ld.masked_fill(~ok[:, None], math.inf)
        idx = torch.where(li >= 0, self._ids_t[li.clamp(min=0)], -1)
        return finalize(idx, ld, k, self.device)


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
    check_matrix("points", points, 3)
    check_matrix("origins", origins, 3)
    check_matrix("dirs", dirs, 3)
    k = check_k(k)
    if origins.shape[0] != dirs.shape[0]:
        raise InputError(f"neighbour search: origins {list(origins.shape)} and dirs {list(dirs.shape)} differ in R")
    device = points.device
    backend = check_backend(backend, device)
    r = origins.shape[0]
    out = empty(r, k, device)
    o_ok = present(origins)
    if r == 0 or not bool(o_ok.any()):
        return out
    if backend == "torch":  # brute force handles per-ray origins directly
        sel = torch.nonzero(o_ok.to(device)).squeeze(1)
        res = perpendicular_brute_any(points, origins[sel.to(origins.device)], dirs[sel.to(dirs.device)], k)
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
        res = perpendicular_brute_any(points, origins[sel.to(origins.device)], dirs[sel.to(dirs.device)], k)
        out.idx[sel], out.dist[sel] = res.idx, res.dist
    return out
