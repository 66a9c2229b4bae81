"""Compiled CPU kernel of the capped screen-space K-nearest search (the "compiled" backend).

Same definition as the pure-torch grid (`grid.py`): candidates of a query pixel are the projected points within
`cap` pixels; they are ranked by pixel distance × per-point weight (weight 1 for "screen", depth / focal for
"screen_depth"). Why a compiled loop: on the CPU the torch grid is a few hundred small tensor ops per frame and a
per-row `topk` (≈ 0.8 µs a row); one loop per query that keeps its K best in an insertion buffer does the same work
in a single pass over ~3 K candidates. Needs numba (an optional dependency: without it `available()` is False and
"auto" keeps the torch grid). CPU only and single-threaded, like the torch grid on the CPU (see grid.py).

Cells are squares of about half the cap (the radius holding K points at the median density, so the K nearest
usually lie in the query's cell and its 8 neighbours). Cells are visited ring by ring around the query's cell; a
cell is skipped when its nearest corner/edge is farther than the cap or, once K candidates are held, when
(its distance × the smallest weight in it) cannot beat the K-th value; the walk stops when a whole ring is out
of reach by the same bounds (with the smallest weight over all points). Every skipped point is provably worse
than the K held, so the result is exact (ties with the K-th value aside).
"""
from __future__ import annotations

import math

import numpy as np

try:  # optional: the torch grid is used without it
    import numba

    _NUMBA_ERROR = None
except ImportError as exc:  # pragma: no cover - exercised only where numba is missing
    numba = None
    _NUMBA_ERROR = exc

_MAX_CELLS = 1 << 22  # bounds the cell table for tiny caps (4 M cells = 32 MB of int64 offsets at most)
_CELL_PER_CAP = 0.5  # cell side / cap


def available() -> bool:
    """True when numba imports (the compiled backend can run)."""
    return numba is not None


