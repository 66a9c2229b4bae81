"""Atlas <-> Blender pixel buffer conversions (no Blender needed): orientation, colour space, degenerate input."""
from __future__ import annotations

import numpy as np
import pytest

from core.util.errors import InputError
from pointgt_blender.scene import atlas_image as ai


def _reference_srgb_to_linear(c):
    return np.array([x / 12.92 if x <= 0.04045 else ((x + 0.055) / 1.055) ** 2.4 for x in c.ravel()]).reshape(c.shape)


def test_transfer_curves_match_reference_and_invert():
    c = np.linspace(0, 1, 1001, dtype=np.float32)
    np.testing.assert_allclose(ai.srgb_to_linear(c), _reference_srgb_to_linear(c.astype(np.float64)), atol=1e-6)
    np.testing.assert_allclose(ai.linear_to_srgb(ai.srgb_to_linear(c)), c, atol=2e-6)


def test_pixels_are_bottom_up_rgba_and_round_trip():
    rng = np.random.default_rng(0)
    atlas = rng.uniform(0, 1, (5, 7, 3)).astype(np.float32)
    px = ai.atlas_to_pixels(atlas)
    assert px.shape == (5 * 7 * 4,) and px.dtype == np.float32
    rgba = px.reshape(5, 7, 4)
    np.testing.assert_allclose(rgba[-1, :, :3], ai.srgb_to_linear(atlas[0]))  # top row of the file is last
    assert (rgba[..., 3] == 1).all()
    np.testing.assert_allclose(ai.pixels_to_atlas(px, 5, 7), atlas, atol=2e-6)
    display = np.ones((5, 7, 4), np.float32)
    display[..., :3] = atlas[::-1]
    np.testing.assert_allclose(ai.pixels_to_atlas(display.ravel(), 5, 7, linear=False), atlas)


def test_nonfinite_and_out_of_range_values_stay_finite_and_in_range():
    bad = np.array([[[np.nan, np.inf, -np.inf], [-1.0, 2.0, 0.5]]], np.float32)
    px = ai.atlas_to_pixels(bad)
    assert np.isfinite(px).all() and px.min() >= 0 and px.max() <= 1
    back = ai.pixels_to_atlas(np.array([np.nan, np.inf, -5, 1] * 2, np.float32), 1, 2)
    assert np.isfinite(back).all() and back.min() >= 0 and back.max() <= 1


def test_wrong_atlas_shape_is_rejected():
    with pytest.raises(InputError, match=r"\[H, W, 3\]"):
        ai.atlas_to_pixels(np.zeros((4, 4), np.float32))
