"""Filling stretched regions (DeformationField.fill): nothing at rest, points on the stretched pairs' segments with
their canonical counterparts, each pair once, the budget kept, tears left open, finite on hostile input."""
import math

import pytest
import torch

from core.edits.deformation import DeformationConfig, DeformationField
from core.util.errors import InputError


def _sheet(n=16):
    u, v = torch.meshgrid(torch.linspace(-1, 1, n), torch.linspace(-1, 1, n), indexing="ij")
    return torch.stack([u.reshape(-1), v.reshape(-1), torch.zeros(n * n)], 1)


def _volume(n=400, seed=0):
    g = torch.Generator().manual_seed(seed)
    return torch.rand(n, 3, generator=g) * 2 - 1


@pytest.mark.parametrize("make", [_sheet, _volume])
def test_nothing_added_at_rest_or_under_a_rigid_motion(make):
    p = make()
    fld = DeformationField(p)
    new, can, src = fld.fill(p)
    assert new.shape == (0, 3) and can.shape == (0, 3) and src.shape == (0,)
    c, s = math.cos(0.8), math.sin(0.8)
    rot = torch.tensor([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])
    assert fld.fill(p @ rot.T + 5.0)[0].shape[0] == 0
    # a uniform compression pulls nothing apart either
    assert fld.fill(p * 0.3)[0].shape[0] == 0


@pytest.mark.parametrize("make", [_sheet, _volume])
def test_added_points_follow_an_affine_stretch_exactly(make):
    """Under d = A c + b the added points are A (their canonical points) + b, on the segment of their pair,
    spaced at most `ratio` times the canonical distance apart."""
    p = make()
    a = torch.tensor([[3.5, 0.4, 0.0], [0.0, 1.0, 0.2], [0.1, 0.0, 1.0]])
    b = torch.tensor([1.0, -2.0, 0.5])
    q = p @ a.T + b
    fld = DeformationField(p)
    new, can, src = fld.fill(q, ratio=1.5, budget=10.0)
    assert new.shape[0] > 0 and torch.isfinite(new).all() and torch.isfinite(can).all()
    assert torch.allclose(new, can @ a.T + b, atol=1e-4)
    # the source is the nearer end: its canonical point is within half the pair's canonical distance
    half = 0.5 * float(fld.scale.max()) + 1e-6
    assert bool(((can - p[src]).norm(dim=1) <= half).all())
    # each pair once: no point added twice from the same source (a grid's crossing diagonals may share a midpoint)
    d = torch.cdist(new, new) + torch.eye(new.shape[0]) * 1e9
    same = (d < 1e-6) & (src[:, None] == src[None, :])
    assert not bool(same.any())


def test_pair_counts_follow_the_growth_and_the_budget_holds():
    p = _sheet(12)
    fld = DeformationField(p)
    q = p * torch.tensor([4.0, 1.0, 1.0])  # x offsets grow 4×: ceil(4 / 1.5) - 1 = 2 points on an x pair
    new, can, _ = fld.fill(q, ratio=1.5, budget=100.0)
    n_x = new.shape[0]
    new2, _, _ = fld.fill(q, ratio=2.1, budget=100.0)  # ceil(4 / 2.1) - 1 = 1 on an x pair
    assert n_x > new2.shape[0] > 0
    m = p.shape[0]
    # one point short of the full fill: the ratio is raised, no further than needed (2.1 would do)
    budget = (n_x - 1) / m
    got = fld.fill(q, ratio=1.5, budget=budget)[0].shape[0]
    assert new2.shape[0] <= got <= budget * m
    for budget in (0.01, 0.05, 0.5):  # a uniform stretch fills all of a level or none of it
        assert fld.fill(q, ratio=1.5, budget=budget)[0].shape[0] <= budget * m
    assert fld.fill(q, ratio=1.5, budget=0.0)[0].shape[0] == 0
    # a pair along y only (offset (0, dy)) did not grow: every added point lies between x-separated points
    assert torch.isfinite(can).all()


