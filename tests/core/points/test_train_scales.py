"""Multi-scale stage-1 training (`TrainConfig.train_scales`): one level is the plain step exactly, a level's
neighbours are those of a frame of its size, and every level trains."""
import pytest
import torch

from core.images.pyramid import downscale_split
from core.points.render import trace_frame
from core.points.resolution import training_footprint
from core.points.train import TrainConfig, fit_points, interior_gain, patch_neighbors, sample_patches
from core.util.errors import DataError, InputError
from tests.helpers.synthetic import fibonacci_cameras, render_split
from tests.helpers.tiny import model_config

TINY_MODEL = model_config("card", num_points=600)


def _cfg(**kw):
    base = dict(steps=40, patches=2, patch_size=12, eval_every=1e9, eval_views=2, device="cpu", seed=0, threads=1,
                prune_every=15, clone_every=20, reg_start=0.0, max_points=700, lr_final=0.2)
    base.update(kw)
    return TrainConfig(**base)


def _native(size=48, views=3):
    cams = fibonacci_cameras(views, seed=3)
    return render_split("sphere", cams, size)


def _state(model):
    return {k: v.detach().clone() for k, v in model.state_dict().items()}


def _same(a, b):
    return a.keys() == b.keys() and all(torch.equal(a[k], b[k]) for k in a)


def test_one_level_is_the_plain_step_exactly():
    """--train-scales 1 is the fit without it; --train-scales 2 alone is the fit on the images downscaled by 2
    (the loader's --downscale 2): same model to the bit, same history."""
    native = _native()
    test = downscale_split(native, 2)
    for decoder in ("none", "unet"):
        mcfg = model_config("card", num_points=600, decoder=decoder)
        plain, h0 = fit_points(native, test, mcfg, _cfg(), show_progress=False)
        one, h1 = fit_points(native, test, mcfg, _cfg(train_scales="1"), show_progress=False)
        assert _same(_state(plain), _state(one)) and h0[-1]["psnr"] == h1[-1]["psnr"]
        assert h1[-1]["train_levels"] == {"1": 40} and "train_levels" not in h0[-1]
        low, h2 = fit_points(test, test, mcfg, _cfg(), show_progress=False)
        two, h3 = fit_points(native, test, mcfg, _cfg(train_scales="2"), show_progress=False)
        assert _same(_state(low), _state(two)) and h2[-1]["psnr"] == h3[-1]["psnr"]


def test_a_levels_neighbours_are_those_of_a_frame_of_its_size():
    """The step searches a level's pixels as render_frame at that size does (pixel-radius rule included)."""
    native = _native(size=64)
    model, _ = fit_points(downscale_split(native, 4), downscale_split(native, 4), TINY_MODEL, _cfg(steps=10),
                          show_progress=False)
    for s in (1, 2, 4):
        level = downscale_split(native, s)
        px, rows, cols, _ = sample_patches(level.alphas[0], 3, 8, 1.0, torch.Generator().manual_seed(1))
        o, d, idx = patch_neighbors(model.xyz.detach(), model.cfg, level.c2w[0], level, px)
        tr = trace_frame(model, level.c2w[0], level.height, level.width, level.focal)
        flat = rows * level.width + cols
        assert torch.equal(idx, tr.idx[flat]), s
        assert torch.allclose(o, tr.origins[flat]) and torch.allclose(d, tr.dirs[flat], atol=1e-6)


def test_every_level_trains_and_the_footprint_is_the_finest_levels():
    native = _native()
    for decoder in ("none", "unet"):
        mcfg = model_config("card", num_points=600, decoder=decoder)
        cfg = _cfg(steps=120, train_scales="1,2,4", prune_every=0, clone_every=0)
        model, hist = fit_points(native, downscale_split(native, 4), mcfg, cfg, show_progress=False)
        levels = hist[-1]["train_levels"]
        assert sum(levels.values()) == 120 and min(levels.values()) > 20, levels
        for p in model.parameters():
            assert torch.isfinite(p).all()
        assert hist[-1]["psnr"] > hist[0]["psnr"] + 5, (decoder, hist[0]["psnr"], hist[-1]["psnr"])
        fine = training_footprint(native.c2w, native.focal, model.xyz.detach())
        assert float(model.train_footprint) == pytest.approx(fine, rel=1e-6)
        # the finest level's pixel is a quarter of the coarsest's: renders at the native size are at scale 1
        assert fine == pytest.approx(training_footprint(native.c2w, native.focal / 4, model.xyz.detach()) / 4)
        # the decoder's pixel is the coarsest level's (the training size), and the fit measured on the finest
        # level which decode `auto` uses inside the object (stored in the model and its last history row)
        assert float(model.decoder_footprint) == pytest.approx(4 * fine, rel=1e-6)
        gain = hist[-1]["interior_gain"]
        if decoder == "none":
            assert gain is None and float(model.interior_gain) == 0.0
        else:
            assert gain == pytest.approx(interior_gain(model, native), abs=1e-5)
            assert float(model.interior_gain) == pytest.approx(gain, abs=1e-6)


