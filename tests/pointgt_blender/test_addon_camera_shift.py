"""Lens shift, non-square renders and non-square pixels: the add-on's camera (an off-centre principal point for
a shifted lens, fx != fy for a pixel aspect other than 1:1)
projects points where Blender's own camera projection puts them."""
from __future__ import annotations

from pathlib import Path

import pytest

from core.images.cameras import Intrinsics
from core.util.errors import InputError
from pointgt_blender.scene.camera import camera_settings, focal_pixels, pixel_aspect, principal_point
from tests.helpers.blender import run_script

SCRIPT = Path(__file__).with_name("camera_shift_script.py")
REPO = Path(__file__).resolve().parents[2]


def test_principal_point_of_a_centred_lens_is_the_image_centre():
    for fit in ('AUTO', 'HORIZONTAL', 'VERTICAL'):
        assert principal_point(0.0, 0.0, fit, 64, 48) == (32.0, 24.0)
    assert principal_point(0.25, 0.0, 'AUTO', 64, 48) == (16.0, 24.0)  # AUTO fits the larger side
    assert principal_point(0.0, 0.25, 'VERTICAL', 64, 48) == (32.0, 36.0)


def test_camera_settings_invert_the_add_on_camera():
    s = camera_settings(Intrinsics(50.0, 50.0, 20.0, 30.0), 64, 48)
    assert s["lens"] == pytest.approx(50.0 * 36.0 / 64) and s["sensor_fit"] == 'HORIZONTAL'
    assert principal_point(s["shift_x"], s["shift_y"], s["sensor_fit"], 64, 48) == pytest.approx((20.0, 30.0))
    assert camera_settings(40.0, 64, 48)["shift_x"] == camera_settings(40.0, 64, 48)["shift_y"] == 0.0
    k = Intrinsics(50.0, 45.0, 20.0, 30.0)  # fx != fy: non-square pixels, fy / fx = aspect_x / aspect_y
    s = camera_settings(k, 64, 48)
    ax, ay = pixel_aspect(k)
    assert (ax, ay) == pytest.approx((1.0, 50.0 / 45.0))
    assert focal_pixels(s["lens"], s["sensor_width"], 24.0, s["sensor_fit"], 64, 48, ax, ay) * ax / ay \
        == pytest.approx(45.0)
    assert principal_point(s["shift_x"], s["shift_y"], s["sensor_fit"], 64, 48, ax, ay) == pytest.approx((20.0, 30.0))
    assert pixel_aspect(Intrinsics(40.0, 60.0, 1.0, 1.0)) == pytest.approx((1.5, 1.0))
    with pytest.raises(InputError, match="pixel aspect"):
        pixel_aspect(Intrinsics(1.0, 500.0, 32.0, 24.0))


@pytest.mark.blender
def test_shifted_and_non_square_cameras_match_blenders_projection():
    rows = run_script(SCRIPT, [str(REPO)], cwd=REPO, timeout=300)
    assert len(rows) == 10
    for row in rows[:7]:
        assert row["max_px_err"] < 1e-4, row  # float32 c2w: ~5e-6 px
        assert row["kind"] == ("float" if row["case"][3:] == [0.0, 0.0, 1.0, 1.0] else "Intrinsics")
    for row in rows[7:]:  # dataset cameras set up in Blender with camera_settings: the same camera back
        assert row["kind"] == "Intrinsics" and row["intrinsics_err"] < 1e-4 and row["max_px_err"] < 1e-4, row
