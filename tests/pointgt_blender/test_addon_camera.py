"""Blender camera -> pinhole camera maths (pointgt_blender/scene/camera.py), without Blender."""
import math

import numpy as np
import pytest

from core.images.cameras import focal_from_fov
from core.util.errors import InputError
from pointgt_blender.scene.camera import camera_to_world, focal_pixels, preview_size, render_size


def test_render_size_follows_percentage():
    assert render_size(1920, 1080, 50) == (960, 540)
    assert render_size(128, 96, 50) == (64, 48)
    with pytest.raises(InputError, match="empty"):
        render_size(1, 1, 10)


def test_preview_keeps_aspect_on_the_long_side():
    assert preview_size(64, 1920, 1080) == (64, 36)
    assert preview_size(64, 1080, 1920) == (36, 64)
    assert preview_size(64, 5000, 10) == (64, 1)  # never zero


@pytest.mark.parametrize("w,h", [(64, 48), (48, 64), (50, 50)])
def test_focal_matches_the_field_of_view_blender_shows(w, h):
    lens, sw, sh = 50.0, 36.0, 24.0
    fov_auto = 2 * math.atan(sw / 2 / lens)  # AUTO: the sensor width spans the longer side
    assert focal_pixels(lens, sw, sh, 'AUTO', w, h) == pytest.approx(focal_from_fov(max(w, h), fov_auto))
    assert focal_pixels(lens, sw, sh, 'HORIZONTAL', w, h) == pytest.approx(focal_from_fov(w, fov_auto))
    fov_v = 2 * math.atan(sh / 2 / lens)
    assert focal_pixels(lens, sw, sh, 'VERTICAL', w, h) == pytest.approx(focal_from_fov(h, fov_v))


def test_degenerate_lens_is_rejected():
    with pytest.raises(InputError, match="positive"):
        focal_pixels(0.0, 36, 24, 'AUTO', 64, 48)


def test_camera_scale_is_removed_and_broken_transforms_rejected():
    rot = np.array([[0, -1, 0], [1, 0, 0], [0, 0, 1]], dtype=np.float64)
    m = np.eye(4)
    m[:3, :3] = rot * np.array([2.0, 3.0, 0.5])  # column scales
    m[:3, 3] = (1, 2, 3)
    c2w = camera_to_world(m)
    np.testing.assert_allclose(c2w[:3, :3], rot, atol=1e-6)
    np.testing.assert_allclose(c2w[:3, 3], (1, 2, 3))
    m[0, 0] = np.nan
    with pytest.raises(InputError, match="NaN"):
        camera_to_world(m)
    z = np.eye(4)
    z[2, 2] = 0.0
    with pytest.raises(InputError, match="zero scale"):
        camera_to_world(z)
