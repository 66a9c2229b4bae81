"""The anti-aliased texture lookup on the textured rays' bounding box equals the whole-frame form."""
import functools

import pytest
import torch

import core.frames.edited as edited
from core.frames.edited import EditConfig, EditState, render_edited
from core.images.cameras import focal_from_fov, look_at
from tests.helpers.tiny import tiny_bundle

_LOOKUP = edited._filtered_lookup


@pytest.mark.parametrize("blend,texture_fn", [("soft", False), ("threshold", False), ("soft", True)])
def test_cropped_lookup_equals_the_whole_frame(monkeypatch, blend, texture_fn):
    bundle = tiny_bundle("fast")[0]
    xyz = bundle.model.xyz.detach()
    bent = xyz + 0.05 * torch.sin(3 * xyz.flip(1))
    painted = bundle.atlas.packed_image().clone()
    painted[::2] = 1.0 - painted[::2]
    fn = (lambda x: torch.sigmoid(5 * x)) if texture_fn else None
    # far enough that the object covers part of the frame (the box is a real crop)
    c2w = look_at((2.0, -3.2, 2.4)).float()
    focal = focal_from_fov(56, 0.69)
    outs = []
    for crop in (True, False):
        monkeypatch.setattr(edited, "_filtered_lookup", functools.partial(_LOOKUP, crop=crop))
        st = EditState(bundle, points=bent, atlas=painted, cfg=EditConfig(blend=blend))
        outs.append(render_edited(st, c2w, 56, 56, focal, texture_fn=fn))
        monkeypatch.undo()
    hit = torch.isfinite(outs[1]["x_can"]).all(-1)
    assert 50 < int(hit.sum()) < 56 * 56 * 0.8
    assert float((outs[0]["rgb"] - outs[1]["rgb"]).abs().max()) <= 1e-6