def _kernel(xs, ys, ws, ids, wcell, start, ncx, ncy, cell, wmin_all, q, cap, k, out_idx, out_val, rs, rcell,
            rs_max, gate, surround, gate_own, between, dirs, ps, ps_max, pcell):
    """For each query q[i] = (col, row) relative to the grid origin: its K best (ids[slot], value) ascending.
    xs, ys, ws, ids [M] sorted by cell (row-major), start [ncx*ncy + 1] cell offsets, wcell [ncx*ncy] smallest
    weight per cell (inf when empty). out_idx [R, K] int64 (-1 = none) and out_val [R, K] float32 (inf = none),
    pre-filled; values are ranked in float64 and stored in float32. rs [M] each point's reach factor (its cap is
    cap × rs), rcell [ncx*ncy] the largest per cell, rs_max the largest of all (all ones: one cap). gate > 0: a
    query with no point within gate × cap gets no neighbours (gate 1: the reach adds points only to queries the
    plain cap already gives one); 0: no gate. surround (with a gate): such a query keeps its K best all the same
    when its candidates (every point within its own reach of the query) surround it: no 3 consecutive of the 8
    45° sectors around the query lack one (`_ringed`) — a hole inside the object's screen outline rather than a
    ray beside it. Until that is known, such a query walks its whole reach (no cell is skipped for the K best).
    gate_own: point j gates at cap × min(gate, rs[j]) (a wider gate only around points that reach that far).
    between (gate > 1): a point within the gate but beyond the plain cap opens it only together with another such
    point whose direction from the query is more than 120° away (_BETWEEN_COS): the query lies between the points
    of a sparse surface, not beside a dense outline (seen from outside a straight edge, the points within
    gate × cap span at most 2·acos(1 / gate) ≤ 120° for gate ≤ 2). dirs [M, 2] float64 scratch space.
    ps [M] each point's perspective factor (>= 1, all ones: none) on the plain cap its gate and the between rule
    measure by (cap × ps[j]; rs already holds it), ps_max the largest, pcell [ncx*ncy] the largest per cell."""
    reach = cap * rs_max  # no point is a candidate beyond this
    walk = max(reach, cap * gate * ps_max)  # nor does the gate look farther
    rmax = int(math.ceil(walk / cell)) + 1
    best = np.empty(k, dtype=np.float64)  # the query's K best values, ascending ...
    slot = np.empty(k, dtype=np.int64)  # ... and their slots
    for i in range(q.shape[0]):
        qx = q[i, 0]
        qy = q[i, 1]
        if not (math.isfinite(qx) and math.isfinite(qy)):
            continue
        if qx < -walk or qy < -walk or qx > ncx * cell + walk or qy > ncy * cell + walk:
            continue  # beyond the cap of every cell (and keeps the cell index arithmetic small)
        cx = int(math.floor(qx / cell))
        cy = int(math.floor(qy / cell))
        # rings nearer than the grid or beyond its far side hold no cell: walk only those that can
        r0 = max(0, -cx, cx - (ncx - 1), -cy, cy - (ncy - 1))
        rend = min(rmax, r0 + ncx + ncy)
        n = 0
        near = gate <= 0.0  # gate: whether a point lies within gate × cap (until then nothing is skipped there)
        gcap = cap * gate * ps_max  # the farthest any point gates
        gcap2 = gcap * gcap
        mask = 0  # surround: the sectors that hold a candidate
        ringed = not surround  # surround: whether they surround the query (nothing is skipped until then)
        nd = 0  # between: directions held in dirs
        for r in range(r0, rend + 1):
            lb = (r - 1) * cell if r > 0 else 0.0  # every point of ring r is at least this far from the query
            if lb > reach and (near or lb > gcap):
                break
            if not near and lb > gcap and not surround:
                break  # gate: nothing within gate × cap, the query stays empty
            if n == k and lb * wmin_all >= best[k - 1] and (near or (lb > gcap and ringed)):
                break
            for dy in range(max(-r, -cy), min(r, ncy - 1 - cy) + 1):
                y = cy + dy
                edge = dy == -r or dy == r
                step = 1 if edge else 2 * r
                dx = -r
                while dx <= r:
                    x = cx + dx
                    dx += step if r > 0 else 1
                    if x < 0 or x >= ncx:
                        continue
                    c = y * ncx + x
                    a = start[c]
                    b = start[c + 1]
                    if a == b:
                        continue
                    # distance from the query to the cell's rectangle
                    ex = max(x * cell - qx, qx - (x + 1) * cell, 0.0)
                    ey = max(y * cell - qy, qy - (y + 1) * cell, 0.0)
                    md = math.sqrt(ex * ex + ey * ey)
                    if md > cap * rcell[c] and (near or md > cap * gate * pcell[c]):
                        continue
                    if n == k and md * wcell[c] >= best[k - 1] and (near or (md > cap * gate * pcell[c] and ringed)):
                        continue
                    for j in range(a, b):
                        ddx = xs[j] - qx
                        ddy = ys[j] - qy
                        d2 = ddx * ddx + ddy * ddy
                        if not near and d2 <= gcap2:
                            gj = cap * min(gate, rs[j]) if gate_own else cap * gate * ps[j]
                            if d2 <= gj * gj:
                                if not between or d2 <= cap * cap * ps[j] * ps[j]:
                                    near = True
                                else:
                                    dd = math.sqrt(d2)
                                    ux = ddx / dd
                                    uy = ddy / dd
                                    for t in range(nd):
                                        if dirs[t, 0] * ux + dirs[t, 1] * uy < _BETWEEN_COS:
                                            near = True
                                            break
                                    dirs[nd, 0] = ux
                                    dirs[nd, 1] = uy
                                    nd += 1
                        cj = cap * rs[j]
                        if d2 > cj * cj:
                            continue
                        if not ringed and not near and d2 > 0.0:
                            mask |= 1 << _sector(ddx, ddy)
                            ringed = _ringed(mask)
                        v = math.sqrt(d2) * ws[j]
                        if n == k and v >= best[k - 1]:
                            continue
                        # insertion into the sorted buffer (equal values keep the earlier one first)
                        p = n if n < k else k - 1
                        while p > 0 and best[p - 1] > v:
                            best[p] = best[p - 1]
                            slot[p] = slot[p - 1]
                            p -= 1
                        best[p] = v
                        slot[p] = j
                        if n < k:
                            n += 1
        if not near and not (surround and ringed):
            continue
        for p in range(n):
            out_idx[i, p] = ids[slot[p]]
            out_val[i, p] = best[p]


