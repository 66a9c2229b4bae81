"""Extreme and stiff deformations through the whole edited render (render_edited on a tiny trained model with a
painted atlas, so neighbours, attention, correspondence and atlas lookups all run): every output finite, images
and alpha in [0, 1]."""
import math

import pytest
import torch

from core.edits.bake import bake
from core.frames.edited import EditState, render_edited
from core.images.cameras import look_at
from tests.helpers.tiny import tiny_bundle
from tests.stability.frame_checks import check_frame

pytestmark = pytest.mark.stability


@pytest.fixture(scope="module")
def tiny():
    bundle, train, test = tiny_bundle("fast")
    painted = bake(bundle.atlas, lambda x: (torch.stack([(x[:, 0] > 0).float(), 0.2 + 0 * x[:, 0],
                                                         (x[:, 1] > 0).float()], 1), None))
    return bundle, test, painted


def _twist(p, turns):
    a = 2 * math.pi * turns * (p[:, 1] - p[:, 1].min()) / (p[:, 1].max() - p[:, 1].min()).clamp_min(1e-9)
    c, s = torch.cos(a), torch.sin(a)
    return torch.stack([c * p[:, 0] + s * p[:, 2], p[:, 1], -s * p[:, 0] + c * p[:, 2]], 1)


def _fold(p):
    """Bend by 180° about the y axis: the card's two halves end up facing each other."""
    r = (p[:, 0].max() - p[:, 0].min()) / math.pi
    a = (p[:, 0] - p[:, 0].min()) / r
    return torch.stack([r * torch.sin(a) + p[:, 2] * torch.sin(a), p[:, 1], r * (1 - torch.cos(a)) + p[:, 2]], 1)


def _far(p, value, frac=0.3):
    q = p.clone()
    q[: int(frac * len(q))] = value
    return q