def test_tears_are_left_open():
    """Half the sheet sent far away (a part detached, grown beyond max_stretch): no bridge across the gap."""
    p = _sheet(16)
    q = p.clone()
    right = p[:, 0] > 0
    q[right] += torch.tensor([1e3, 0.0, 0.0])
    new, _, _ = DeformationField(p).fill(q, ratio=1.5, budget=10.0)
    assert new.shape[0] == 0


def test_hostile_inputs_give_finite_points():
    p = _volume(300)
    fld = DeformationField(p)
    q = p * torch.tensor([5.0, 1.0, 1.0])
    q[::7] = float("nan")
    q[3::11] = 1e30
    q[5::13] = 0.0  # collapsed onto one point
    new, can, src = fld.fill(q, ratio=1.5, budget=4.0)
    assert new.shape[0] > 0
    assert torch.isfinite(new).all() and torch.isfinite(can).all()
    assert bool(torch.isfinite(q[src]).all())  # sources are present points
    assert float(new.abs().max()) < 1e3
    # every point absent: nothing to fill
    assert fld.fill(torch.full_like(p, float("nan")))[0].shape[0] == 0


def test_with_ids_duplicated_and_removed_points():
    p = _sheet(12)
    n = p.shape[0]
    ids = torch.cat([torch.arange(0, n, 2), torch.arange(n), torch.arange(5)])  # some twice, some thrice
    q = p[ids] * torch.tensor([3.0, 1.0, 1.0])
    fld = DeformationField(p)
    new, can, src = fld.fill(q, ids, ratio=1.5, budget=2.0)
    assert new.shape[0] > 0 and torch.isfinite(new).all()
    assert int(src.min()) >= 0 and int(src.max()) < q.shape[0]
    assert torch.allclose(new, can * torch.tensor([3.0, 1.0, 1.0]), atol=1e-4)


def test_gradients_and_fill_match_the_separate_calls():
    p = _volume(300)
    q = p * torch.tensor([3.0, 0.5, 1.0])
    fld = DeformationField(p, DeformationConfig(k=10))
    f, (new, can, src) = fld.gradients_and_fill(q, ratio=1.5, budget=3.0)
    assert torch.equal(f, fld.gradients(q))
    sep = fld.fill(q, ratio=1.5, budget=3.0)
    assert torch.equal(new, sep[0]) and torch.equal(can, sep[1]) and torch.equal(src, sep[2])


def test_bad_ratio_and_budget_are_refused():
    p = _sheet(6)
    fld = DeformationField(p)
    for kw in ({"ratio": 1.0}, {"ratio": float("nan")}, {"budget": -1.0}, {"budget": float("inf")}):
        with pytest.raises(InputError):
            fld.fill(p, **kw)


@pytest.mark.parametrize("make", [_sheet, _volume])
def test_partner_and_fraction_place_each_point_between_its_pair(make):
    """with_partner: every added point lies `fraction` of the way from its source to its partner (deformed and
    canonical), fraction in (0, 0.5] (the source is the nearer end); the first three outputs are the plain call's."""
    p = make()
    a = torch.tensor([[4.0, 0.3, 0.0], [0.0, 1.0, 0.0], [0.0, 0.2, 1.0]])
    q = p @ a.T
    fld = DeformationField(p)
    new, can, src, partner, frac = fld.fill(q, ratio=1.5, budget=10.0, with_partner=True)
    plain = fld.fill(q, ratio=1.5, budget=10.0)
    assert all(torch.equal(x, y) for x, y in zip((new, can, src), plain))
    assert new.shape[0] > 0 and partner.shape == src.shape == frac.shape
    assert bool((frac > 0).all()) and bool((frac <= 0.5).all()) and bool((partner != src).all())
    f = frac[:, None]
    assert torch.allclose(new, (1 - f) * q[src] + f * q[partner], atol=1e-4)
    assert torch.allclose(can, (1 - f) * p[src] + f * p[partner], atol=1e-5)
    # gradients_and_fill gives the same tuple
    _, both = fld.gradients_and_fill(q, ratio=1.5, budget=10.0, with_partner=True)
    assert all(torch.equal(x, y) for x, y in zip(both, (new, can, src, partner, frac)))


