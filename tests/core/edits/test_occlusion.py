"""The occlusion rule (core/edits/occlusion.py): a ray whose neighbours come from two parts of a folded surface
keeps the front part; one part however moved (rigid, stretched) is left alone; extreme inputs stay finite."""
import math

import pytest
import torch

from core.edits.occlusion import front_anchors, front_layer, unoccluded
from core.points.trace import Trace

SPACING = 0.1


def _sheet(z: float, n: int = 5) -> torch.Tensor:
    """n × n points of a sheet at height z around the z axis, SPACING apart: [n², 3]."""
    g = (torch.arange(n, dtype=torch.float32) - (n - 1) / 2) * SPACING
    x, y = torch.meshgrid(g, g, indexing="ij")
    return torch.stack([x.reshape(-1), y.reshape(-1), torch.full((n * n,), z)], 1)


def _trace(points: torch.Tensor, weights: torch.Tensor, bg: float = 0.2) -> Trace:
    """One ray straight down the z axis from z = 5, every point its neighbour with fg weights `weights` [M]."""
    m = points.shape[0]
    fg = (weights / weights.sum())[None]
    o, d = torch.tensor([[0.0, 0.0, 5.0]]), torch.tensor([[0.0, 0.0, -1.0]])
    return Trace(origins=o, dirs=d, idx=torch.arange(m)[None], weights=fg * (1 - bg), fg_weights=fg,
                 bg=torch.tensor([bg]), x=(fg[..., None] * points[None]).sum(1), active=torch.tensor([True]),
                 shape=(1, 1))


def _fold():
    """A front sheet (canonical = where it is) over a back sheet 5 spacings below it that came from 3 units away
    along x (a part folded under the front one); each part moved rigidly (F = I)."""
    front, back = _sheet(0.0), _sheet(-5 * SPACING)
    points = torch.cat([front, back])
    p_can = torch.cat([front, back + torch.tensor([3.0, 0.0, 5 * SPACING])])
    return points, p_can, torch.eye(3).expand(points.shape[0], 3, 3)


def test_a_fold_keeps_the_front_part():
    points, p_can, inv_f = _fold()
    n = points.shape[0] // 2
    w = torch.cat([torch.ones(n), 2 * torch.ones(n)])  # the back part outweighs the front one 2:1
    tr = _trace(points, w)
    out = front_layer(tr, points, p_can, inv_f, SPACING)
    assert float(out.fg_weights[0, n:].abs().max()) == 0.0
    assert torch.allclose(out.fg_weights[0, :n], torch.full((n,), 1.0 / n))
    assert torch.allclose(out.weights.sum(1), tr.weights.sum(1))  # coverage kept
    assert torch.equal(out.bg, tr.bg)
    assert abs(float(out.x[0, 2])) < 1e-6 and float(tr.x[0, 2]) < -0.3  # x̂ on the front sheet again


def test_a_thin_edge_in_front_is_kept_and_the_part_behind_the_surface_dropped():
    """A part's edge (one point, little weight) passes in front: it is no surface of the ray's own, so it stays as
    it is; the first layer with enough weight is the surface, and the part behind it goes."""
    points, p_can, inv_f = _fold()
    n = points.shape[0] // 2
    edge = torch.tensor([[0.05, 0.0, 0.5]])
    points = torch.cat([edge, points])
    p_can = torch.cat([edge + torch.tensor([-3.0, 0.0, 0.0]), p_can])
    inv_f = torch.eye(3).expand(points.shape[0], 3, 3)
    w = torch.cat([torch.tensor([0.5]), torch.ones(n), torch.ones(n)])
    tr = _trace(points, w)
    out = front_layer(tr, points, p_can, inv_f, SPACING)
    assert float(out.fg_weights[0, 1 + n:].abs().max()) == 0.0
    assert float(out.fg_weights[0, 0]) > 0 and float(out.fg_weights[0, 1:1 + n].min()) > 0
    assert torch.allclose(out.fg_weights.sum(1), torch.ones(1))


