"""Resampling onto another pinhole camera (core/images/resample.py) against brute-force references."""
import math

import numpy as np
import pytest

from core.images.intrinsics import Intrinsics
from core.images.resample import bilinear, resample, source_pixels


def _bilinear_reference(img, x, y):
    """One point, plain Python: pixel centres at +0.5, border repeated."""
    H, W = img.shape[:2]
    sx = min(max(x - 0.5, 0.0), W - 1.0)
    sy = min(max(y - 0.5, 0.0), H - 1.0)
    x0, y0 = int(math.floor(sx)), int(math.floor(sy))
    x1, y1 = min(x0 + 1, W - 1), min(y0 + 1, H - 1)
    ax, ay = sx - x0, sy - y0
    return ((1 - ay) * ((1 - ax) * img[y0, x0] + ax * img[y0, x1])
            + ay * ((1 - ax) * img[y1, x0] + ax * img[y1, x1]))


def test_bilinear_matches_the_reference_inside_and_outside():
    rng = np.random.default_rng(0)
    img = rng.uniform(0, 1, (7, 9, 4)).astype(np.float32)
    px = rng.uniform(-3, 12, (5, 6))
    py = rng.uniform(-3, 10, (5, 6))
    px[0, 0], py[0, 0] = 9.0, 7.0  # the far corner exactly
    out, inside = bilinear(img, px, py)
    for r in range(5):
        for c in range(6):
            np.testing.assert_allclose(out[r, c], _bilinear_reference(img, px[r, c], py[r, c]), atol=1e-6)
            assert inside[r, c] == (0 <= px[r, c] <= 9 and 0 <= py[r, c] <= 7)


def test_the_same_camera_gives_the_same_pixels():
    img = np.random.default_rng(1).uniform(0, 1, (6, 10, 3)).astype(np.float32)
    k = Intrinsics(11.0, 9.0, 4.25, 3.5)
    out, seen = resample(img, k, k, (6, 10))
    assert seen == 1.0 and np.array_equal(out, img)


def test_source_pixels_follow_the_pinhole_projection():
    """A target pixel's ray, projected through the source camera by hand, lands where source_pixels says."""
    src, dst = Intrinsics(40.0, 31.0, 13.0, 9.5), Intrinsics(25.0, 22.0, 10.0, 8.0)
    px, py = source_pixels(dst, (12, 16), src)
    for r, c in [(0, 0), (5, 11), (11, 15)]:
        x, y = (c + 0.5 - dst.cx) / dst.fx, (r + 0.5 - dst.cy) / dst.fy
        assert px[r, c] == pytest.approx(src.fx * x + src.cx) and py[r, c] == pytest.approx(src.fy * y + src.cy)


@pytest.mark.parametrize("scale", [1e-6, 1e6])
def test_extreme_cameras_give_finite_pictures(scale):
    img = np.random.default_rng(2).uniform(0, 1, (5, 5, 2)).astype(np.float32)
    src = Intrinsics(10.0 * scale, 10.0, 2.5, 2.5)
    out, seen = resample(img, src, Intrinsics(10.0, 10.0, 2.5, 2.5), (4, 6))
    assert np.isfinite(out).all() and out.min() >= 0 and out.max() <= 1 and 0 <= seen <= 1


def test_a_denser_source_is_filtered_down_not_aliased():
    """A photo with twice the focal length and pixels per side maps each target pixel onto a 2 x 2 block: the
    result is the block average (a single bilinear sample would alias a checkerboard to flat grey or stripes)."""
    img = np.indices((8, 12)).sum(0)[..., None] % 2 * np.ones(3)  # a one-pixel checkerboard
    k = Intrinsics(7.0, 6.0, 3.0, 2.0)
    out, seen = resample(img.astype(np.float32), k.scaled(2.0), k, (4, 6))
    assert seen == 1.0
    np.testing.assert_allclose(out, img.reshape(4, 2, 6, 2, 3).mean((1, 3)), atol=1e-6)