def test_partner_outputs_are_empty_where_nothing_stretched():
    p = _sheet(8)
    fld = DeformationField(p)
    for q in (p, p * 0.5, torch.full_like(p, float("nan"))):
        out = fld.fill(q, with_partner=True)
        assert len(out) == 5 and all(x.shape[0] == 0 for x in out)
    assert len(fld.fill(p, budget=0.0, with_partner=True)) == 5


def test_gap_is_what_the_budget_left_open():
    """with_gap: per point the largest growth left between consecutive points on its pairs: g / (n + 1) on a filled
    pair, g on one left as it is. A generous budget closes every pair to within the ratio (the 4×-stretched x
    pairs get 2 points each: 4 / 3 left, a diagonal pair one: 2.92 / 2); a tight one leaves them sparse; rest, a compression and a tear (beyond
    max_stretch) leave nothing grown."""
    p = _sheet(12)
    fld = DeformationField(p)
    q = p * torch.tensor([4.0, 1.0, 1.0])
    full = fld.fill(q, ratio=1.5, budget=100.0, with_gap=True)
    assert len(full) == 5 and bool((full[3] >= 1).all()) and float(full[3].max()) <= 1.5 + 1e-5
    assert float(full[3].min()) >= 4.0 / 3.0 - 1e-5  # every point has an x pair: 4 / 3 left on it at least
    half = fld.fill(p * torch.tensor([1.3, 1.0, 1.0]), ratio=1.5, budget=100.0, with_gap=True)
    assert half[0].shape[0] == 0 and math.isclose(float(half[3].max()), 1.3, rel_tol=1e-4)  # unfilled: its growth
    tight = fld.fill(q, ratio=1.5, budget=0.2, with_gap=True)
    gap = tight[3]
    assert tight[0].shape[0] <= 0.2 * p.shape[0]
    assert bool((gap >= 1).all()) and float(gap.max()) > 1.5 and float(gap.max()) <= 4.0 + 1e-5
    assert bool(((gap <= 1.5 + 1e-5) | (gap > 4.0 / 3.0)).all())
    _, both = fld.gradients_and_fill(q, ratio=1.5, budget=0.2, with_partner=True, with_gap=True)
    assert len(both) == 7 and torch.equal(both[5], gap) and torch.equal(both[6], tight[4])
    assert torch.equal(tight[4], torch.where(gap > 1.5, gap, torch.ones_like(gap)))  # sparse: above the ratio only
    for r in (p, p * 0.5, p * torch.tensor([100.0, 1.0, 1.0])):  # 100×: every x-offset pair tears
        out = fld.fill(r, ratio=1.5, budget=0.2, with_gap=True)
        assert torch.equal(out[-2], torch.ones(p.shape[0])) and torch.equal(out[-1], torch.ones(p.shape[0]))
    nan = fld.fill(torch.full_like(p, float("nan")), with_gap=True)
    assert torch.equal(nan[-2], torch.ones(p.shape[0])) and torch.equal(nan[-1], torch.ones(p.shape[0]))


