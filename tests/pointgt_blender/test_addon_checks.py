"""Pose warnings from plain arrays (no Blender): collapsed, blown up, off-camera, and quiet for a fine pose."""
from __future__ import annotations

import numpy as np

from pointgt_blender.bridge.checks import extent, in_view, pose_warning

C2W = np.eye(4, dtype=np.float32)
C2W[2, 3] = 3.0  # at z = 3 looking down -Z at the origin


def _card(scale=1.0, shift=(0.0, 0.0, 0.0)):
    g = np.linspace(-0.5, 0.5, 11)
    xy = np.stack(np.meshgrid(g, g), -1).reshape(-1, 2)
    return (np.c_[xy, np.zeros(len(xy))] * scale + np.asarray(shift)).astype(np.float32)


def test_a_fine_pose_gives_no_warning():
    pts = _card()
    assert pose_warning("card", pts, extent(pts), C2W, 60.0, 64, 48) == ""


def test_collapsed_blown_up_and_off_camera_are_named():
    rest = extent(_card())
    assert "collapsed" in pose_warning("card", _card(1e-6), rest, C2W, 60.0, 64, 48)
    assert "blew up" in pose_warning("card", _card(1e6), rest, C2W, 60.0, 64, 48)
    assert "off-camera" in pose_warning("card", _card(shift=(100.0, 0.0, 0.0)), rest, C2W, 60.0, 64, 48)
    assert "off-camera" in pose_warning("card", _card(shift=(0.0, 0.0, 10.0)), rest, C2W, 60.0, 64, 48)  # behind


def test_non_finite_points_do_not_break_the_checks():
    pts = _card()
    pts[:5] = np.nan
    pts[5:8] = np.inf
    assert np.isfinite(extent(pts))
    seen = in_view(pts, C2W, 60.0, 64, 48)
    assert not seen[:8].any() and seen[8:].any()
    assert pose_warning("card", pts, extent(_card()), C2W, 60.0, 64, 48) == ""
    assert "no finite point" in pose_warning("card", np.full((4, 3), np.nan, np.float32), 1.0, C2W, 60.0, 64, 48)


def test_in_view_follows_an_off_centre_camera_with_two_focal_lengths():
    """A shifted lens / capture camera: the brute-force projection through Intrinsics decides what is in view."""
    from core.images.intrinsics import Intrinsics

    k = Intrinsics(60.0, 45.0, 10.0, 40.0)  # principal point near the left edge and the bottom
    pts = np.random.default_rng(0).uniform(-2, 2, (400, 3)).astype(np.float32)
    cam = pts.astype(np.float64) - C2W[:3, 3]
    col = k.fx * cam[:, 0] / -cam[:, 2] + k.cx
    row = -k.fy * cam[:, 1] / -cam[:, 2] + k.cy
    expect = (-cam[:, 2] > 0) & (col >= 0) & (col < 64) & (row >= 0) & (row < 48)
    assert 20 < expect.sum() < 380
    np.testing.assert_array_equal(in_view(pts, C2W, k, 64, 48), expect)
    assert pose_warning("card", _card(), extent(_card()), C2W, k, 64, 48) == ""
