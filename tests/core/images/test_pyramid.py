"""Image pyramids of a split (core/images/pyramid.py): a level is the loader's --downscale of the same files, its
camera the one of that size, and sizes or lists that do not fit raise errors naming the flag."""
import pytest
import torch

from core.images.cameras import Intrinsics, rays_for_pixels
from core.images.dataset import load_split
from core.images.pyramid import (AUTO_MAX_FACTOR, area_downscale, auto_train_scales, downscale_split, ladder,
                                 parse_scales, parse_weights, pyramid)
from core.points.train import sample_patches
from core.util.errors import InputError
from tests.helpers.synthetic import fibonacci_cameras, render_split, write_split


def test_a_level_is_the_loaders_downscale_of_the_same_files(tmp_path):
    root = write_split(tmp_path / "card", render_split("card", fibonacci_cameras(3, seed=1), 48))
    native = load_split(root, "train")
    for s in (2, 3, 4):
        loaded = load_split(root, "train", downscale=s)
        level = downscale_split(native, s)
        assert (level.height, level.width) == (loaded.height, loaded.width) == (48 // s, 48 // s)
        assert isinstance(level.focal, float) and level.focal == pytest.approx(loaded.focal, rel=1e-12)
        assert torch.allclose(level.images, loaded.images, atol=2e-6)
        assert torch.allclose(level.alphas, loaded.alphas, atol=2e-6)
        assert torch.equal(level.c2w, loaded.c2w)
        # a patch of the level is the patch of the downscaled images: same pixels, same values
        pa, ra, ca, _ = sample_patches(level.alphas[1], 3, 8, 0.75, torch.Generator().manual_seed(4))
        pb, rb, cb, _ = sample_patches(loaded.alphas[1], 3, 8, 0.75, torch.Generator().manual_seed(4))
        assert torch.equal(pa, pb) and torch.allclose(level.images[1][ra, ca], loaded.images[1][rb, cb], atol=2e-6)
    assert downscale_split(native, 1) is native


def test_a_level_pixel_sees_the_centre_of_its_block_off_centre_camera_too():
    k = Intrinsics(50.0, 46.0, 21.0, 13.5)
    split = render_split("card", fibonacci_cameras(2, seed=2), 40, height=24, intrinsics=k)
    for s in (2, 4):
        level = downscale_split(split, s)
        assert isinstance(level.focal, Intrinsics)
        assert level.focal.as_list() == pytest.approx([50.0 / s, 46.0 / s, 21.0 / s, 13.5 / s])
        px = torch.tensor([[0.5, 0.5], [3.5, 2.5], [level.width - 0.5, level.height - 0.5]])
        o1, d1 = rays_for_pixels(split.c2w[0], px, level.height, level.width, level.focal)
        o2, d2 = rays_for_pixels(split.c2w[0], px * s, split.height, split.width, split.focal)
        assert torch.allclose(o1, o2) and torch.allclose(d1, d2, atol=1e-6)
        # block means: level pixel (r, c) averages native rows s*r .. s*r + s - 1
        assert torch.allclose(level.images[0, 1, 2], split.images[0, s:2 * s, 2 * s:3 * s].mean((0, 1)), atol=1e-6)


def test_centred_cameras_stay_single_focal_and_scale_exactly():
    split = render_split("sphere", fibonacci_cameras(1, seed=0), 32)
    level = downscale_split(split, 4)
    assert level.focal == split.focal / 4 and level.intrinsics.cx == 4.0 and level.meta["pyramid_level"] == 4


def test_block_means_of_extreme_images():
    assert torch.equal(area_downscale(torch.ones(1, 6, 6, 3), 3), torch.ones(1, 2, 2, 3))
    checker = ((torch.arange(8)[:, None] + torch.arange(8)[None]) % 2).float()[None]  # [1, 8, 8] of 0 and 1
    assert torch.equal(area_downscale(checker, 2), torch.full((1, 4, 4), 0.5))
    assert torch.equal(area_downscale(checker, 8), torch.full((1, 1, 1), 0.5))  # one pixel: the whole image


def test_sizes_and_lists_that_do_not_fit_are_refused_naming_the_flag():
    split = render_split("card", fibonacci_cameras(1, seed=0), 33, height=30)
    with pytest.raises(InputError, match=r"--train-scales: .*33x30.*2 do\(es\) not divide.*\[1, 3\]"):
        pyramid(split, [1, 2])
    with pytest.raises(InputError, match="--train-scales"):
        downscale_split(split, 2)
    assert sorted(pyramid(split, [1, 3])) == [1, 3]
    assert parse_scales("4, 1,2") == [1, 2, 4] and parse_scales("") == [] and parse_scales(" Off") == []
    for bad in ("1,x", "0,2", "2,2", "1,65", "1.5"):
        with pytest.raises(InputError, match="--train-scales"):
            parse_scales(bad)
    assert parse_weights("", 3) == pytest.approx([1 / 3] * 3)
    assert parse_weights("1,3", 2) == [0.25, 0.75]
    for bad in ("1", "1,2,3", "0,0", "-1,2", "inf,1", "nan,1", "a,b"):
        with pytest.raises(InputError, match="--train-scale-weights"):
            parse_weights(bad, 2)


def test_ladder_is_the_powers_of_two_that_divide_the_factor_and_the_factor():
    assert [ladder(f) for f in (1, 2, 3, 4, 6, 8, 12)] == [[1], [1, 2], [1, 3], [1, 2, 4], [1, 2, 6], [1, 2, 4, 8],
                                                           [1, 2, 4, 12]]


def test_the_default_pyramid_of_a_downscale():
    """--downscale N --train-scales auto: no pyramid for N = 1; else the images are read at 1/L with N/L <=
    AUTO_MAX_FACTOR and trained down to the training size (1/N), two thirds of the steps on it; "auto" itself is no list
    of factors (only `pointgt fit` resolves it)."""
    assert auto_train_scales(1) == (1, "", "")
    assert auto_train_scales(2) == (1, "1,2", "1,2")
    assert auto_train_scales(3) == (1, "1,3", "1,2")
    assert auto_train_scales(4) == (1, "1,2,4", "1,1,4")
    assert auto_train_scales(8) == (2, "1,2,4", "1,1,4")
    assert auto_train_scales(6) == (2, "1,3", "1,2")
    assert auto_train_scales(5) == (5, "", "")  # no divisor of 5 leaves a factor of 2-4: the training size alone
    for n in range(1, 65):
        load, scales, weights = auto_train_scales(n)
        assert n % load == 0
        if scales:
            levels = parse_scales(scales)
            assert load * levels[-1] == n and levels[-1] <= AUTO_MAX_FACTOR  # coarsest level = the training size
            shares = parse_weights(weights, len(levels))
            assert shares[-1] == pytest.approx(2 / 3) and len(set(shares[:-1])) == 1
        else:
            assert load == n
    with pytest.raises(InputError, match="--train-scales auto: `pointgt fit`"):
        parse_scales("auto")