def test_budget_gap_counts_only_pairs_the_budget_kept_sparse():
    """gap_pairs "budget": a pair grown past (max_per_pair + 1) × ratio (it got the most points a pair gets: a
    joint's near-tear) leaves no gap, while a pair the budget kept sparse keeps the gap "all" gives it."""
    p = _sheet(12)
    fld = DeformationField(p)
    q = p * torch.tensor([12.0, 1.0, 1.0])  # x pairs grow 12×: 7 points at ratio 1.5, capped at 2 → gap 4
    full = fld.fill(q, ratio=1.5, budget=100.0, max_per_pair=2, with_gap=True)
    near_tear = fld.fill(q, ratio=1.5, budget=100.0, max_per_pair=2, with_gap=True, gap_pairs="budget")
    assert float(full[-1].max()) > 3.9 and torch.equal(near_tear[-1], torch.ones(p.shape[0]))
    for a, b in zip(full[:-1], near_tear[:-1]):  # the points themselves do not depend on it
        assert torch.equal(a, b)
    q = p * torch.tensor([4.0, 1.0, 1.0])  # the budget, not the cap, keeps these sparse
    tight = fld.fill(q, ratio=1.5, budget=0.2, with_gap=True)
    tight_b = fld.fill(q, ratio=1.5, budget=0.2, with_gap=True, gap_pairs="budget")
    assert float(tight[-1].max()) > 1.5 and torch.equal(tight[-1], tight_b[-1])


def _plain_budget_ratio(g, ratio, cap, limit):
    """Reference: bisection over every distinct step g / i >= ratio for the smallest keeping the budget."""
    count = lambda r: (torch.ceil(g / r * (1.0 - 1e-12)) - 1.0).clamp(0, cap).long()  # noqa: E731
    steps = g[:, None] / torch.arange(1, cap + 1, dtype=g.dtype)
    cands = sorted(set(steps[steps >= ratio].tolist()))
    return next(c for c in cands if int(count(c).sum()) <= limit)


def _torch_budget_ratio(g, ratio, cap, limit):
    from core.edits.deformation import _budget_ratio

    count = lambda r: (torch.ceil(g / r * (1.0 - 1e-12)) - 1.0).clamp(0, cap).long()  # noqa: E731
    return _budget_ratio(g, ratio, cap, limit, count)


def _compiled_budget_ratio(g, ratio, cap, limit):
    pytest.importorskip("numba")
    from core.edits.deformation import _fill_budget_ratio_c

    return _fill_budget_ratio_c(g.numpy(), ratio, cap, limit)


