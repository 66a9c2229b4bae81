"""Huge and tiny scene scales: the model (points, `spacing`, atlas frame) and the cameras scaled together by 1e-3
or 1e3 must render the same picture, through the whole edited path (deformed points + painted atlas)."""
import copy

import pytest
import torch

from core.atlas.surface import SurfaceProjection
from core.edits.bake import bake
from core.frames.edited import EditState, render_edited
from tests.helpers.tiny import tiny_bundle
from tests.stability.frame_checks import check_frame

pytestmark = pytest.mark.stability


def scaled_bundle(bundle, s: float):
    """A copy of bundle with every length multiplied by s: points, spacing, training pixel footprint, atlas
    centre/half, texel map, bake samples and the anchor planes of the mid-surface and of the side split."""
    b = copy.deepcopy(bundle)
    with torch.no_grad():
        b.model.xyz.mul_(s)
        b.model.spacing.mul_(s)
        b.model.train_footprint.mul_(s)
        b.atlas.centre.mul_(s)
        b.atlas.texel_xyz.mul_(s)
    b.atlas.half *= s
    if b.atlas.bake_samples is not None:
        b.atlas.bake_samples = b.atlas.bake_samples * s
    for owner in (b.atlas, b.atlas.sides):  # anchor planes: the mid-surface's, the side split's normals
        surf = getattr(owner, "surface", None)
        if surf is not None:
            owner.surface = SurfaceProjection(surf.centres * s, surf.normals, surf.bandwidth * s, surf.k)
    return b


@pytest.fixture(scope="module")
def tiny():
    bundle, _, test = tiny_bundle("fast")
    painted = bake(bundle.atlas, lambda x: (torch.stack([(x[:, 0] > 0).float(), (x[:, 1] > 0).float(),
                                                         0.5 + 0 * x[:, 0]], 1), None))
    return bundle, test, painted


@pytest.mark.parametrize("s", [1e-3, 1e3])
def test_scaled_scene_renders_the_same_picture(tiny, s):
    bundle, test, painted = tiny
    big = scaled_bundle(bundle, s)
    xyz = bundle.model.xyz.detach()
    bent = xyz + 0.05 * torch.sin(3 * xyz[:, [1, 2, 0]])  # a non-rigid pose
    ref_state = EditState(bundle, points=bent, atlas=painted)
    state = EditState(big, points=bent * s, atlas=painted)
    compared = 0
    for i in range(len(test)):
        cam = test.c2w[i].clone()
        ref = render_edited(ref_state, cam, test.height, test.width, test.focal)
        cam[:3, 3] *= s
        out = render_edited(state, cam, test.height, test.width, test.focal)
        check_frame(out, test.height, test.width)
        assert out["stats"]["texture_rays"] == ref["stats"]["texture_rays"]
        assert (out["alpha"] - ref["alpha"]).abs().max() < 1e-3
        assert (out["rgb"] - ref["rgb"]).abs().max() < 2e-3
        hit = torch.isfinite(ref["x_can"]).all(-1)
        assert torch.allclose(out["x_can"][hit] / s, ref["x_can"][hit], atol=1e-4, rtol=1e-3)
        compared += int(hit.sum())
    assert compared > 50  # the frames do show the textured object
