"""Floaters (core/points/floaters.py): the graph's components, the mask against its definition, the fit's removal."""
import math

import pytest
import torch

import core.points.train as train_mod
from core.points.floaters import components, floater_mask
from core.points.neighbors.knn import point_knn
from core.points.train import fit_points
from tests.core.points.test_train import TINY_MODEL, _tiny_cfg, _two_views


def _sheet(n=30, step=0.1):
    g = torch.arange(n, dtype=torch.float64) * step
    x, y = torch.meshgrid(g, g, indexing="ij")
    return torch.stack([x.reshape(-1), y.reshape(-1), torch.zeros(n * n, dtype=torch.float64)], 1)


def _brute(xyz, size, radius):
    """The definition with all pairs: components of the graph of pairs closer than radius × the median nearest
    distance; points of components with fewer than `size` points."""
    d = torch.cdist(xyz, xyz)
    d.fill_diagonal_(math.inf)
    spacing = float(d.min(1).values.median())
    adj = d < radius * spacing
    lab = torch.arange(xyz.shape[0])
    while True:
        new = torch.where(adj, lab[None, :], lab[:, None]).min(1).values
        new = torch.minimum(new, lab)
        if torch.equal(new, lab):
            break
        lab = new
    return torch.bincount(lab, minlength=len(lab))[lab] < size


def test_components_of_a_chain_a_pair_and_a_single_point():
    # 0-1-2-3 a chain (edges listed one way only), 4-5 a pair, 6 alone
    idx = torch.tensor([[1, -1], [2, -1], [3, -1], [-1, -1], [5, -1], [-1, -1], [-1, -1]])
    edge = idx >= 0
    assert components(idx, edge).tolist() == [0, 0, 0, 0, 4, 4, 6]
    assert components(idx, torch.zeros_like(edge)).tolist() == list(range(7))  # no edges: every point alone


def test_specks_apart_from_a_sheet_are_floaters_and_nothing_else():
    sheet = _sheet()
    speck = torch.tensor([[1.5, 1.5, 1.0], [1.52, 1.5, 1.0], [1.5, 1.52, 1.0]], dtype=torch.float64)
    near = torch.tensor([[1.0, 1.0, 0.2]], dtype=torch.float64)  # 2 spacings above the sheet: joined to it
    blob = 3.0 + 0.05 * torch.randn(25, 3, generator=torch.Generator().manual_seed(0), dtype=torch.float64)
    xyz = torch.cat([sheet, speck, near, blob])
    mask = floater_mask(xyz, max_size=20, radius=3.0)
    want = torch.zeros(len(xyz), dtype=torch.bool)
    want[len(sheet):len(sheet) + 3] = True  # the speck; the 25-point blob is a part, not a floater
    assert torch.equal(mask, want)
    assert torch.equal(floater_mask(xyz, max_size=30, radius=3.0)[-25:], torch.ones(25, dtype=torch.bool))


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_mask_matches_the_definition_on_random_clouds(seed):
    g = torch.Generator().manual_seed(seed)
    base = _sheet(20) + 0.01 * torch.randn(400, 3, generator=g, dtype=torch.float64)
    stray = 4.0 * torch.rand(12, 3, generator=g, dtype=torch.float64) - 1.0  # scattered, some near the sheet
    xyz = torch.cat([base, stray])
    for size, radius in ((5, 2.0), (10, 3.0), (20, 5.0)):
        got = floater_mask(xyz, max_size=size, radius=radius, max_share=1.0)
        assert torch.equal(got, _brute(xyz, size, radius)), (size, radius)