@pytest.mark.parametrize("seed", [0, 1, 2])
@pytest.mark.parametrize("impl", [_torch_budget_ratio, _compiled_budget_ratio], ids=["torch", "compiled"])
def test_budget_ratio_equals_the_plain_bisection(seed, impl):
    """The torch budget ratio (partial sort, checked; bisection where the check fails) and the compiled one
    (quickselect above a floor, checked; a walk to the next step where the check fails) pick the same step as a
    bisection over every distinct step, ties included."""
    gen = torch.Generator().manual_seed(seed)
    g = 1.0 + 9.0 * torch.rand(500, generator=gen, dtype=torch.float64)
    g[:100] = 4.0  # ties: one growth shared by many pairs (a uniform stretch)
    g[100:110] = 12.0 / 7.0
    for cap in (1, 3, 8):
        count = lambda r: (torch.ceil(g / r * (1.0 - 1e-12)) - 1.0).clamp(0, cap).long()  # noqa: E731
        full = int(count(1.5).sum())
        for limit in (0, 1, 7, 99, 100, 101, 350, full // 2, full - 1):
            assert impl(g, 1.5, cap, limit) == _plain_budget_ratio(g, 1.5, cap, limit)


@pytest.mark.parametrize("seed", [0, 3])
def test_fill_with_cached_reverse_lists_equals_the_generic_pairing(seed):
    """The canonical points' own neighbour lists (no ids) find each pair's other side in a cached table; the
    generic pairing (any rows, as with ids) gives the same points, exactly, budget hit or not, with holes."""
    gen = torch.Generator().manual_seed(seed)
    p = _volume(600, seed)
    q = p * torch.tensor([5.0, 1.0, 1.0]) + 0.3 * torch.sin(4 * p) * torch.rand(600, 1, generator=gen)
    q[7] = float("nan")  # a missing point: its pairs carry no weight
    fld = DeformationField(p)
    g = fld._gather_deformed(q, None, with_rows=True)
    for budget in (0.2, 1.0, 10.0):
        fast = fld._fill(q, g, 1.5, 8, budget, True, True, canonical_rows=True)
        plain = fld._fill(q, g, 1.5, 8, budget, True, True, canonical_rows=False)
        assert fast[0].shape[0] > 0
        for a, b in zip(fast, plain):
            assert torch.equal(a, b)
    # the table itself: l = nbr[j, s] lists j at slot reverse_slots[j, s]
    rev, nb = fld.reverse_slots, fld.nbr
    j, s = torch.nonzero(rev >= 0, as_tuple=True)
    assert torch.equal(nb[nb[j, s], rev[j, s]], j)
    j, s = torch.nonzero((rev < 0) & (nb >= 0), as_tuple=True)
    assert not bool((nb[nb[j, s]] == j[:, None]).any())


def test_tear_growth_leaves_pairs_grown_past_it_open():
    """tear: pairs grown by more than it get no points and leave no gap (as past max_stretch); pairs below it are
    filled exactly as without it; None and any value at or above max_stretch are the plain call; <= 1 is refused."""
    p = _sheet(12)
    fld = DeformationField(p)
    q = p * torch.tensor([14.0, 1.0, 1.0])  # x pairs grow 14×, diagonals ~9.9×: both below max_stretch (20)
    plain = fld.fill(q, ratio=1.5, budget=100.0, with_partner=True, with_gap=True)
    for tear in (None, 20.0, 50.0):
        out = fld.fill(q, ratio=1.5, budget=100.0, with_partner=True, with_gap=True, tear=tear)
        assert all(torch.equal(a, b) for a, b in zip(out, plain))
    torn = fld.fill(q, ratio=1.5, budget=100.0, with_partner=True, with_gap=True, tear=12.0)
    assert 0 < torn[0].shape[0] < plain[0].shape[0]
    d = (p[torn[3]] - p[torn[2]]).abs()  # the pairs still filled: diagonals (both offsets), no pure x pair
    assert bool((d[:, 1] > 1e-6).all())
    assert float(torn[5].max()) <= 1.5 + 1e-5  # what was filled is closed; the x pairs count as torn
    nothing = fld.fill(q, ratio=1.5, budget=100.0, with_gap=True, tear=1.2)
    assert nothing[0].shape[0] == 0 and torch.equal(nothing[-2], torch.ones(p.shape[0]))
    _, both = fld.gradients_and_fill(q, ratio=1.5, budget=100.0, with_partner=True, with_gap=True, tear=12.0)
    assert all(torch.equal(a, b) for a, b in zip(both, torn))
    for bad in (1.0, float("nan")):
        with pytest.raises(InputError):
            fld.fill(q, tear=bad)


@pytest.mark.parametrize("seed", [0, 1])
def test_compiled_fill_equals_the_torch_path(seed, monkeypatch):
    """The compiled fill (numba, CPU) gives the torch path's points, sources, partners, fractions, gaps and sparse
    gaps bit for bit: the cached neighbour lists and ids (duplicated and removed points), budgets hit or not,
    ties, tears, missing points, every option."""
    pytest.importorskip("numba")
    import core.edits.deformation as deformation

    gen = torch.Generator().manual_seed(seed)
    p = _volume(500, seed)
    bend = 0.3 * torch.sin(4 * p) * torch.rand(500, 1, generator=gen)
    cases = [(p * torch.tensor([5.0, 1.0, 1.0]) + bend, None),
             (p * torch.tensor([3.0, 3.0, 1.0]), None),  # a uniform stretch: many equal growths
             (torch.where(p[:, :1] > 0, p * torch.tensor([9.0, 1.0, 1.0]), p), None)]  # a joint-like tear
    q = cases[0][0].clone()
    q[7] = float("nan")  # a missing point
    cases.append((q, None))
    ids = torch.cat([torch.arange(500)[torch.arange(500) % 7 != 3], torch.arange(0, 500, 5)])  # removed, copies
    cases.append((cases[0][0][ids] + 0.01 * torch.rand(ids.shape[0], 3, generator=gen), ids))
    fld = DeformationField(p)
    options = [dict(ratio=1.5, max_per_pair=8, budget=b, gap_pairs=gp) for b in (0.2, 1.0, 10.0)
               for gp in ("all", "budget")]
    options += [dict(ratio=1.3, max_per_pair=3, budget=0.5, tear=6.0, gap_pairs="budget"),
                dict(ratio=2.2, max_per_pair=1, budget=1.0)]
    compiled = deformation._fill_compiled(p)
    assert compiled is not None
    for q, ids in cases:
        g = fld._gather_deformed(q, ids, with_rows=True)
        for kw in options:
            for partner, gap in ((True, True), (False, False)):
                args = (q, g, kw["ratio"], kw["max_per_pair"], kw["budget"], partner, gap)
                rest = dict(canonical_rows=ids is None, gap_pairs=kw.get("gap_pairs", "all"), tear=kw.get("tear"))
                fast = fld._fill(*args, **rest)
                monkeypatch.setattr(deformation, "_fill_compiled", lambda pts: None)
                ref = fld._fill(*args, **rest)
                monkeypatch.setattr(deformation, "_fill_compiled", lambda pts: compiled)
                assert len(fast) == len(ref)
                for a, b in zip(fast, ref):
                    assert a.dtype == b.dtype and torch.equal(a, b)
    assert ref[0].shape[0] > 0


def test_compiled_selection_helpers_match_plain_numpy():
    """The budget ratio's quickselect (ties included) and its next-step walk in both directions, against numpy."""
    pytest.importorskip("numba")
    import numpy as np

    from core.edits.deformation import _fill_next_step_c, _kth_smallest_c

    rng = np.random.default_rng(0)
    for n in (1, 2, 7, 500):
        a = np.round(rng.random(n) * 20) / 4  # many equal values
        for k in {0, n // 2, n - 1}:
            b = a.copy()
            assert _kth_smallest_c(b, n, k) == np.sort(a)[k]
            assert sorted(b) == sorted(a)  # reordered, nothing lost
    g = 1.0 + 9.0 * rng.random(300)
    g[:50] = 4.0
    steps = np.unique([x / i for x in g for i in range(1, 9) if x / i >= 1.5])
    for r in (steps[0], steps[len(steps) // 2], steps[-1], 3.0):
        up, down = steps[steps > r], steps[steps < r]
        assert _fill_next_step_c(g, r, 1.5, 8, True) == (up[0] if len(up) else -1.0)
        assert _fill_next_step_c(g, r, 1.5, 8, False) == (down[-1] if len(down) else -1.0)


@pytest.mark.parametrize("compiled", [True, False])
def test_huge_budgets_and_caps_are_the_largest_that_matter(compiled, monkeypatch):
    """A budget or a per-pair cap far beyond what any pair can take (1e300, 10**30) gives the points a merely large
    one gives, on the compiled path and the torch path alike (no overflow, no giant allocation)."""
    import core.edits.deformation as deformation

    if not compiled:
        monkeypatch.setattr(deformation, "_fill_compiled", lambda pts: None)
    p = _volume(300, 2)
    q = p * torch.tensor([6.0, 1.0, 1.0])
    fld = DeformationField(p)
    huge = fld.fill(q, ratio=1.5, budget=1e300, max_per_pair=10 ** 30, with_partner=True, with_gap=True,
                    gap_pairs="budget")
    large = fld.fill(q, ratio=1.5, budget=100.0, max_per_pair=100, with_partner=True, with_gap=True,
                     gap_pairs="budget")
    assert huge[0].shape[0] > 0 and all(torch.equal(a, b) for a, b in zip(huge, large))
