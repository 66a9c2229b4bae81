"""tools/bench/frames.py: each timed case renders in the render mode it names."""
import torch

from tests.helpers.tiny import tiny_bundle
from tools.bench.frames import Case


def test_cases_render_in_their_mode():
    from core.frames.edited import render_edited

    bundle, _, test = tiny_bundle("card")
    painted = bundle.atlas.packed_image().clone()
    c2w, h, w, f = test.c2w[0], 3 * test.height, 3 * test.width, 3 * test.focal
    frames = {}
    for mode in ("auto", "filtered", "upsampled"):
        for edited in (False, True):
            case = Case("x", bundle, edited, bundle.model.xyz.detach().clone() if edited else None,
                        painted if edited else None, mode=mode)
            state = case.state()
            assert state.cfg.render_mode == mode
            frames[mode, edited] = render_edited(state, c2w, h, w, f)["rgb"]
    assert torch.equal(frames["auto", False], frames["upsampled", False])  # a single-scale fit: `auto` is upsampled
    assert not torch.equal(frames["filtered", False], frames["upsampled", False])
    assert Case("x", bundle, False).state().cfg.render_mode == "auto"