def test_a_cloud_of_specks_loses_nothing_and_non_finite_points_stay():
    g = torch.Generator().manual_seed(3)
    scattered = 10.0 * torch.rand(200, 3, generator=g, dtype=torch.float64)  # no surface: all small groups
    assert not floater_mask(scattered).any()  # more than max_share would go: none does
    xyz = torch.cat([_sheet(), torch.tensor([[math.nan, 0.0, 0.0], [5.0, 5.0, 5.0]], dtype=torch.float64)])
    mask = floater_mask(xyz)
    assert not mask[-2] and mask[-1] and int(mask.sum()) == 1
    assert not floater_mask(xyz[:5]).any()  # fewer points than a group: nothing to tell apart
    dup = torch.zeros(100, 3)  # one position 100 times: no spacing
    assert not floater_mask(dup).any()


def test_point_knn_is_the_brute_force_knn():
    g = torch.Generator().manual_seed(4)
    xyz = torch.rand(300, 3, generator=g, dtype=torch.float64)
    idx, dist = point_knn(xyz, 6)
    d = torch.cdist(xyz, xyz)
    d.fill_diagonal_(math.inf)
    want_d, _ = d.topk(6, largest=False)
    assert torch.allclose(dist.double(), want_d, atol=1e-6)
    assert torch.allclose(d.gather(1, idx), want_d)


def test_the_fit_removes_its_floaters_unless_told_to_keep_them(monkeypatch):
    train, test = _two_views()
    hull = train_mod.visual_hull_points
    far = torch.tensor([[9.0, 9.0, 9.0], [9.01, 9.0, 9.0], [9.0, 9.01, 9.0]])

    def with_speck(*a, **kw):  # the hull's points and three more far from them, where no view looks
        return torch.cat([hull(*a, **kw), far])
    monkeypatch.setattr(train_mod, "visual_hull_points", with_speck)
    n = TINY_MODEL.num_points + 3
    model, hist = fit_points(train, test, TINY_MODEL, _tiny_cfg(steps=3), show_progress=False)
    assert hist[-1]["floaters_removed"] >= 3 and model.num_points == n - hist[-1]["floaters_removed"]
    assert not (model.xyz.detach() - far[0]).norm(dim=1).lt(1.0).any()
    assert model.features.shape[0] == model.influence.shape[0] == model.num_points
    kept, hist = fit_points(train, test, TINY_MODEL, _tiny_cfg(steps=3, keep_floaters=True), show_progress=False)
    assert kept.num_points == n and hist[-1]["floaters_removed"] == 0


def test_pruning_steps_remove_floaters_too(monkeypatch):
    """floaters_while_pruning (the default): every pruning step (10-70 % of training) drops the floaters, then the
    end does."""
    train, test = _two_views()
    hull = train_mod.visual_hull_points
    far = torch.tensor([[9.0, 9.0, 9.0], [9.01, 9.0, 9.0], [9.0, 9.01, 9.0]])
    monkeypatch.setattr(train_mod, "visual_hull_points", lambda *a, **kw: torch.cat([hull(*a, **kw), far]))
    calls = []

    def spy(xyz, *a):
        mask = floater_mask(xyz, *a)
        calls.append((xyz.shape[0], int(mask.sum()), bool((xyz - far[0]).norm(dim=1).lt(1.0).any())))
        return mask
    monkeypatch.setattr(train_mod, "floater_mask", spy)
    cfg = _tiny_cfg(steps=30, prune_every=10, floaters_while_pruning=True)
    model, hist = fit_points(train, test, TINY_MODEL, cfg, show_progress=False)
    assert len(calls) == 3  # the pruning steps at steps 10 and 20, then the end
    assert calls[0][2] and calls[0][1] >= 3  # the first pruning step saw the speck and dropped it
    assert not calls[1][2] and not calls[2][2]
    assert hist[-1]["floaters_removed"] == sum(c[1] for c in calls)  # the pruning steps' and the end's
    calls.clear()
    fit_points(train, test, TINY_MODEL, _tiny_cfg(steps=30, prune_every=10, floaters_while_pruning=False),
               show_progress=False)
    assert len(calls) == 1  # --no-floaters-while-pruning: the end only
