"""The occlusion rule (core/edits/occlusion.py): a ray whose neighbours come from two parts of a folded surface
keeps the front part; one part however moved (rigid, stretched) is left alone; extreme inputs stay finite."""
import math

import torch

from core.edits.occlusion import front_layer
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
