"""The bitmap packer: exact-cell placement, padding between islands, orientations, fixed sizes."""
import numpy as np
import pytest
from scipy.ndimage import distance_transform_edt

from core.atlas.bitmap_pack import pack_bitmap
from core.atlas.islands import pack_islands, start_side
from core.atlas.outlines import cell_pixels
from core.util.errors import InputError


def _masks():
    """24 rectangles and three curved (arc) islands, whose hollows a shape packer can fill."""
    rng = np.random.default_rng(0)
    masks = [np.ones((h, w), bool) for h, w in rng.integers(8, 40, (24, 2))]
    yy, xx = np.mgrid[-30:31, -30:31]
    arc = (np.hypot(yy, xx) < 30) & (np.hypot(yy, xx) > 22) & (yy > -5)
    arc = arc[np.any(arc, 1)][:, np.any(arc, 0)]
    return masks + [arc, arc.T.copy(), arc[::-1].copy()]


def _labels(masks, offsets, orient, side):
    """Island id per pixel [side, side] (-1 outside); asserts every cell lands inside the image, no two on one."""
    lab = np.full((side, side), -1)
    for i, m in enumerate(masks):
        rr, kk = np.nonzero(m)
        pc, pr = cell_pixels(kk, rr, np.broadcast_to(offsets[i], (len(rr), 2)), np.full(len(rr), orient[i]))
        assert pc.min() >= 0 and pr.min() >= 0 and pc.max() < side and pr.max() < side
        assert (lab[pr, pc] == -1).all()
        lab[pr, pc] = i
    return lab


@pytest.mark.parametrize("pad", [1, 2, 3])
def test_bitmap_packing_keeps_islands_whole_apart_and_denser_than_xatlas(pad):
    masks = _masks()
    offsets, orient, side = pack_bitmap(masks, pad, 0, transpose=True)
    lab = _labels(masks, offsets, orient, side)
    cells = sum(int(m.sum()) for m in masks)
    assert (lab >= 0).sum() == cells and side >= start_side(masks, pad, 1.0) - 2 * pad
    isl = lab >= 0
    for i in range(len(masks)):  # the separation bilinear lookups need (as xatlas's packing gives)
        assert distance_transform_edt(lab != i)[isl & (lab != i)].min() >= 2 * pad - 1
    if pad == 2:  # interlocking arcs and rectangles: a tighter square than the outline packer's
        _, _, side_x = pack_islands(masks, pad, 0, transpose=True)
        assert side < side_x and cells / side ** 2 > 0.65, (side, side_x)