def test_one_part_however_moved_is_left_alone():
    """Two stacked layers of ONE part (canonical = a thick slab) under a rigid rotation + translation and under a
    3× stretch with its exact F: every neighbour is in every other's layer, the trace comes back unchanged."""
    slab = torch.cat([_sheet(0.0), _sheet(-2 * SPACING)])
    w = torch.rand(slab.shape[0], generator=torch.Generator().manual_seed(0)) + 0.1
    c, s = math.cos(0.7), math.sin(0.7)
    rot = torch.tensor([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])
    stretch = torch.diag(torch.tensor([3.0, 1.0, 1.0]))
    for f in (rot, stretch, torch.eye(3)):
        points = slab @ f.T + torch.tensor([0.0, 0.0, 0.3])
        tr = _trace(points, w)
        out = front_layer(tr, points, slab, torch.linalg.inv(f).expand(slab.shape[0], 3, 3), SPACING)
        assert out is tr or (torch.equal(out.fg_weights, tr.fg_weights) and torch.equal(out.x, tr.x))


def test_extreme_inputs_stay_finite():
    """Non-finite and huge positions, empty slots, rays without neighbours: finite weights summing as before."""
    points, p_can, inv_f = _fold()
    points = points.clone()
    points[0] = float("nan")
    points[1] = 1e30
    n = points.shape[0]
    tr = _trace(torch.nan_to_num(points, nan=0.0), torch.ones(n))
    idx = tr.idx.clone()
    idx[0, 2] = -1
    fg = tr.fg_weights.clone()
    fg[0, 2] = 0.0
    tr = Trace(origins=tr.origins.repeat(2, 1), dirs=tr.dirs.repeat(2, 1), idx=torch.cat([idx, torch.full_like(idx, -1)]),
               weights=torch.cat([tr.weights, torch.zeros_like(tr.weights)]), fg_weights=torch.cat([fg, fg * 0]),
               bg=torch.tensor([0.2, 1.0]), x=tr.x.repeat(2, 1), active=torch.tensor([True, False]), shape=(1, 2))
    out = front_layer(tr, points, p_can, inv_f, SPACING)
    assert torch.isfinite(out.fg_weights).all() and torch.isfinite(out.weights).all() and torch.isfinite(out.x).all()
    assert torch.allclose(out.weights.sum(1) + out.bg, torch.ones(2), atol=1e-5)


def _noisy_three_parts(g: torch.Generator):
    """The fold's two layers plus an edge in front of them, positions jittered and a random near-identity inverse
    gradient per point: points [M, 3], p_can [M, 3], inv_f [M, 3, 3]."""
    points, p_can, _ = _fold()
    edge = _sheet(0.4, 3) + torch.tensor([0.3, 0.0, 0.0])
    points = torch.cat([points, edge]) + 0.02 * torch.randn(points.shape[0] + edge.shape[0], 3, generator=g)
    p_can = torch.cat([p_can, edge - torch.tensor([3.0, 0.0, 0.0])])
    inv_f = torch.eye(3) + 0.1 * torch.randn(points.shape[0], 3, 3, generator=g)
    return points, p_can, inv_f


def _random_lists(m: int, rows: int, cols: int, empty: float, g: torch.Generator) -> torch.Tensor:
    """rows lists of cols distinct point indices in [0, m), each slot -1 (empty) with probability `empty`:
    [rows, cols] int64."""
    lists = torch.stack([torch.randperm(m, generator=g)[:cols] for _ in range(rows)])
    lists[torch.rand(rows, cols, generator=g) < empty] = -1
    return lists


def test_compiled_and_torch_keep_the_same_neighbours():
    """Many rays over a noisy fold (three layers: front, back, an edge in front) with random neighbour lists and
    weights: the compiled walk keeps exactly the neighbours the torch reference keeps."""
    pytest.importorskip("numba")
    g = torch.Generator().manual_seed(1)
    points, p_can, inv_f = _noisy_three_parts(g)
    m = points.shape[0]
    r, k = 300, 12
    idx = _random_lists(m, r, k, 0.1, g)
    w = torch.rand(r, k, generator=g) * (idx >= 0)
    fg = w / w.sum(1, keepdim=True).clamp_min(1e-12)
    xy = 0.2 * torch.randn(r, 2, generator=g)
    tr = Trace(origins=torch.cat([xy, torch.full((r, 1), 5.0)], 1), dirs=torch.tensor([[0.0, 0.0, -1.0]]).repeat(r, 1),
               idx=idx, weights=0.8 * fg, fg_weights=fg, bg=torch.full((r,), 0.2), x=torch.zeros(r, 3),
               active=torch.ones(r, dtype=torch.bool), shape=(1, r))
    a = front_layer(tr, points, p_can, inv_f, SPACING, backend="torch")
    b = front_layer(tr, points, p_can, inv_f, SPACING, backend="compiled")
    changed = (a.fg_weights != tr.fg_weights).any(1)
    assert int(changed.sum()) > 20  # the walk ran and dropped layers on many rays
    assert torch.equal(a.fg_weights, b.fg_weights) and torch.equal(a.x, b.x) and torch.equal(a.weights, b.weights)


