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


def _overlaps(occ: np.ndarray, feet: list[np.ndarray]) -> list[np.ndarray]:
    """Overlap counts of each footprint [a, b] (0/1) at every position inside occ [H, W] (0/1) -> per footprint
    [H - a + 1, W - b + 1] float (integers up to rounding; empty when it does not fit): entry (r, c) counts the
    occupied cells under the footprint placed with its first cell at (r, c). One FFT of occ for all of them."""
    H, W = occ.shape
    fh, fw = _fft_size(H), _fft_size(W)
    spec = np.fft.rfft2(occ, (fh, fw))
    out = []
    for foot in feet:
        a, b = foot.shape
        if a > H or b > W:
            out.append(np.zeros((0, 0)))
            continue
        corr = np.fft.irfft2(spec * np.conj(np.fft.rfft2(foot, (fh, fw))), (fh, fw))
        out.append(corr[:H - a + 1, :W - b + 1])
    return out


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
    holds them, then up to `search` placements into fixed squares bisect between it and the side their padded
    footprints fill exactly, to within 1 % of the side. Returns (offsets [I, 2] int (col, row), orient [I] int (ORIENT_NP), side): mask cell (col, row) goes
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
    # footprints never overlap, so they fit in the image grown by g on every side: no smaller square holds them
    feet = sum(int(o[0][3].sum()) for o in shapes)
    lo, hi = max(math.isqrt(feet) - 2 * g, longest) - 1, best[2]
    for _ in range(search):
        if hi - lo <= max(1, hi // 100):  # within 1 % of the side: not worth another placement
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
    spot in reading order (row, then col). The reading-order search runs over bands of rows from the first row
    with a free cell down, so an island that fits near the top costs a band, not the image."""
    occ = np.zeros((S + 2 * g, S + 2 * g), np.float64)  # footprints, the image grown by g on every side
    offsets = np.zeros((len(shapes), 2), np.int64)
    orient = np.zeros(len(shapes), np.int64)
    extent = 0
    for i in order:
        opts = [o for o in shapes[i] if o[1].shape[0] <= S and o[1].shape[1] <= S]
        best = None
        if corner:  # no spot past the used square and its gap can win: the free spot (0, extent + 2 g) just right
            # of it has a nearer far corner (while it fits the image)
            hmax = max(o[3].shape[0] for o in opts) if opts else 0
            lim = extent + 2 * g
            win = occ[:min(lim + hmax, S + 2 * g), :min(lim + hmax, S + 2 * g)]
            for (q, t, first, foot), ov in zip(opts, _overlaps(win, [o[3] for o in opts])):
                h, w = t.shape
                ov = ov[:min(S - h, lim) + 1, :min(S - w, lim) + 1]
                rr, cc = np.nonzero(ov < 0.5)
                if len(rr) == 0:
                    continue
                far = np.maximum(rr + h, cc + w)
                k = np.lexsort((cc, rr + cc, far))[0]
                cand = (int(far[k]), int(rr[k] + cc[k]), int(rr[k]), int(cc[k]), q, t, first, foot)
                if best is None or cand[:2] < best[:2]:
                    best = cand
        elif opts:
            full = occ[g:S + g, g:S + g].all(1)
            r0 = int(np.argmin(full)) if not full.all() else S  # rows above are full: no island starts there
            hmax = max(o[3].shape[0] for o in opts)
            band = max(32, hmax)
            while best is None and r0 <= S - min(o[1].shape[0] for o in opts):
                win = occ[r0:r0 + band + hmax - 1]  # spots of rows r0 .. r0 + band - 1 for every orientation
                for (q, t, first, foot), ov in zip(opts, _overlaps(win, [o[3] for o in opts])):
                    h, w = t.shape
                    ov = ov[:max(min(band, S - h - r0 + 1), 0)]
                    rr, cc = np.nonzero(ov < 0.5)
                    if len(rr) == 0:
                        continue
                    cand = (int(rr[0]) + r0, int(cc[0]), int(rr[0]) + r0, int(cc[0]), q, t, first, foot)
                    if best is None or cand[:2] < best[:2]:
                        best = cand
                r0 += band
        if best is None:
            return None
        _, _, r, c, q, t, first, foot = best
        occ[r:r + foot.shape[0], c:c + foot.shape[1]] += foot
        offsets[i] = np.array([c, r], np.int64) - first
        orient[i] = q
        extent = max(extent, r + t.shape[0], c + t.shape[1])
    return offsets, orient, extent
