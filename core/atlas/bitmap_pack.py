"""A dense packer for island cell masks: every island placed by its exact cell shape, not its bounding box.

Islands go in one at a time, largest first. Each is tried in every allowed orientation (the eight symmetries of the
texel grid, or only the identity) at every position of the image where its footprint (its cells grown by pad - 1
texels in the chessboard metric) overlaps no footprint already placed; the overlap count of all positions at once is
one FFT correlation of the occupied image with the footprint. In a square of fixed side the first free position in
reading order wins (over the orientations), so islands interlock (a curved island's hollow takes small islands).
A greedy order that fails a square can succeed with another, so a square is tried with up to four (`ORDERS`: the
largest footprint first or the longest island first, each orientation placed by its first free position or by
where its bottom row lands) before it counts as too small; the smallest side is found by bisection.
Two disjoint footprints leave the islands' cells at least 2 pad - 1 apart, the separation bilinear lookups need
(core/atlas/islands.py). The result has the same form as `pack_islands`'s, so it drops into `build_islands`.
"""
from __future__ import annotations

import math

import numpy as np
from scipy.fft import ifft, irfft, next_fast_len, rfft2

from core.atlas.islands import bisect_side
from core.atlas.outlines import ORIENT_NP, cell_pixels
from core.util.errors import InputError


def _oriented(mask: np.ndarray, q: int) -> tuple[np.ndarray, np.ndarray]:
    """mask [h, w] bool turned by orientation q -> (the turned mask [h', w'] bool, (col, row) [2] of the pixel
    that cell_pixels gives mask's cells with offset 0 at the turned mask's first cell): an island placed with its
    turned mask's first cell at pixel P has offset P - that."""
    rr, kk = np.nonzero(mask)
    pc, pr = cell_pixels(kk, rr, np.zeros((1, 2), np.int64), np.full(len(rr), q))
    c0, r0 = int(pc.min()), int(pr.min())
    out = np.zeros((int(pr.max()) - r0 + 1, int(pc.max()) - c0 + 1), bool)
    out[pr - r0, pc - c0] = True
    return out, np.array([c0, r0], np.int64)


def _grow(mask: np.ndarray, by: int) -> np.ndarray:
    """mask [h, w] bool grown by `by` cells in the chessboard metric -> [h + 2 by, w + 2 by] bool."""
    if by <= 0:
        return mask.copy()
    from scipy.ndimage import binary_dilation
    return binary_dilation(np.pad(mask, by), np.ones((2 * by + 1, 2 * by + 1), bool))


def _shapes(masks: list[np.ndarray], g: int, transpose: bool) -> list[list[tuple]]:
    """Per island, its distinct orientations (every symmetry of the texel grid with transpose, else the identity):
    [(q, turned mask [h, w] bool, first-cell pixel [2] (`_oriented`), footprint [h + 2 g, w + 2 g] float 0/1)]."""
    qs = range(len(ORIENT_NP)) if transpose else (0,)
    shapes = []
    for m in masks:
        if not m.any():
            raise InputError("island packing: an island has no cells")
        seen, opts = set(), []
        for q in qs:
            t, first = _oriented(m, q)
            key = (t.shape, t.tobytes())
            if key in seen:  # a symmetric island: one orientation per distinct shape
                continue
            seen.add(key)
            opts.append((q, t, first, _grow(t, g).astype(np.float32)))
        shapes.append(opts)
    return shapes


# greedy orders a square is tried with (pack_bitmap): (islands by footprint size or by longest side, the
# orientations compared by their first free position or by the row their bottom lands on)
ORDERS = (("area", False), ("longest", False), ("area", True), ("longest", True))


def _order(shapes, masks, by: str) -> list[int]:
    """Islands in placement order: the largest footprint first ("area", then the longest side) or the longest side
    first ("longest", then the footprint); ties by index."""
    area = [-int(s[0][3].sum()) for s in shapes]
    longest = [-max(m.shape) for m in masks]
    key = (lambda i: (area[i], longest[i], i)) if by == "area" else (lambda i: (longest[i], area[i], i))
    return sorted(range(len(masks)), key=key)