def _nonfinite(p):
    q = p.clone()
    n = len(q)
    q[: n // 6, 0] = float("nan")
    q[n // 6: n // 3, 1] = float("inf")
    q[n // 3: n // 2, 2] = float("-inf")
    return q


DEFORMS = {
    "twist_360": lambda p: _twist(p, 1.0),
    "fold_180": _fold,
    "squash_to_zero_thickness": lambda p: p * torch.tensor([1.0, 1.0, 1e-7]),
    "stretch_5x": lambda p: p * torch.tensor([5.0, 1.0, 1.0]),
    "coincident_pairs": lambda p: p[torch.arange(len(p)) // 2 * 2],
    "all_coincident_but_one": lambda p: torch.cat([p[:1].expand(len(p) - 1, 3), p[1:2]]),
    "far_away_1e6": lambda p: _far(p, 1e6),
    "far_away_1e30": lambda p: _far(p, 1e30),
    "all_far_away_1e30": lambda p: _far(p, 1e30, frac=1.0),
    "nan_and_inf": _nonfinite,
    "all_nan": lambda p: torch.full_like(p, float("nan")),
    "collapse_to_plane": lambda p: p * torch.tensor([1.0, 0.0, 1.0]),
    "collapse_to_point": lambda p: torch.zeros_like(p) + torch.tensor([0.1, -0.2, 0.05]),
    "float16_input": lambda p: p.half(),
    "denormal_offsets": lambda p: p * 1e-39 + torch.tensor([0.0, 0.0, 1e-40]),
    "mirror": lambda p: p * torch.tensor([-1.0, 1.0, 1.0]),  # every neighbourhood inverted
    "torn_by_jitter": lambda p: p + 0.5 * torch.randn(p.shape, generator=torch.Generator().manual_seed(0)),
    "stretch_5x_with_nan": lambda p: _nonfinite(p * torch.tensor([5.0, 1.0, 1.0])),
}

# (ids from the model's point count n, the deformation of the points they pick)
ID_CASES = {
    "duplicated_then_stretched": (lambda n: torch.cat([torch.arange(n), torch.arange(n)]),
                                  lambda p: p * torch.tensor([5.0, 1.0, 1.0])),
    "half_removed_then_folded": (lambda n: torch.arange(0, n, 2), _fold),
    "reversed_then_squashed": (lambda n: torch.arange(n - 1, -1, -1), lambda p: p * torch.tensor([1.0, 1.0, 1e-6])),
    "one_point_many_times": (lambda n: torch.zeros(64, dtype=torch.long),
                             lambda p: p + torch.linspace(0, 1, 64)[:, None]),
}


@pytest.mark.parametrize("name", list(DEFORMS))
def test_extreme_deformations_render_finite_frames(tiny, name):
    bundle, test, painted = tiny
    pts = DEFORMS[name](bundle.model.xyz.detach())
    state = EditState(bundle, points=pts, atlas=painted)
    for i in range(len(test)):
        out = render_edited(state, test.c2w[i], test.height, test.width, test.focal)
        check_frame(out, test.height, test.width)
    if name in ("nan_and_inf", "all_nan"):
        assert out["stats"]["non_finite_points"] == state.non_finite_points > 0
    if name in ("all_nan", "all_far_away_1e30"):
        assert float(out["alpha"].max()) == 0.0  # nothing left to draw: a clean background frame


@pytest.mark.parametrize("name", list(ID_CASES))
def test_extreme_deformations_of_added_or_removed_points_render_finite_frames(tiny, name):
    """Points removed, duplicated or reordered (ids), then deformed hard: F, the fill and the correspondence work
    on the points' canonical ids; every frame finite."""
    bundle, test, painted = tiny
    make_ids, deform = ID_CASES[name]
    ids = make_ids(bundle.model.num_points)
    state = EditState(bundle, points=deform(bundle.model.xyz.detach()[ids]), ids=ids, atlas=painted)
    for i in range(len(test)):
        check_frame(render_edited(state, test.c2w[i], test.height, test.width, test.focal), test.height, test.width)


def test_mirrored_points_through_a_mirrored_camera_give_the_frame_flipped(tiny):
    """Sensible, not only finite, where every neighbourhood is inverted: the points mirrored in x and seen through
    the camera mirrored the same way (its image flipped left-right) render the frame of the points barely moved,
    flipped (geometry only: F-aware keys, fill, fold and occlusion rules all run on the mirrored points)."""
    from core.images.metrics import psnr

    bundle, test, _ = tiny
    xyz = bundle.model.xyz.detach()
    flip = torch.diag(torch.tensor([-1.0, 1.0, 1.0, 1.0]))
    for i in range(len(test)):
        ref = render_edited(EditState(bundle, points=xyz + 1e-6), test.c2w[i], test.height, test.width, test.focal)
        out = render_edited(EditState(bundle, points=xyz * torch.tensor([-1.0, 1.0, 1.0])), flip @ test.c2w[i] @ flip,
                            test.height, test.width, test.focal)
        check_frame(out, test.height, test.width)
        assert float(psnr(out["rgb"].flip(1), ref["rgb"])) > 35.0
        assert float(psnr(out["alpha"].flip(1), ref["alpha"])) > 35.0


def test_camera_looking_away_renders_background(tiny):
    bundle, test, painted = tiny
    cam = look_at((0.0, 0.0, 4.0), target=(0.0, 0.0, 8.0), up=(0.0, 1.0, 0.0)).float()
    out = render_edited(EditState(bundle, points=bundle.model.xyz.detach() * 1.01, atlas=painted), cam,
                        test.height, test.width, test.focal)
    check_frame(out, test.height, test.width)
    assert out["stats"]["rays_shaded"] == 0 and out["stats"]["texture_rays"] == 0
    assert torch.equal(out["rgb"], torch.ones_like(out["rgb"]))


def test_camera_inside_the_point_cloud(tiny):
    bundle, test, painted = tiny
    cam = look_at((0.0, 0.0, 0.01), target=(0.0, 0.0, -1.0), up=(0.0, 1.0, 0.0)).float()
    out = render_edited(EditState(bundle, atlas=painted), cam, test.height, test.width, test.focal)
    check_frame(out, test.height, test.width)


@pytest.mark.parametrize("influence", [1e30, -1e30, "mixed", float("inf"), float("-inf")])
def test_huge_attention_logits(tiny, influence):
    """The learned influence enters the softmax logits: ±1e30 (and ±inf from a diverged fit) must not give NaN."""
    bundle, test, painted = tiny
    model = bundle.model
    saved = model.influence.detach().clone()
    n = model.num_points
    try:
        with torch.no_grad():
            if influence == "mixed":
                model.influence.copy_(torch.where(torch.arange(n) % 2 == 0, 1e30, -1e30))
            else:
                model.influence.fill_(influence)
        state = EditState(bundle, points=model.xyz.detach() + 1e-3, atlas=painted)
        out = render_edited(state, test.c2w[0], test.height, test.width, test.focal)
    finally:
        with torch.no_grad():
            model.influence.copy_(saved)
    check_frame(out, test.height, test.width)


@pytest.mark.parametrize("dtype", [torch.float16, torch.float64])
def test_atlas_image_in_other_float_types(tiny, dtype):
    bundle, test, painted = tiny
    out = render_edited(EditState(bundle, atlas=painted.to(dtype)), test.c2w[0], test.height, test.width, test.focal)
    ref = render_edited(EditState(bundle, atlas=painted), test.c2w[0], test.height, test.width, test.focal)
    check_frame(out, test.height, test.width)
    assert (out["rgb"] - ref["rgb"]).abs().max() < 5e-3  # float16 rounding of the paint only


def test_temperature_extremes(tiny):
    from core.frames.edited import EditConfig

    bundle, test, painted = tiny
    for temp in (1e-9, 1e9):
        state = EditState(bundle, points=bundle.model.xyz.detach() * 0.9, atlas=painted,
                          cfg=EditConfig(temperature=temp))
        check_frame(render_edited(state, test.c2w[0], test.height, test.width, test.focal), test.height, test.width)
