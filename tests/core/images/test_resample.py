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


def _picture(x, y):
    """A smooth colour field of normalised camera coordinates: [..., 3]."""
    return np.stack([0.5 + 0.4 * np.sin(5 * x + 1) * np.cos(4 * y), 0.5 + 0.4 * np.cos(3 * x - 2 * y),
                     0.5 + 0.3 * np.sin(6 * y + x)], -1)


def test_distorting_a_picture_then_undistorting_recovers_it():
    """A synthetic pinhole image is distorted by the brute-force inverse of the lens (fixed-point iteration,
    tests/helpers/synthetic.py) with the reference bilinear sampler; undistorting it gives the image back."""
    import torch

    from core.images.resample import Distortion
    from tests.helpers.synthetic import undistort_normalised

    k, (h, w) = Intrinsics(40.0, 38.0, 31.0, 25.0), (48, 64)
    lens = (-0.2, 0.05, 0.01, 0.003, -0.002)
    u, v = np.meshgrid(np.arange(w) + 0.5, np.arange(h) + 0.5)
    image = _picture((u - k.cx) / k.fx, (v - k.cy) / k.fy).astype(np.float32)
    xu, yu = undistort_normalised(lens, torch.from_numpy((u - k.cx) / k.fx), torch.from_numpy((v - k.cy) / k.fy))
    src_u, src_v = xu.numpy() * k.fx + k.cx, yu.numpy() * k.fy + k.cy  # where each distorted pixel looks
    distorted = np.array([[_bilinear_reference(image, src_u[r, c], src_v[r, c]) for c in range(w)]
                          for r in range(h)], np.float32)
    assert np.abs(distorted - image).max() > 0.1  # the lens really moves the picture
    back, seen = resample(distorted, k, k, (h, w), Distortion(*lens))
    assert seen == 1.0  # barrel distortion: the distorted photo sees every ray of the pinhole camera
    err = np.abs(back - image)[1:-1, 1:-1]  # the outermost ring was read from repeated borders when distorting
    assert err.max() < 5e-3, err.max()
    wrong, _ = resample(distorted, k, k, (h, w))  # ignoring the lens does not
    assert np.abs(wrong - image)[1:-1, 1:-1].max() > 0.1


def test_distortion_that_folds_over_is_detected_and_extreme_lenses_stay_finite():
    from core.images.resample import Distortion

    assert not Distortion(-0.2, 0.05, 0.01).folds(1.0)
    assert Distortion(-0.5).folds(1.0)  # r (1 - 0.5 r²) peaks at r = 0.82
    assert not Distortion(-0.5).folds(0.8)
    img = np.random.default_rng(3).uniform(0, 1, (6, 8, 4)).astype(np.float32)
    k = Intrinsics(5.0, 5.0, 4.0, 3.0)
    for lens in (Distortion(1e30, 1e30, 1e30, 1e30, 1e30), Distortion(-1e30), Distortion(0.0, 0.0, 0.0, 1e-300)):
        out, seen = resample(img, k, k, (6, 8), lens)
        assert np.isfinite(out).all() and 0 <= out.min() and out.max() <= 1 and 0 <= seen <= 1
    with pytest.raises(Exception, match="k1 must be a finite number"):
        Distortion(float("nan"))


def test_bands_give_the_same_picture_as_one_pass(monkeypatch):
    import core.images.resample as rs

    img = np.random.default_rng(4).uniform(0, 1, (20, 30, 4)).astype(np.float32)
    src, dst = Intrinsics(40.0, 36.0, 14.0, 11.0), Intrinsics(18.0, 17.0, 8.5, 6.0)  # denser source: s = 3
    whole, seen = rs.resample(img, src, dst, (13, 17), rs.Distortion(-0.1, 0.01))
    monkeypatch.setattr(rs, "BAND_SAMPLES", 17 * 9 * 2)  # two target rows per band
    banded, seen_b = rs.resample(img, src, dst, (13, 17), rs.Distortion(-0.1, 0.01))
    assert np.array_equal(whole, banded) and seen == seen_b