def pack_bitmap(masks: list[np.ndarray], pad: int, size: int = 0, transpose: bool = False, search: int = 8,
                orders=ORDERS):
    """Pack island cell masks (each [h, w] bool, cropped) by their exact shapes with `pad` texels of padding.

    transpose: each island may take any of the eight symmetries of the texel grid (else only the identity).
    size > 0: into one size x size image (None when they do not all fit); 0: the smallest square found: a first
    square where the padded footprints would fill 80 % (10 % larger until they fit), then up to `search`
    sides bisect between it and the side the footprints fill exactly, to within 1 % of the side. Each square is
    tried with the greedy `orders` (`ORDERS`) in turn until one fits every island.
    Returns (offsets [I, 2] int (col, row), orient [I] int (ORIENT_NP), side): mask cell (col, row) goes to pixel
    cell_pixels(col, row, offset, orient), as `pack_islands`."""
    if not masks:
        raise InputError("island packing: no islands")
    g = max(int(pad) - 1, 0)
    shapes = _shapes(masks, g, transpose)
    longest = max(max(m.shape) for m in masks)
    cells = sum(int(m.sum()) for m in masks)
    if not orders:
        raise InputError("island packing: no placement order")
    plans = [(_order(shapes, masks, by), bottom) for by, bottom in orders]

    def place(side: int):
        for order, bottom in plans:
            got = _place_all(shapes, order, side, g, bottom)
            if got is not None:
                return got
        return None

    if size > 0:
        if longest > size:
            return None
        got = place(int(size))
        return None if got is None else (got[0], got[1], int(size))
    # footprints never overlap, so they fit in the image grown by g on every side: no smaller square holds them
    feet = sum(int(o[0][3].sum()) for o in shapes)
    lo = max(math.isqrt(feet) - 2 * g, longest) - 1
    S, best = max(int(math.ceil(math.sqrt(feet / 0.8))), longest + 2 * g), None
    while best is None:  # a first square that holds them: the footprints at 80 % of it, larger until they fit
        got = place(S)
        if got is not None:
            best, hi = (got[0], got[1], S), S
        else:
            if S > 64 * (math.isqrt(cells) + longest + 2 * g + 1):
                raise InputError("island packing: no placement found")
            lo, S = S, int(math.ceil(S * 1.1)) + 1
    # within 1 % of the side: not worth another placement
    return bisect_side(place, lo, hi, best, search, tol=0.01)


def longest_runs(a: np.ndarray) -> np.ndarray:
    """a [R, W] bool -> [R] int64, the longest run of True in each row."""
    idx = np.arange(1, a.shape[1] + 1)
    if a.shape[1] == 0:
        return np.zeros(a.shape[0], np.int64)
    return (idx - np.maximum.accumulate(np.where(a, 0, idx), axis=1)).max(1)


def _start_rows(opts, free_run: np.ndarray, S: int) -> np.ndarray:
    """Rows (ascending) where some orientation's footprint could start: each footprint row needs a run of free
    cells at least as long as its own longest run of cells in the image row it lands on (necessary, not
    sufficient: the FFT decides). free_run [S + 2 g]: the longest free run of each row of the grown image."""
    ok = np.zeros(S, bool)
    for q, t, first, foot in opts:
        n = S - t.shape[0] + 1
        if n <= 0:
            continue
        need = longest_runs(foot > 0)
        ok_q = np.ones(n, bool)
        for k in np.argsort(-need, kind="stable"):  # the most demanding rows first: most spots fail early
            ok_q &= free_run[k:k + n] >= need[k]
            if not ok_q.any():
                break
        ok[:n] |= ok_q
    return np.flatnonzero(ok)


