"""An off-centre camera is a crop of a centred one: rendering an h x w window through Intrinsics(f, f, W/2 - c0,
H/2 - r0) must give the pixels of the full W x H render at rows r0.., cols c0.. — for the point renderer and the edited
(atlas-textured) frames. The full centred render is the brute-force reference."""
import copy

import pytest
import torch

from core.frames.edited import EditState, render_edited
from core.images.cameras import Intrinsics
from core.points.render import render_frame
from tests.helpers.tiny import tiny_bundle

R0, C0, h, w = 5, 9, 14, 19  # a non-square window off the centre of the 32 x 32 test view


@pytest.fixture(scope="module")
def model_pair():
    bundle, _, test = tiny_bundle("fast")
    bundle = copy.deepcopy(bundle)  # the cached model is shared: change a copy
    # the perpendicular search picks neighbours per ray, independent of the frame (the screen searches cap their
    # radius from the frame's point density, which a crop changes)
    bundle.model.cfg.neighbors = "perpendicular"
    return bundle, test


def _crop_camera(test):
    f = float(test.focal)
    return Intrinsics(f, f, 0.5 * test.width - C0, 0.5 * test.height - R0)


def test_point_render_of_a_window_equals_the_crop_of_the_full_render(model_pair):
    bundle, test = model_pair
    with torch.no_grad():
        full = render_frame(bundle.model, test.c2w[0], test.height, test.width, test.focal)
        crop = render_frame(bundle.model, test.c2w[0], h, w, _crop_camera(test))
    ref = full["rgb"].reshape(test.height, test.width, 3)[R0:R0 + h, C0:C0 + w]
    torch.testing.assert_close(crop["rgb"].reshape(h, w, 3), ref, atol=1e-4, rtol=0)
    ref_a = full["alpha"].reshape(test.height, test.width)[R0:R0 + h, C0:C0 + w]
    torch.testing.assert_close(crop["alpha"].reshape(h, w), ref_a, atol=1e-4, rtol=0)
    assert float(ref_a.max()) > 0.5  # the window shows the object


def test_edited_render_of_a_window_equals_the_crop_away_from_its_border(model_pair):
    bundle, test = model_pair
    state = EditState(bundle, atlas=bundle.atlas.packed_image())
    with torch.no_grad():
        full = render_edited(state, test.c2w[0], test.height, test.width, test.focal)
        crop = render_edited(state, test.c2w[0], h, w, _crop_camera(test))
    ref = full["rgb"].reshape(test.height, test.width, 3)[R0:R0 + h, C0:C0 + w]
    got = crop["rgb"].reshape(h, w, 3)
    # the pixel filter reads a pixel's neighbours: compare one pixel in from the window's border
    torch.testing.assert_close(got[1:-1, 1:-1], ref[1:-1, 1:-1], atol=2e-3, rtol=0)
