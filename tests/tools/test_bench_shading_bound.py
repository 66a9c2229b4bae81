"""tools/bench/shading_bound.py: the shading fit on synthetic points (the Blender side is eval-edits' ground truth,
tested there)."""
import torch

from tools.bench.shading_bound import fit_shading, reshade_factor, sh_basis


def _sphere(n=3000, seed=0):
    g = torch.Generator().manual_seed(seed)
    p = torch.nn.functional.normalize(torch.randn(n, 3, generator=g, dtype=torch.float64), dim=1)
    d = torch.cdist(p, p)
    nbr = d.topk(9, largest=False).indices[:, 1:]
    pairs = torch.stack([torch.arange(n)[:, None].expand_as(nbr).reshape(-1), nbr.reshape(-1)], 1)
    return p, pairs


def test_a_lit_sphere_gives_its_shading_back_and_an_unlit_one_none():
    """Patches of two paints (red, blue) under a light from +z: the fit recovers log S; the same paints unlit, laid
    out so that they follow the normal (red above, blue below), give no shading (the paint edge is another
    chromaticity); a paint in two brightnesses at random (dark flecks) barely moves it."""
    p, pairs = _sphere()
    true = torch.zeros(8, dtype=torch.float64)
    true[2] = 0.6  # log S = 0.6 z
    shade = torch.exp(sh_basis(p) @ true)
    paint = torch.where(p[:, :1] > 0, torch.tensor([0.8, 0.2, 0.1]), torch.tensor([0.1, 0.3, 0.9])).double()
    b, used = fit_shading(paint * shade[:, None], p, pairs)
    assert used > 1000 and torch.allclose(b, true, atol=0.02)
    layered = torch.where(p[:, 2:] > 0, torch.tensor([0.8, 0.2, 0.1]), torch.tensor([0.1, 0.3, 0.9])).double()
    b, _ = fit_shading(layered, p, pairs)
    assert float(b.abs().max()) < 1e-6
    g = torch.Generator().manual_seed(1)
    flecks = torch.where(torch.rand(p.shape[0], 1, generator=g) < 0.1, 0.2, 1.0).double() * torch.ones(1, 3)
    b, _ = fit_shading(flecks, p, pairs)
    assert float((sh_basis(p) @ b).abs().max()) < 0.1


def test_reshade_factor_is_one_at_rest_and_follows_a_turned_normal():
    b = torch.zeros(8, dtype=torch.float64)
    b[2] = 0.6
    n = torch.tensor([[0.0, 0.0, 1.0], [1.0, 0.0, 0.0]], dtype=torch.float64)
    dirs = -n  # seen head-on
    eye = torch.eye(3).expand(2, 3, 3)
    assert torch.allclose(reshade_factor(eye, n, dirs, b), torch.ones(2, dtype=torch.float64))
    turn = torch.tensor([[0.0, 0.0, -1.0], [0.0, 1.0, 0.0], [1.0, 0.0, 0.0]])  # z -> -x: the lit top turned aside
    r = reshade_factor(turn[None], n[:1], torch.tensor([[1.0, 0.0, 0.0]]), b)  # seen from -x, head-on
    assert torch.allclose(r, torch.exp(torch.tensor([-0.6], dtype=torch.float64)), atol=1e-6)
    # seen from behind (+x): the other side, whose rest normal faced -z, away from the light: brighter now
    r = reshade_factor(turn[None], n[:1], torch.tensor([[-1.0, 0.0, 0.0]]), b)
    assert torch.allclose(r, torch.exp(torch.tensor([0.6], dtype=torch.float64)), atol=1e-6)
    singular = reshade_factor(torch.zeros(1, 3, 3), n[:1], dirs[:1], b)
    assert float(singular) == 1.0