def _overlaps(product: np.ndarray, fw: int, n: int, m: int) -> np.ndarray:
    """The first n x m entries of irfft2(product, (fh, fw)) for a half spectrum product [fh, fw // 2 + 1]: the
    complex inverse down every column, then the real inverse along the first n rows only (a band's spots are its
    first rows; the rest of the window is the footprint's reach below them)."""
    return irfft(ifft(product, axis=0)[:n], fw, axis=1)[:, :m]


def _free_spots(ov: np.ndarray):
    """(row, col) of every entry of ov [n, m] below 0.5 in reading order, found one at a time (the caller takes
    the first that its exact check accepts; most bands stop at the first)."""
    free = (ov < 0.5).ravel()
    k = 0
    while k < free.size:
        k += int(free[k:].argmax())
        if not free[k]:
            return
        yield divmod(k, ov.shape[1])
        k += 1


def _place_all(shapes, order, S: int, g: int, bottom: bool = False):
    """Greedy placement of every island (in `order`) into an S x S image, each at its first free spot in reading
    order (row, then col); over its orientations the one whose spot comes first (bottom: whose bottom row, spot row
    + height, is highest, then the leftmost): (offsets [I, 2], orient [I]) or None when one does not fit. The
    search runs over bands of rows from the first row where a footprint could start down (`_start_rows`), so an
    island that fits near the top costs a band, not the image."""
    # footprints, the image grown by g on every side; single precision: the FFTs run twice as fast, and a spot
    # whose rounded count says free is checked cell by cell
    occ = np.zeros((S + 2 * g, S + 2 * g), np.float32)
    free_run = np.full(S + 2 * g, S + 2 * g, np.int64)  # longest run of free cells in each row of occ
    offsets = np.zeros((len(shapes), 2), np.int64)
    orient = np.zeros(len(shapes), np.int64)
    for i in order:
        opts = [o for o in shapes[i] if o[1].shape[0] <= S and o[1].shape[1] <= S]
        best = None
        if opts:
            starts = _start_rows(opts, free_run, S)
            hmax = max(o[3].shape[0] for o in opts)
            band = max(32, hmax)
            H, W = band + hmax - 1, S + 2 * g  # the window of a band's spots, for every orientation
            fh, fw = next_fast_len(H, real=True), next_fast_len(W, real=True)
            specs = [np.conj(rfft2(o[3], (fh, fw))) for o in opts] if len(starts) else []  # once per island
            j = 0
            while best is None and j < len(starts):
                r0 = int(starts[j])
                spec = rfft2(occ[r0:r0 + H], (fh, fw))  # rows past the image read as zero-padding
                for (q, t, first, foot), fs in zip(opts, specs):
                    h, w = t.shape
                    n = min(band, S - h - r0 + 1)  # spots r0 .. r0 + n - 1 keep the island inside the image
                    if n <= 0:
                        continue
                    foot_h, foot_w = foot.shape
                    ov = _overlaps(spec * fs, fw, n, W - foot_w + 1)
                    for r, c in _free_spots(ov):  # row-major: the first free spot in reading order
                        r += r0
                        # single-precision FFTs: the count is checked exactly before the spot is taken
                        if not (occ[r:r + foot_h, c:c + foot_w] * foot).any():
                            cand = (r + h if bottom else r, c, r, q, first, foot)
                            if best is None or cand[:2] < best[:2]:  # then over orientations
                                best = cand
                            break
                j = int(np.searchsorted(starts, r0 + band))  # the next band: from the next possible start on
        if best is None:
            return None
        _, c, r, q, first, foot = best
        occ[r:r + foot.shape[0], c:c + foot.shape[1]] += foot
        free_run[r:r + foot.shape[0]] = longest_runs(occ[r:r + foot.shape[0]] == 0)
        offsets[i] = np.array([c, r], np.int64) - first
        orient[i] = q
    return offsets, orient