_BETWEEN_COS = -0.5  # between: cos 120°
_SECTORS = 8  # surround: the turn around a query in 45° sectors
_SECTOR_RUN = 3  # ... surrounded when no this many consecutive sectors lack a candidate


def _sector_py(dx, dy):
    """The 45° sector (0..7, counter-clockwise from +x) of the direction (dx, dy) != 0."""
    s = int(math.floor(math.atan2(dy, dx) / (0.25 * math.pi))) % _SECTORS
    return s


def _ringed_py(mask):
    """Whether a bit mask of occupied sectors leaves no _SECTOR_RUN consecutive sectors (around the turn) empty."""
    for s in range(_SECTORS):
        empty = True
        for t in range(_SECTOR_RUN):
            if mask & (1 << ((s + t) % _SECTORS)):
                empty = False
                break
        if empty:
            return False
    return True


_sector, _ringed = _sector_py, _ringed_py  # the kernel calls these names: compiled with it (`_get_kernel`)


_compiled = None


def _jit_kernel(cache: bool):
    """The kernel and the helpers it calls compiled by numba, each from its Python function (so a second attempt,
    without the cache, starts again from those)."""
    global _sector, _ringed
    _sector = numba.njit(cache=cache, nogil=True, fastmath=False)(_sector_py)
    _ringed = numba.njit(cache=cache, nogil=True, fastmath=False)(_ringed_py)
    return numba.njit(cache=cache, nogil=True, fastmath=False)(_kernel)


def _get_kernel():
    global _compiled
    if _compiled is None:
        if numba is None:
            raise RuntimeError(f"the compiled neighbour search needs numba ({_NUMBA_ERROR}); "
                               "install it (pip install numba) or use backend='grid'")
        try:  # cached next to the module (or numba's user cache) so later processes skip the ~2 s compile
            _compiled = _jit_kernel(cache=True)
        except RuntimeError:  # no writable cache location (read-only install): compile per process
            _compiled = _jit_kernel(cache=False)
    return _compiled