def test_level_weights_pick_the_levels():
    native = _native(size=32)
    _, hist = fit_points(native, native, TINY_MODEL, _cfg(steps=30, train_scales="1,2", train_scale_weights="0,1"),
                         show_progress=False)
    assert hist[-1]["train_levels"] == {"1": 0, "2": 30}


def test_extreme_levels_sizes_that_do_not_divide_and_a_one_pixel_level():
    odd = _native(size=33)
    with pytest.raises(InputError, match="--train-scales"):
        fit_points(odd, odd, TINY_MODEL, _cfg(steps=5, train_scales="1,2"), show_progress=False)
    with pytest.raises(InputError, match="--train-scale-weights"):
        fit_points(odd, odd, TINY_MODEL, _cfg(steps=5, train_scales="1,3", train_scale_weights="1"),
                   show_progress=False)
    # a coarsest level smaller than a patch (4² for 12² patches): the fit runs and stays finite
    tiny = _native(size=16)
    model, hist = fit_points(tiny, tiny, TINY_MODEL, _cfg(steps=20, train_scales="1,4", patch_size=12),
                             show_progress=False)
    assert all(torch.isfinite(p).all() for p in model.parameters())
    assert hist[-1]["train_levels"]["4"] > 0
    # one pixel, the object no longer opaque in it: the visual hull says so, as --downscale 16 would
    with pytest.raises(DataError, match="no 3-D point projects onto the foreground"):
        fit_points(tiny, tiny, TINY_MODEL, _cfg(steps=5, train_scales="1,16"), show_progress=False)


def test_pick_level_settles_on_the_coarsest_level_at_the_end():
    """--train-scale-settle: before 1 - settle the shares pick the level; after it the coarsest, without drawing
    (so the random stream of the steps before is that of the fit without it)."""
    from core.points.train import pick_level

    p = torch.tensor([0.5, 0.5, 0.0], dtype=torch.float64)
    gen = torch.Generator().manual_seed(0)
    early = {pick_level(p, 0.2, 0.3, gen) for _ in range(50)}
    assert early == {0, 1}
    state = gen.get_state()
    assert all(pick_level(p, f, 0.3, gen) == 2 for f in (0.7, 0.85, 1.0))
    assert torch.equal(gen.get_state(), state)
    assert pick_level(p, 0.0, 1.0, gen) == 2  # settle 1: the training size throughout
    assert pick_level(torch.ones(1, dtype=torch.float64), 0.9, 0.5, gen) == 0  # one level: nothing to pick
    assert torch.equal(gen.get_state(), state)
    assert {pick_level(p, 0.99, 0.0, gen) for _ in range(50)} == {0, 1}  # settle 0: the shares to the end


def test_settle_trains_the_last_steps_on_the_training_size_and_zero_is_the_fit_without_it():
    native = _native(size=32)
    mcfg = model_config("card", num_points=600, decoder="unet")
    base = dict(steps=40, train_scales="1,2", train_scale_weights="1,1", prune_every=0, clone_every=0)
    plain, h0 = fit_points(native, native, mcfg, _cfg(**base), show_progress=False)
    zero, h1 = fit_points(native, native, mcfg, _cfg(**base, train_scale_settle=0.0), show_progress=False)
    assert _same(_state(plain), _state(zero)) and h0[-1]["train_levels"] == h1[-1]["train_levels"]
    model, hist = fit_points(native, native, mcfg, _cfg(**base, train_scale_settle=0.5), show_progress=False)
    levels = hist[-1]["train_levels"]
    # steps 20..39 (frac >= 0.5) on the coarsest level; the first 20 shared as the fit without settling shares them
    first = {k: v for k, v in h0[-1]["train_levels"].items()}
    assert levels["2"] >= 20 and levels["1"] > 0 and levels["1"] + levels["2"] == 40
    assert levels["1"] <= first["1"]
    assert all(torch.isfinite(p).all() for p in model.parameters())
    assert hist[-1]["psnr"] > hist[0]["psnr"] + 3


