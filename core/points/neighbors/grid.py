"""The "grid" backend (capped screen searches, any device, pure torch): a pixel-space cell grid, see CellGrid."""
from __future__ import annotations

import contextlib
import math

import torch

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


class CellGrid:
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
def one_cpu_thread(device: torch.device):
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