class CompiledGrid:
    """Projected points of one camera in square cells, queried by the compiled kernel.

    px [M, 2] float64 (col, row) pixel coords, already filtered (finite, in front, inside the frame ± 1 px);
    weight [M] float64 or None; ids [M] int64, what a query returns for each point; cap > 0 pixels (finite);
    height, width of the frame; reach [M] float64 >= 1 or None: point m is a candidate within cap × reach[m]
    pixels (cells are sized by `cap` × the square root of the median reach: a few far-reaching points do not make
    every query visit larger cells, and where most points reach far a query does not walk many small ones; the
    answer does not depend on the cell size). gate > 0: a query with no point within gate × cap gets none, unless
    surround and its candidates surround it (`_kernel`); gate_own: point j's gate is cap × min(gate, reach[j]);
    between: beyond the plain cap the gate opens only for points on opposite sides of the query (`_kernel`).
    perspective [M] float64 >= 1 or None: point m gates at gate × cap × perspective[m] and counts as within the
    plain cap for `between` within cap × perspective[m] (its reach already holds the factor)."""

    def __init__(self, px: np.ndarray, weight: np.ndarray | None, ids: np.ndarray, cap: float, height: int,
                 width: int, reach: np.ndarray | None = None, gate: float = 0.0, surround: bool = False,
                 gate_own: bool = False, between: bool = False, perspective: np.ndarray | None = None):
        self.cap = float(cap)
        self.gate = float(gate) if gate and math.isfinite(float(gate)) and float(gate) > 0 else 0.0
        self.surround = bool(surround) and self.gate > 0
        self.gate_own = bool(gate_own) and self.gate > 0
        self.between = bool(between) and self.gate > 0
        span_x, span_y = width + 2.0, height + 2.0  # candidates lie inside the frame ± 1 px
        rs = np.ones(len(px)) if reach is None else np.maximum(np.nan_to_num(np.asarray(reach, dtype=np.float64),
                                                                             nan=1.0, posinf=1.0), 1.0)
        ps = np.ones(len(px)) if perspective is None else np.maximum(np.nan_to_num(
            np.asarray(perspective, dtype=np.float64), nan=1.0, posinf=1.0), 1.0)
        grow = math.sqrt(float(np.median(rs))) if len(rs) else 1.0
        self.cell = max(_CELL_PER_CAP * self.cap * grow, math.sqrt(span_x * span_y / _MAX_CELLS))
        self.ncx = int(span_x // self.cell) + 1
        self.ncy = int(span_y // self.cell) + 1
        rel = np.asarray(px, dtype=np.float64) + 1.0  # grid origin at (-1, -1)
        cx = np.clip(np.floor(rel[:, 0] / self.cell), 0, self.ncx - 1).astype(np.int64)
        cy = np.clip(np.floor(rel[:, 1] / self.cell), 0, self.ncy - 1).astype(np.int64)
        cell_id = cy * self.ncx + cx
        self.order = np.argsort(cell_id, kind="stable")  # slot -> row of px
        counts = np.bincount(cell_id, minlength=self.ncx * self.ncy)
        self.start = np.concatenate([[0], np.cumsum(counts)]).astype(np.int64)
        self.xs = np.ascontiguousarray(rel[self.order, 0])
        self.ys = np.ascontiguousarray(rel[self.order, 1])
        w = np.ones(len(rel)) if weight is None else np.asarray(weight, dtype=np.float64)
        self.ws = np.ascontiguousarray(w[self.order])
        self.ids = np.ascontiguousarray(np.asarray(ids, dtype=np.int64)[self.order])
        self.wcell = np.full(self.ncx * self.ncy, np.inf)
        np.minimum.at(self.wcell, cell_id, w)
        self.wmin = float(w.min()) if len(w) else 1.0
        self.ps = np.ascontiguousarray(ps[self.order])
        self.ps_max = float(ps.max()) if len(ps) else 1.0
        self.pcell = np.ones(self.ncx * self.ncy)
        np.maximum.at(self.pcell, cell_id, ps)
        self.rs = np.ascontiguousarray(rs[self.order])
        self.rcell = np.ones(self.ncx * self.ncy)
        np.maximum.at(self.rcell, cell_id, rs)
        self.rs_max = float(rs.max()) if len(rs) else 1.0

    def query(self, q: np.ndarray, k: int) -> tuple[np.ndarray, np.ndarray]:
        """q [R, 2] float64 (col, row), non-finite rows get no neighbours -> (ids [R, k] int64 of the ids given
        to __init__, -1 = none; value [R, k] float32 ascending, inf = none)."""
        r = q.shape[0]
        idx = np.full((r, k), -1, dtype=np.int64)
        val = np.full((r, k), np.inf, dtype=np.float32)
        if r and len(self.xs):
            qq = np.ascontiguousarray(np.asarray(q, dtype=np.float64) + 1.0)
            _get_kernel()(self.xs, self.ys, self.ws, self.ids, self.wcell, self.start, self.ncx, self.ncy, self.cell,
                          self.wmin, qq, self.cap, k, idx, val, self.rs, self.rcell, self.rs_max, self.gate,
                          self.surround, self.gate_own, self.between, np.empty((len(self.xs), 2)), self.ps,
                          self.ps_max, self.pcell)
        return idx, val