def test_fine_steps_without_the_decoder_leave_it_alone():
    """--train-scale-fine no-decoder: the finer levels' steps do not move the decoder (all its steps on them:
    it is the initial decoder to the bit), the points and the other networks still train; on the coarsest level
    it trains as with `all`."""
    native = _native(size=32)
    mcfg = model_config("card", num_points=600, decoder="unet")
    base = dict(steps=12, train_scales="1,2", prune_every=0, clone_every=0)
    fine_only = dict(base, train_scale_weights="1,0", train_scale_fine="no-decoder")
    init, _ = fit_points(native, native, mcfg, _cfg(**{**fine_only, "steps": 2}), show_progress=False)
    fine, hist = fit_points(native, native, mcfg, _cfg(**fine_only), show_progress=False)
    assert hist[-1]["train_levels"] == {"1": 12, "2": 0}
    dec0, dec1 = init.decoder.state_dict(), fine.decoder.state_dict()
    assert all(torch.equal(dec0[k], dec1[k]) for k in dec0)
    assert not bool(fine.decoder.out.weight.any())  # its correction is still the initial zero
    assert not torch.equal(init.xyz, fine.xyz) and not torch.equal(init.features, fine.features)
    coarse_all, _ = fit_points(native, native, mcfg, _cfg(**base, train_scale_weights="0,1"), show_progress=False)
    coarse_only, _ = fit_points(native, native, mcfg, _cfg(**base, train_scale_weights="0,1",
                                                           train_scale_fine="no-decoder"), show_progress=False)
    assert _same(_state(coarse_all), _state(coarse_only))
    mixed, hist = fit_points(native, native, mcfg, _cfg(**{**base, "steps": 30}, train_scale_fine="no-decoder"),
                             show_progress=False)
    assert min(hist[-1]["train_levels"].values()) > 0
    assert all(torch.isfinite(p).all() for p in mixed.parameters())
    assert not all(torch.equal(dec0[k], mixed.decoder.state_dict()[k]) for k in dec0)


def test_what_the_finer_levels_train():
    """frozen_on_fine: what --train-scale-fine leaves to the training size's steps; with `colour` a fit whose
    steps are all on the finer level moves the point features and the decoder, never the positions, influence or
    attention."""
    from core.points.train import frozen_on_fine

    mcfg = model_config("card", num_points=600, decoder="unet")
    native = _native(size=32)
    model, _ = fit_points(native, native, mcfg, _cfg(steps=2), show_progress=False)
    names = {id(p): n for n, p in model.named_parameters()}
    assert frozen_on_fine(model, "all") == []
    no_dec = {names[id(p)] for p in frozen_on_fine(model, "no-decoder")}
    assert no_dec and all(n.startswith("decoder.") for n in no_dec)
    colour = {names[id(p)] for p in frozen_on_fine(model, "colour")}
    assert {"xyz", "influence"} <= colour and "features" not in colour
    assert not any(n.startswith("decoder.") for n in colour)
    feats = {names[id(p)] for p in frozen_on_fine(model, "features")}
    assert feats == set(names.values()) - {"features"}
    base = dict(steps=12, train_scales="1,2", train_scale_weights="1,0", prune_every=0, clone_every=0)
    a, _ = fit_points(native, native, mcfg, _cfg(**{**base, "steps": 2}, train_scale_fine="colour"),
                      show_progress=False)
    b, _ = fit_points(native, native, mcfg, _cfg(**base, train_scale_fine="colour"), show_progress=False)
    assert torch.equal(a.xyz, b.xyz) and torch.equal(a.influence, b.influence)
    assert not torch.equal(a.features, b.features) and bool(b.decoder.out.weight.any())


def test_mixed_steps_train_the_training_size_every_step():
    """--train-scale-mix: every step has round(share x patches) patches on the coarsest level and the rest on a
    finer one (one backward); off (0) is the one-level step exactly."""
    from core.points.train import mixed_patches

    assert mixed_patches(16, 0.75, 3) == 12 and mixed_patches(16, 0.0, 3) == 0 and mixed_patches(16, 0.75, 1) == 0
    assert mixed_patches(2, 0.95, 2) == 1 and mixed_patches(2, 0.01, 2) == 1 and mixed_patches(1, 0.5, 2) == 0
    native = _native(size=32)
    mcfg = model_config("card", num_points=600, decoder="unet")
    base = dict(steps=20, patches=4, train_scales="1,2,4", train_scale_weights="1,0,4", prune_every=15,
                clone_every=10)
    plain, h0 = fit_points(native, native, mcfg, _cfg(**base), show_progress=False)
    off, h1 = fit_points(native, native, mcfg, _cfg(**base, train_scale_mix=0.0), show_progress=False)
    assert _same(_state(plain), _state(off))
    model, hist = fit_points(native, native, mcfg, _cfg(**base, train_scale_mix=0.75), show_progress=False)
    # the coarsest in every step; the finer part on level 1 only (level 2's weight is 0)
    assert hist[-1]["train_levels"] == {"1": 20, "2": 0, "4": 20}
    assert all(torch.isfinite(p).all() for p in model.parameters())
    assert hist[-1]["psnr"] > hist[0]["psnr"] + 3
