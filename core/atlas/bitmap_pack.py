"""A dense packer for island cell masks: every island placed by its exact cell shape, not its bounding box.

Islands go in one at a time, largest first. Each is tried in every allowed orientation (the eight symmetries of the
texel grid, or only the identity) at every position of the image where its footprint (its cells grown by pad - 1
texels in the chessboard metric) overlaps no footprint already placed; the overlap count of all positions at once is
one FFT correlation of the occupied image with the footprint. In a square of fixed side the first free position in
reading order wins (over the orientations), so islands interlock (a curved island's hollow takes small islands);
the smallest side is found by bisection, from the side of a first placement that grows a square from one corner
(each island where its far corner is nearest the image's top-left corner).
Two disjoint footprints leave the islands' cells at least 2 pad - 1 apart, the separation bilinear lookups need
(core/atlas/islands.py). The result has the same form as `pack_islands`'s, so it drops into `build_islands`.
"""
from __future__ import annotations

import math

import numpy as np

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


def _overlaps(occ: np.ndarray, foot: np.ndarray) -> np.ndarray:
    """Overlap counts of footprint foot [a, b] at every position inside occ [H, W] (both 0/1) -> [H - a + 1,
    W - b + 1] float (integers up to rounding): entry (r, c) counts the occupied cells under foot placed with its
    first cell at (r, c)."""
    H, W = occ.shape
    a, b = foot.shape
    fh, fw = _fft_size(H), _fft_size(W)
    spec = np.fft.rfft2(occ, (fh, fw)) * np.conj(np.fft.rfft2(foot, (fh, fw)))
    return np.fft.irfft2(spec, (fh, fw))[:H - a + 1, :W - b + 1]


def _fft_size(n: int) -> int:
    """The smallest 2^i 3^j 5^k >= n (fast FFT lengths)."""
    best = 1 << max(int(n - 1).bit_length(), 0)
    f5 = 1
    while f5 < 2 * n:
        f3 = f5
        while f3 < 2 * n:
            f2 = f3
            while f2 < n:
                f2 *= 2
            best = min(best, f2)
            f3 *= 3
        f5 *= 5
    return best


def pack_bitmap(masks: list[np.ndarray], pad: int, size: int = 0, transpose: bool = False, search: int = 8):
    """Pack island cell masks (each [h, w] bool, cropped) by their exact shapes with `pad` texels of padding.

    transpose: each island may take any of the eight symmetries of the texel grid (else only the identity).
    size > 0: into one size x size image, each island at its first free spot in reading order (None when they do
    not all fit); 0: the smallest square found: a placement that grows a square from one corner gives a side that
    holds them, then up to `search` placements into fixed squares bisect between it and the side their cells fill
    exactly. Returns (offsets [I, 2] int (col, row), orient [I] int (ORIENT_NP), side): mask cell (col, row) goes
    to pixel cell_pixels(col, row, offset, orient), as `pack_islands`."""
    if not masks:
        raise InputError("island packing: no islands")
    g = max(int(pad) - 1, 0)
    qs = range(len(ORIENT_NP)) if transpose else (0,)
    shapes = []  # per island: [(q, turned mask, first-cell pixel, footprint)]
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
            opts.append((q, t, first, _grow(t, g).astype(np.float64)))
        shapes.append(opts)
    longest = max(max(m.shape) for m in masks)
    cells = sum(int(m.sum()) for m in masks)
    order = sorted(range(len(masks)), key=lambda i: (-int(shapes[i][0][3].sum()), -max(masks[i].shape), i))
    if size > 0:
        if longest > size:
            return None
        got = _place_all(shapes, order, int(size), g, corner=False)
        return None if got is None else (got[0], got[1], int(size))
    S = max(int(math.ceil(math.sqrt(sum(int(o[0][3].sum()) for o in shapes) / 0.5))), longest + 2 * g)
    best = None
    while best is None:  # the corner placement in a generous square, larger until everything fits
        best = _place_all(shapes, order, S, g, corner=True)
        if best is None:
            if S > 64 * (math.isqrt(cells) + longest + 2 * g + 1):
                raise InputError("island packing: no placement found")
            S = int(math.ceil(S * 1.25)) + 1
    best = (best[0], best[1], max(best[2], 1))
    lo, hi = max(math.isqrt(cells), longest) - 1, best[2]  # no square below lo + 1 holds the cells
    for _ in range(search):
        if hi - lo <= 1:
            break
        mid = (lo + hi) // 2
        got = _place_all(shapes, order, mid, g, corner=False)
        if got is None:
            lo = mid
        else:
            hi, best = mid, (got[0], got[1], mid)
    return best


def _place_all(shapes, order, S: int, g: int, corner: bool):
    """Greedy placement of every island (in `order`) into an S x S image: (offsets [I, 2], orient [I], the used
    square's side) or None when one does not fit. corner: each island at the free spot whose far corner is nearest
    the image's top-left corner (Chebyshev extent, then row + col), over its orientations; else at its first free
    spot in reading order (row, then col)."""
    occ = np.zeros((S + 2 * g, S + 2 * g), np.float64)  # footprints, the image grown by g on every side
    offsets = np.zeros((len(shapes), 2), np.int64)
    orient = np.zeros(len(shapes), np.int64)
    extent = 0
    for i in order:
        best = None
        for q, t, first, foot in shapes[i]:
            h, w = t.shape
            if h > S or w > S:
                continue
            if corner:  # no spot past the used square and its gap can win: the free spot (0, extent + 2 g) just
                # right of it has a nearer far corner (while it fits the image)
                lim_r, lim_c = min(S - h, extent + 2 * g), min(S - w, extent + 2 * g)
                win = occ[:lim_r + h + 2 * g, :lim_c + w + 2 * g]
            else:
                win = occ
            rr, cc = np.nonzero(_overlaps(win, foot) < 0.5)
            if len(rr) == 0:
                continue
            if corner:
                far = np.maximum(rr + h, cc + w)
                k = np.lexsort((cc, rr + cc, far))[0]
                cand = (int(far[k]), int(rr[k] + cc[k]), int(rr[k]), int(cc[k]), q, t, first, foot)
            else:
                k = 0  # np.nonzero is row-major: the first free spot in reading order
                cand = (int(rr[k]), int(cc[k]), int(rr[k]), int(cc[k]), q, t, first, foot)
            if best is None or cand[:2] < best[:2]:
                best = cand
        if best is None:
            return None
        _, _, r, c, q, t, first, foot = best
        occ[r:r + foot.shape[0], c:c + foot.shape[1]] += foot
        offsets[i] = np.array([c, r], np.int64) - first
        orient[i] = q
        extent = max(extent, r + t.shape[0], c + t.shape[1])
    return offsets, orient, extent