def test_bitmap_packing_without_transpose_keeps_every_orientation_and_fixed_sizes_fit_or_say_none():
    masks = _masks()
    offsets, orient, side = pack_bitmap(masks, 2, 0, transpose=False)
    assert (orient == 0).all()
    _labels(masks, offsets, orient, side)
    offsets, orient, got = pack_bitmap(masks, 2, side + 10, transpose=True)
    assert got == side + 10
    _labels(masks, offsets, orient, got)
    assert pack_bitmap(masks, 2, start_side(masks, 2, 1.0) // 2, transpose=True) is None
    assert pack_bitmap([np.ones((50, 3), bool)], 2, 40) is None  # longer than the image


def test_a_square_the_largest_first_order_cannot_fill_is_tried_with_the_other_orders():
    """Greedy placement depends on its order: 12 notched blobs the largest-first order cannot put into a 67² square
    go in with another of ORDERS, so the smallest square found shrinks (72² with that order alone), and the
    islands stay whole and apart."""
    from core.atlas.bitmap_pack import ORDERS
    rng = np.random.default_rng(1)
    masks = []
    for _ in range(12):
        h, w = rng.integers(3, 30, 2)
        m = rng.random((h, w)) < 0.85
        m[0, :] = m[:, 0] = True
        masks.append(m)
    assert pack_bitmap(masks, 2, 67, transpose=True, orders=ORDERS[:1]) is None
    assert pack_bitmap(masks, 2, 0, transpose=True, orders=ORDERS[:1])[2] == 72
    for size in (67, 0):
        offsets, orient, side = pack_bitmap(masks, 2, size, transpose=True)
        assert side <= 67
        lab = _labels(masks, offsets, orient, side)
        isl = lab >= 0
        for i in range(len(masks)):
            assert distance_transform_edt(lab != i)[isl & (lab != i)].min() >= 3
    with pytest.raises(InputError):
        pack_bitmap(masks, 2, 0, orders=())


def test_bitmap_packing_orients_asymmetric_islands_exactly():
    L = np.zeros((9, 6), bool)
    L[:, :2] = True
    L[-2:, :] = True
    masks = [L] * 6 + [np.ones((3, 3), bool)]
    offsets, orient, side = pack_bitmap(masks, 1, 0, transpose=True)
    lab = _labels(masks, offsets, orient, side)
    for i in range(len(masks)):  # each placed island is its mask under its symmetry: same cell count, shape kept
        sel = lab == i
        rr, cc = np.nonzero(sel)
        box = sel[rr.min():rr.max() + 1, cc.min():cc.max() + 1]
        syms = [np.rot90(m, k) for m in (masks[i], masks[i].T) for k in range(4)]
        assert box.sum() == masks[i].sum() and any(s.shape == box.shape and (s == box).all() for s in syms)
    assert len(set(orient[:6].tolist())) > 1  # the L shapes interlock in more than one orientation


def test_bitmap_packing_rejects_empty_input():
    with pytest.raises(InputError):
        pack_bitmap([], 2)
    with pytest.raises(InputError):
        pack_bitmap([np.zeros((3, 3), bool)], 2)


def _place_reference(shapes, order, S, g):
    """The reading-order placement by direct overlap tests at every spot (no FFT, no bands)."""
    occ = np.zeros((S + 2 * g, S + 2 * g), bool)
    offsets, orient = np.zeros((len(shapes), 2), np.int64), np.zeros(len(shapes), np.int64)
    for i in order:
        best = None
        for q, t, first, foot in shapes[i]:
            h, w = t.shape
            f = foot > 0.5
            spot = next(((r, c) for r in range(S - h + 1) for c in range(S - w + 1)
                         if not (occ[r:r + f.shape[0], c:c + f.shape[1]] & f).any()), None)
            if spot is not None and (best is None or spot < best[0]):
                best = (spot, q, first, f)
        if best is None:
            return None
        (r, c), q, first, f = best
        occ[r:r + f.shape[0], c:c + f.shape[1]] |= f
        offsets[i], orient[i] = np.array([c, r]) - first, q
    return offsets, orient


@pytest.mark.parametrize("seed", [1])
def test_banded_fft_placement_matches_a_direct_search(seed):
    from core.atlas import bitmap_pack as bp
    rng = np.random.default_rng(seed)
    masks = []
    for _ in range(14):  # blobs with holes and notches, some taller than a band
        h, w = rng.integers(3, 40, 2)
        m = rng.random((h, w)) < 0.8
        m[0, :] = m[:, 0] = True
        masks.append(m)
    g = 1
    shapes = bp._shapes(masks, g, transpose=True)
    order = list(range(len(masks)))
    fits = []
    for S in (90, 100, 130):  # too small; tight (several bands of rows); loose
        got, want = bp._place_all(shapes, order, S, g), _place_reference(shapes, order, S, g)
        assert (got is None) == (want is None)
        fits.append(got is not None)
        if got is not None:
            assert np.array_equal(got[0], want[0]) and np.array_equal(got[1], want[1])
    assert fits == [False, True, True]


def test_spots_the_rounded_fft_calls_free_are_checked_exactly(monkeypatch):
    """The overlap counts come from single-precision FFTs; a spot they call free by mistake (here: every count of
    one overlapping cell pushed below 0.5) is refused by the exact check, so the placement is still the direct
    search's."""
    from core.atlas import bitmap_pack as bp
    rng = np.random.default_rng(2)
    masks = [rng.random((h, w)) < 0.85 for h, w in rng.integers(4, 30, (10, 2))]
    for m in masks:
        m[0, :] = m[:, 0] = True
    g = 1
    shapes = bp._shapes(masks, g, transpose=True)
    order = list(range(len(masks)))
    real = bp._overlaps
    wrong = []

    def rounded_badly(*a, **k):
        out = real(*a, **k)
        bad = np.abs(out - 1) < 0.25
        wrong.append(int(bad.sum()))
        return np.where(bad, out - 0.7, out)

    monkeypatch.setattr(bp, "_overlaps", rounded_badly)
    got, want = bp._place_all(shapes, order, 70, g), _place_reference(shapes, order, 70, g)
    assert got is not None and want is not None and sum(wrong) > 0
    assert np.array_equal(got[0], want[0]) and np.array_equal(got[1], want[1])


def test_overlap_rows_and_free_spots_match_the_full_inverse_and_reading_order():
    """_overlaps keeps the first rows of the full 2-D inverse transform; _free_spots lists the entries below 0.5
    in the order np.nonzero gives them."""
    from scipy.fft import irfft2, rfft2

    from core.atlas import bitmap_pack as bp
    rng = np.random.default_rng(5)
    occ = (rng.random((45, 61)) < 0.4).astype(np.float32)
    foot = (rng.random((9, 7)) < 0.8).astype(np.float32)
    fh, fw = 48, 64
    product = rfft2(occ, (fh, fw)) * np.conj(rfft2(foot, (fh, fw)))
    full = irfft2(product, (fh, fw))
    for n, m in ((1, 5), (20, 55), (fh, fw)):
        assert np.allclose(bp._overlaps(product, fw, n, m), full[:n, :m], atol=1e-3)
    ov = np.where(rng.random((13, 17)) < 0.2, 0.0, 2.0)
    assert list(bp._free_spots(ov)) == [(int(r), int(c)) for r, c in zip(*np.nonzero(ov < 0.5))]
    assert list(bp._free_spots(np.ones((3, 4)))) == []
    assert list(bp._free_spots(np.zeros((2, 2)))) == [(0, 0), (0, 1), (1, 0), (1, 1)]


def test_longest_free_runs_per_row():
    from core.atlas.bitmap_pack import longest_runs
    rng = np.random.default_rng(4)
    a = rng.random((40, 23)) < 0.7
    a[0], a[1] = True, False

    def loop(row):
        best = run = 0
        for v in row:
            run = run + 1 if v else 0
            best = max(best, run)
        return best

    assert longest_runs(a).tolist() == [loop(r) for r in a]
    assert longest_runs(np.zeros((3, 0), bool)).tolist() == [0, 0, 0]
