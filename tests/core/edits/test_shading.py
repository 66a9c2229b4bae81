"""core/edits/shading.py: the shading fit on synthetic points, the re-shading factor, and the renderer's reshade
setting on a tiny model (the Blender side of tools/bench/shading_bound.py is eval-edits' ground truth, tested
there)."""
import pytest
import torch

from core.edits.shading import fit_shading, reshade_factor, sh_basis


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


@pytest.fixture(scope="module")
def tiny():
    from tests.helpers.tiny import tiny_bundle

    bundle, _, test = tiny_bundle("fast")
    return bundle, test


def test_atlas_shading_is_fitted_once_per_atlas_and_finite(tiny):
    from core.edits.shading import atlas_shading

    bundle, _ = tiny
    first = atlas_shading(bundle)
    assert first is not None and first.b.shape == (8,) and bool(torch.isfinite(first.b).all())
    assert first.log_range >= 0.0 and atlas_shading(bundle) is first  # cached on the atlas


def test_reshade_leaves_rest_frames_and_off_alone_and_keeps_moved_frames_finite(tiny):
    """reshade on: a rest frame is the same frame (nothing moved); a turned model's frame differs from the plain
    one only on the object, stays finite and in range, and says how many rays it re-shaded; auto with a threshold
    above the model's fitted range changes nothing."""
    import math

    import core.frames.edited as edited
    from core.edits.shading import atlas_shading
    from core.frames.edited import EditConfig, EditState, render_edited
    from tests.stability.frame_checks import check_frame

    bundle, test = tiny
    view = (test.c2w[0], test.height, test.width, test.focal)
    rest = render_edited(EditState(bundle), *view)
    rest_on = render_edited(EditState(bundle, cfg=EditConfig(reshade="on")), *view)
    assert torch.equal(rest["rgb"], rest_on["rgb"]) and rest_on["stats"]["reshaded_rays"] == 0
    xyz = bundle.model.xyz.detach()
    a = math.radians(60)  # a turn about x: every normal changes
    rot = torch.tensor([[1.0, 0.0, 0.0], [0.0, math.cos(a), -math.sin(a)], [0.0, math.sin(a), math.cos(a)]])
    turned = (xyz - xyz.mean(0)) @ rot.T + xyz.mean(0)
    plain = render_edited(EditState(bundle, points=turned), *view)
    on = render_edited(EditState(bundle, points=turned, cfg=EditConfig(reshade="on")), *view)
    check_frame(on, test.height, test.width)
    assert on["stats"]["reshaded_rays"] > 0 and plain["stats"]["reshaded_rays"] == 0
    assert torch.equal(on["alpha"], plain["alpha"])  # coverage is not touched
    off_object = on["alpha"] < 1e-4
    assert torch.equal(on["rgb"][off_object], plain["rgb"][off_object])
    if atlas_shading(bundle).log_range > 0:
        assert not torch.equal(on["rgb"], plain["rgb"])
    saved = edited.RESHADE_MIN_RANGE
    try:
        edited.RESHADE_MIN_RANGE = atlas_shading(bundle).log_range + 1.0
        auto = render_edited(EditState(bundle, points=turned, cfg=EditConfig(reshade="auto")), *view)
    finally:
        edited.RESHADE_MIN_RANGE = saved
    assert torch.equal(auto["rgb"], plain["rgb"]) and auto["stats"]["reshaded_rays"] == 0