def test_unoccluded_takes_the_first_k_candidates_the_front_layer_does_not_hide():
    points, p_can, inv_f = _fold()
    n = points.shape[0] // 2
    # ranked candidates of one ray: back, front, back, front, front, none; anchor = the first front point
    cand = torch.tensor([[n, 0, n + 1, 1, 2, -1]])
    o, d = torch.tensor([[0.0, 0.0, 5.0]]), torch.tensor([[0.0, 0.0, -1.0]])
    depth = torch.tensor([5.0])
    got = unoccluded(cand, torch.tensor([0]), depth, o, d, points, p_can, inv_f, SPACING, k=2)
    assert got.tolist() == [[0, 1]]
    got = unoccluded(cand, torch.tensor([0]), depth, o, d, points, p_can, inv_f, SPACING, k=5)
    assert got.tolist() == [[0, 1, 2, -1, -1]]
    # a hidden-part point in front of the anchor is no longer hidden: kept in its rank
    got = unoccluded(cand, torch.tensor([0]), torch.tensor([6.0]), o, d, points, p_can, inv_f, SPACING, k=5)
    assert got.tolist() == [[n, 0, n + 1, 1, 2]]


def test_unoccluded_compiled_equals_torch():
    """Random ranked candidate lists (gaps, none at all) over three noisy parts, random anchors and depths: the
    compiled choice takes exactly the candidates the torch reference takes."""
    pytest.importorskip("numba")
    g = torch.Generator().manual_seed(4)
    points, p_can, inv_f = _noisy_three_parts(g)
    m = points.shape[0]
    s, c = 300, 16
    cand = _random_lists(m, s, c, 0.15, g)
    cand[:3] = -1
    anchor = cand.clamp_min(0)[:, 0]
    o = torch.cat([0.2 * torch.randn(s, 2, generator=g), torch.full((s, 1), 5.0)], 1)
    d = torch.tensor([[0.0, 0.0, -1.0]]).repeat(s, 1)
    depth = 5.0 + 0.3 * torch.randn(s, generator=g)
    for k in (4, 8, 20):
        a = unoccluded(cand, anchor, depth, o, d, points, p_can, inv_f, SPACING, k, backend="torch")
        b = unoccluded(cand, anchor, depth, o, d, points, p_can, inv_f, SPACING, k, backend="compiled")
        assert torch.equal(a, b)
    # k = 20 >= 16 candidates: every candidate the front layer does not hide is taken, and some were hidden
    assert 0 < int((a >= 0).sum()) < int((cand >= 0).sum())
    assert (a[:3] == -1).all()


@pytest.mark.parametrize("backend", ["torch", "compiled"])
def test_front_anchors_skip_rays_whose_hidden_share_is_below_min_hidden(backend):
    """The back part holds 3 % of the ray's weight: with min_hidden 0.05 the ray is not worth searching again
    (None), with 0.02 or 0 it is, and the anchor is a front-sheet point at its depth."""
    if backend == "compiled":
        pytest.importorskip("numba")
    points, p_can, inv_f = _fold()
    n = points.shape[0] // 2
    w = torch.cat([torch.full((n,), 0.97 / n), torch.full((n,), 0.03 / n)])
    tr = _trace(points, w)
    assert front_anchors(tr, points, p_can, inv_f, SPACING, backend=backend, min_hidden=0.05) is None
    for mh in (0.0, 0.02):
        rows, anchor, depth, keep = front_anchors(tr, points, p_can, inv_f, SPACING, backend=backend, min_hidden=mh)
        assert rows.tolist() == [0] and int(anchor[0]) < n and abs(float(depth[0]) - 5.0) < 1e-5
        assert keep[0, :n].all() and not keep[0, n:].any()
