"""Stage-1 training on tiny analytic scenes (seconds each)."""
import dataclasses
import math

import torch

from core.bundle import Bundle, load_bundle, save_bundle
from core.points.render import render_frame
import core.points.train as train_mod
from core.points.train import DEFAULT_STEPS, TrainConfig, build_optimizer, fit_points, step_cap
from tests.helpers.synthetic import fibonacci_cameras, render_split
from tests.helpers.tiny import model_config

TINY_MODEL = model_config("card", num_points=600)


def _tiny_cfg(**kw):
    base = dict(steps=150, patches=1, patch_size=32, eval_every=1e9, eval_views=2, device="cpu", seed=0, threads=1,
                prune_every=0, clone_every=0, lr_final=0.2)
    base.update(kw)
    return TrainConfig(**base)


def _two_views():
    cams = fibonacci_cameras(2, seed=3)
    split = render_split("sphere", cams, 32)
    return split, split


def test_two_view_scene_overfits():
    train, test = _two_views()
    model, hist = fit_points(train, test, TINY_MODEL, _tiny_cfg(steps=250), show_progress=False)
    assert hist[-1]["psnr"] > 25.0, hist[-1]
    assert hist[-1]["psnr"] > hist[0]["psnr"] + 10


def test_fixed_seed_same_result():
    train, test = _two_views()
    cfg = _tiny_cfg(steps=20)
    m1, h1 = fit_points(train, test, TINY_MODEL, cfg, show_progress=False)
    m2, h2 = fit_points(train, test, TINY_MODEL, cfg, show_progress=False)
    assert torch.equal(m1.xyz, m2.xyz) and torch.equal(m1.features, m2.features)
    assert h1[-1]["psnr"] == h2[-1]["psnr"]


def test_densification_and_regularizers_run_and_stay_finite():
    train, test = _two_views()
    cfg = _tiny_cfg(steps=60, prune_every=10, clone_every=15, reg_start=0.0, max_points=700, clone_frac=0.1)
    model, hist = fit_points(train, test, TINY_MODEL, cfg, show_progress=False)
    assert model.num_points != TINY_MODEL.num_points  # something was pruned or cloned
    for p in (model.xyz, model.features, model.influence):
        assert torch.isfinite(p).all()
    assert model.xyz.shape[0] == model.features.shape[0] == model.influence.shape[0]


def test_model_file_round_trip(tmp_path):
    train, test = _two_views()
    model, _ = fit_points(train, test, TINY_MODEL, _tiny_cfg(steps=5), show_progress=False)
    path = save_bundle(tmp_path / "m.pgt", Bundle(model=model, meta={"scene": {"name": "sphere"}}))
    loaded = load_bundle(path, device="cpu")
    a = render_frame(model, test.c2w[0], 32, 32, test.focal)["rgb"]
    b = render_frame(loaded.model, test.c2w[0], 32, 32, test.focal)["rgb"]
    assert torch.equal(a, b)
    assert loaded.meta["scene"]["name"] == "sphere"


def test_zoom_pixels_tile_each_pixel_and_pool_back():
    from core.points.train import pool_index, pool_zoomed, sample_patches, zoom_pixels

    g = torch.Generator().manual_seed(0)
    px, _, _, size = sample_patches(torch.ones(20, 24), 3, 4, 0.5, g)
    for zoom in (2, 3):
        sub = zoom_pixels(px, size, zoom)
        assert sub.shape == (3 * (4 * zoom) ** 2, 2)
        owner = pool_index(3, size, zoom)
        assert bool(((sub - px[owner]).abs() < 0.5).all())  # every sub-pixel ray lies in its own pixel
        assert torch.allclose(pool_zoomed(sub, 3, size, zoom), px, atol=1e-5)  # ... and they average to its centre
        assert torch.bincount(owner).eq(zoom * zoom).all()


def test_zoomed_steps_train_both_decoders_and_stay_finite():
    train, test = _two_views()
    for decoder in ("none", "unet"):
        cfg = _tiny_cfg(steps=100, zoom_frac=1.0, zoom_max=3, reg_start=0.0)
        model, hist = fit_points(train, test, model_config("card", num_points=600, decoder=decoder), cfg,
                                 show_progress=False)
        for p in model.parameters():
            assert torch.isfinite(p).all()
        assert hist[-1]["psnr"] > hist[0]["psnr"] + 5, (decoder, hist[0]["psnr"], hist[-1]["psnr"])
        assert float(model.train_footprint) > 0
        assert float(model.decoder_footprint) == float(model.train_footprint)  # one scale: the same pixel


def test_step_cap_follows_the_budget_given():
    assert step_cap(TrainConfig()) == DEFAULT_STEPS  # no budget given: the default step count
    assert step_cap(TrainConfig(minutes=10.0)) == float("inf")  # minutes alone: no step cap
    assert step_cap(TrainConfig(steps=50, minutes=10.0)) == 50  # both: whichever ends first
    assert step_cap(TrainConfig(steps=50)) == 50


def test_minutes_alone_train_past_the_default_step_count(monkeypatch):
    """A time budget without --steps runs until the minutes are spent, not until DEFAULT_STEPS (made tiny here);
    without a time budget the default step count ends the fit."""
    monkeypatch.setattr(train_mod, "DEFAULT_STEPS", 3)
    train, test = _two_views()
    _, hist = fit_points(train, test, TINY_MODEL, _tiny_cfg(steps=0), show_progress=False)
    assert hist[-1]["step"] == 3
    _, hist = fit_points(train, test, TINY_MODEL, _tiny_cfg(steps=0, minutes=0.01), show_progress=False)
    assert hist[-1]["step"] > 3 and hist[-1]["seconds"] >= 0.6
    _, hist = fit_points(train, test, TINY_MODEL, _tiny_cfg(steps=2, minutes=0.01), show_progress=False)
    assert hist[-1]["step"] == 2


def test_training_steps_with_workers_equal_the_training_thread(monkeypatch):
    """A stage-1 fit (UNet decoder, regularizers, dropout) with the step's key-MLP chunks and decoder patches on
    two workers (other operations on one torch thread) or all on the training thread: the same points and
    weights after a few steps, to float rounding (small key chunks so that these tiny steps have several)."""
    import functools

    import core.points.model as model_mod
    from core.points.key_mlp import key_logits

    monkeypatch.setattr(model_mod, "key_logits", functools.partial(key_logits, chunk=256))
    before = torch.get_num_threads()
    train = test = render_split("sphere", fibonacci_cameras(6, seed=3), 32)
    mcfg = model_config("card", num_points=500, decoder="unet")
    fits = {w: fit_points(train, test, mcfg, _tiny_cfg(steps=3, patches=2, patch_size=16, reg_start=0.0,
                                                       key_path="chunked", threads=2, workers=w),
                          show_progress=False)[0] for w in (1, 2)}
    for name, p in fits[1].named_parameters():
        p, q = p.detach(), dict(fits[2].named_parameters())[name].detach()
        err = float((p - q).abs().max()) / max(float(p.abs().max()), 1e-12)
        assert err <= 1e-4, f"{name} after 3 steps: {err:.2e}"  # Adam's first steps amplify rounding a little
    assert torch.get_num_threads() == before, "fit_points left the thread count changed"


def test_base_weight_trains_the_decoder_free_render_of_the_residual_unet_only():
    train, test = _two_views()
    for decoder, changes in (("unet", True), ("none", False)):
        mcfg = model_config("card", num_points=600, decoder=decoder)
        feats = [fit_points(train, test, mcfg, _tiny_cfg(steps=5, base_weight=w), show_progress=False)[0].features
                 for w in (0.0, 1.0)]
        assert torch.isfinite(feats[1]).all()
        assert torch.equal(feats[0], feats[1]) != changes, decoder


def test_decoder_weight_decay_shrinks_only_the_decoder():
    train, test = _two_views()
    mcfg = model_config("card", num_points=600, decoder="unet")
    norms = {}
    for wd in (0.0, 50.0):
        model, _ = fit_points(train, test, mcfg, _tiny_cfg(steps=30, decoder_weight_decay=wd), show_progress=False)
        dec = model.decoder.enc1[0].weight
        assert torch.isfinite(dec).all()
        norms[wd] = float(dec.detach().norm())
    assert norms[50.0] < 0.8 * norms[0.0], norms
    groups = {g["name"]: g for g in build_optimizer(model, _tiny_cfg(decoder_weight_decay=50.0)).param_groups}
    assert groups["decoder"]["weight_decay"] == 50.0  # the decoder's weights alone are decayed
    assert all(g["weight_decay"] == 0.0 for n, g in groups.items() if n != "decoder")
    assert {id(p) for p in groups["decoder"]["params"]} == {id(p) for p in model.decoder.parameters()}


def test_dihedral_gives_the_eight_symmetries_and_undoes_them():
    x = torch.arange(2 * 3 * 5 * 5, dtype=torch.float32).reshape(2, 3, 5, 5)
    seen = set()
    for t in range(8):
        y = train_mod.dihedral(x, t)
        assert y.shape == x.shape
        assert torch.equal(train_mod.dihedral(y, t, inverse=True), x)
        seen.add(tuple(y[0, 0].reshape(-1).tolist()))
    assert len(seen) == 8
    assert torch.equal(train_mod.dihedral(x, 1), x.flip(-1)) and torch.equal(train_mod.dihedral(x, 4), x.mT)


def test_decoder_flip_keeps_the_decoded_patch_on_its_target():
    """At initialisation the residual UNet returns its base colour and coverage pixel by pixel, so a first training
    step with the flips must give the same points as one without: any misalignment of the decoded patch and its
    target would change the loss."""
    train, test = _two_views()
    mcfg = model_config("card", num_points=600, decoder="unet")
    used = []
    real = train_mod.dihedral

    def spy(x, t, inverse=False):
        used.append(t)
        return real(x, t, inverse)

    train_mod.dihedral = spy
    try:
        for seed in range(8):
            used.clear()
            on = fit_points(train, test, mcfg, _tiny_cfg(steps=1, seed=seed, decoder_flip=True),
                            show_progress=False)[0]
            if any(t & 4 for t in used) and any(t & 3 for t in used):
                break
        assert any(t & 4 for t in used) and any(t & 3 for t in used), used  # transposed and flipped
        off = fit_points(train, test, mcfg, _tiny_cfg(steps=1, seed=seed, decoder_flip=False),
                         show_progress=False)[0]
    finally:
        train_mod.dihedral = real
    for name in ("xyz", "features", "influence"):
        torch.testing.assert_close(getattr(on, name), getattr(off, name), rtol=1e-5, atol=1e-6)


def test_point_dropout_schedule_decays_to_zero_at_its_end():
    assert train_mod.point_dropout(0.0, 0.3, 0.5) == 0.3
    for frac in (0.1, 0.25, 0.4, 0.5, 0.9):  # the default end: a cosine to 0 at half of training
        assert train_mod.point_dropout(frac, 0.3, 0.5) == 0.3 * train_mod._cosine(min(frac * 2, 1.0))
    assert abs(train_mod.point_dropout(0.4, 0.3, 0.8) - 0.15) < 1e-12  # half-way: half the probability
    assert train_mod.point_dropout(0.8, 0.3, 0.8) < 1e-12 and train_mod.point_dropout(1.0, 0.3, 0.8) == 0.0
    ps = [train_mod.point_dropout(f / 100, 0.5, 1.0) for f in range(101)]
    assert all(a >= b for a, b in zip(ps, ps[1:]))  # non-increasing


def test_feature_dropout_drops_whole_feature_channels_only():
    gen = torch.Generator().manual_seed(0)
    feat = torch.rand(6, 4 + 40, 5, 5) + 0.5
    out = train_mod.feature_dropout(feat, 0.25, 4, gen)
    assert torch.equal(out[:, :4], feat[:, :4])  # base colour and coverage kept
    dropped = (out[:, 4:] == 0).flatten(2)
    assert torch.equal(dropped.all(-1), dropped.any(-1))  # a channel is zeroed as a whole
    kept = ~dropped.all(-1)[..., None, None].expand_as(feat[:, 4:])
    torch.testing.assert_close(out[:, 4:][kept], feat[:, 4:][kept] / 0.75)
    assert 0.1 < float(dropped.all(-1).float().mean()) < 0.4
    assert train_mod.feature_dropout(feat, 0.0, 4, gen) is feat
    extreme = train_mod.feature_dropout(feat, 0.95, 4, gen)
    assert torch.isfinite(extreme).all()


def test_decoder_dropout_trains_and_test_renders_do_not_drop():
    train, test = _two_views()
    mcfg = model_config("card", num_points=600, decoder="unet")
    fits = [fit_points(train, test, mcfg, _tiny_cfg(steps=8, decoder_dropout=p), show_progress=False)[0]
            for p in (0.0, 0.95)]
    assert torch.isfinite(fits[1].features).all() and not torch.equal(fits[0].features, fits[1].features)
    a = render_frame(fits[1], test.c2w[0], 32, 32, test.focal)["rgb"]
    b = render_frame(fits[1], test.c2w[0], 32, 32, test.focal)["rgb"]
    assert torch.equal(a, b)  # no dropout at render time


def test_decoder_stop_freezes_the_decoder_and_the_points_keep_learning():
    f = train_mod.decoder_lr_factor
    assert f(0.9, 0.0) == 1.0 and f(0.2, 0.6) == 1.0 and f(0.3, 0.6) == 1.0 and f(0.6, 0.6) == 0.0
    assert f(1.0, 0.6) == 0.0 and abs(f(0.45, 0.6) - 0.5) < 1e-9
    train, test = _two_views()
    mcfg = model_config("card", num_points=600, decoder="unet")
    first = fit_points(train, test, mcfg, _tiny_cfg(steps=1), show_progress=False)[0]
    # stop = 1e-3 of 30 steps: the decoder learns on the first step only
    late = fit_points(train, test, mcfg, _tiny_cfg(steps=30, decoder_stop=1e-3), show_progress=False)[0]
    for (name, p), q in zip(first.decoder.named_parameters(), late.decoder.parameters()):
        assert torch.equal(p, q), name
    assert not torch.equal(first.features, late.features)


def test_lr_final_groups_override_the_final_fraction_per_group():
    import pytest
    from core.util.errors import InputError
    finals = train_mod.lr_finals(TrainConfig(lr_final=0.05, lr_final_groups="decoder=0.15, xyz=1"))
    assert finals == {"xyz": 1.0, "features": 0.05, "influence": 0.05, "networks": 0.05, "decoder": 0.15}
    assert set(train_mod.lr_finals(TrainConfig())) == set(train_mod.LR_GROUPS)
    for bad in ("points=0.1", "xyz", "xyz=abc", "xyz=0", "xyz=1.5"):
        with pytest.raises(InputError):
            train_mod.lr_finals(TrainConfig(lr_final_groups=bad))
    train, test = _two_views()
    mcfg = model_config("card", num_points=600, decoder="unet")
    every = ",".join(f"{g}=0.2" for g in train_mod.LR_GROUPS)
    ref = fit_points(train, test, mcfg, _tiny_cfg(steps=12, lr_final=0.2), show_progress=False)[0]
    same = fit_points(train, test, mcfg, _tiny_cfg(steps=12, lr_final=0.9, lr_final_groups=every),
                      show_progress=False)[0]
    assert torch.equal(ref.xyz, same.xyz) and torch.equal(ref.features, same.features)
    for p, q in zip(ref.decoder.parameters(), same.decoder.parameters()):
        assert torch.equal(p, q)
    # only the decoder's schedule differs: the step's first update is the same (frac 0), the fit's end is not
    dec = fit_points(train, test, mcfg, _tiny_cfg(steps=12, lr_final=0.2, lr_final_groups="decoder=1"),
                     show_progress=False)[0]
    assert any(not torch.equal(p, q) for p, q in zip(ref.decoder.parameters(), dec.decoder.parameters()))


def test_ray_jitter_shifts_each_patch_as_a_whole():
    gen = torch.Generator().manual_seed(0)
    alpha = torch.zeros(40, 40)
    alpha[10:30, 10:30] = 1.0
    px = train_mod.sample_patches(alpha, 6, 8, 0.5, gen)[0]
    out = train_mod.jitter_patches(px, 6, 0.5, gen)
    shift = (out - px).reshape(6, 64, 2)
    assert torch.allclose(shift, shift[:, :1].expand_as(shift))  # one offset per patch: still a regular grid
    assert float(shift.abs().max()) <= 0.5 and len({tuple(s) for s in shift[:, 0].tolist()}) == 6
    train, test = _two_views()
    a = fit_points(train, test, TINY_MODEL, _tiny_cfg(steps=5, ray_jitter=0.0), show_progress=False)[0]
    b = fit_points(train, test, TINY_MODEL, _tiny_cfg(steps=5, ray_jitter=0.5), show_progress=False)[0]
    assert torch.isfinite(b.xyz).all() and not torch.equal(a.xyz, b.xyz)


def test_bilinear_target_is_the_image_at_pixel_centres_and_interpolates_between_them():
    gen = torch.Generator().manual_seed(1)
    img = torch.rand(9, 11, 3, generator=gen)
    rows, cols = torch.meshgrid(torch.arange(9), torch.arange(11), indexing="ij")
    rows, cols = rows.reshape(-1), cols.reshape(-1)
    centres = torch.stack([cols + 0.5, rows + 0.5], dim=-1).float()
    assert torch.equal(train_mod.sample_bilinear(img, centres), img[rows, cols])  # zero offset: the pixels
    inner = (rows < 8) & (cols < 10)
    for dx, dy in ((1, 0), (0, 1), (1, 1)):  # integer offsets: the neighbouring pixels
        got = train_mod.sample_bilinear(img, centres[inner] + torch.tensor([float(dx), float(dy)]))
        torch.testing.assert_close(got, img[rows[inner] + dy, cols[inner] + dx], rtol=0, atol=1e-7)
    half = train_mod.sample_bilinear(img, centres[inner] + torch.tensor([0.5, 0.0]))
    torch.testing.assert_close(half, 0.5 * (img[rows[inner], cols[inner]] + img[rows[inner], cols[inner] + 1]))
    # exact on a linear ramp at any sub-pixel position inside the outer pixel centres; clamped beyond them
    yy, xx = torch.meshgrid(torch.arange(9.0), torch.arange(11.0), indexing="ij")
    ramp = 0.3 * xx - 0.2 * yy + 1.0                                     # [H, W]: a mask-shaped input
    pos = torch.rand(200, 2, generator=gen) * torch.tensor([10.0, 8.0]) + 0.5
    torch.testing.assert_close(train_mod.sample_bilinear(ramp, pos),
                               0.3 * (pos[:, 0] - 0.5) - 0.2 * (pos[:, 1] - 0.5) + 1.0, rtol=0, atol=1e-5)
    far = train_mod.sample_bilinear(img, torch.tensor([[-1e30, -1e30], [1e30, 1e30], [0.0, 100.0]]))
    torch.testing.assert_close(far, torch.stack([img[0, 0], img[8, 10], img[8, 0]]))


def test_bilinear_jitter_targets_train_and_differ_from_kept_pixels():
    train, test = _two_views()
    kept = fit_points(train, test, TINY_MODEL, _tiny_cfg(steps=5, ray_jitter=0.5, jitter_target="pixel"),
                      show_progress=False)[0]
    interp = fit_points(train, test, TINY_MODEL, _tiny_cfg(steps=5, ray_jitter=0.5, jitter_target="bilinear"),
                        show_progress=False)[0]
    assert torch.isfinite(interp.xyz).all() and torch.isfinite(interp.features).all()
    assert not torch.equal(kept.features, interp.features)
    # without jitter the target rule does nothing
    a = fit_points(train, test, TINY_MODEL, _tiny_cfg(steps=3, ray_jitter=0.0, jitter_target="pixel"),
                   show_progress=False)[0]
    b = fit_points(train, test, TINY_MODEL, _tiny_cfg(steps=3, ray_jitter=0.0, jitter_target="bilinear"),
                   show_progress=False)[0]
    assert torch.equal(a.features, b.features)


def test_parameter_average_follows_its_formula_and_the_point_set():
    from core.points.ema import ParamEMA
    model = train_mod.PointModel(TINY_MODEL, torch.rand(50, 3), 0.1)
    same = ParamEMA(model, 0.0)
    avg = ParamEMA(model, 0.5)
    start = {n: p.detach().clone() for n, p in model.named_parameters()}
    with torch.no_grad():
        for p in model.parameters():
            p.add_(1.0)
    same.update(model)
    avg.update(model)  # warm-up: d = min(0.5, 1 / 10) = 0.1
    for n, p in model.named_parameters():
        assert torch.equal(same.shadow[n], p)  # decay 0: the parameters themselves
        torch.testing.assert_close(avg.shadow[n], 0.1 * start[n] + 0.9 * p.detach())
    assert abs(avg.rate() - 2 / 11) < 1e-12 and ParamEMA(model, 0.999).rate() == 0.1
    src = torch.tensor([3, 3, 7, 0])
    jit = torch.zeros(4, 3)
    jit[1] = 0.25
    before = {n: avg.shadow[n].clone() for n in ("xyz", "features", "influence")}
    avg.resize(("xyz", "features", "influence"), src, jit)
    assert torch.equal(avg.shadow["xyz"], before["xyz"][src] + jit)
    assert torch.equal(avg.shadow["features"], before["features"][src])
    snapshot = {n: p.detach().clone() for n, p in model.named_parameters()}
    pair = ParamEMA(model, 0.5)
    with torch.no_grad():
        for p in pair.shadow.values():
            p.mul_(-3.0)
    pair.swap(model)
    pair.swap(model)
    for n, p in model.named_parameters():
        assert torch.equal(p, snapshot[n])  # swapped twice: unchanged


def test_fit_with_parameter_average_trains_the_same_and_saves_the_average(tmp_path):
    train, test = _two_views()
    # floaters kept: the average's point set and the trained one's may hold different floaters
    kw = dict(steps=40, prune_every=10, clone_every=15, max_points=700, clone_frac=0.1, keep_floaters=True)
    plain, h_plain = fit_points(train, test, TINY_MODEL, _tiny_cfg(**kw), show_progress=False)
    avg, h_avg = fit_points(train, test, TINY_MODEL, _tiny_cfg(ema=0.9, **kw), show_progress=False)
    assert avg.num_points == plain.num_points != TINY_MODEL.num_points  # the average followed the point set
    # the average does not change training: the trained parameters score as the plain fit does
    assert h_avg[-1]["raw"]["psnr"] == h_plain[-1]["psnr"]
    assert "raw" not in h_plain[-1]
    assert not torch.equal(avg.features, plain.features) and torch.isfinite(avg.xyz).all()
    path = save_bundle(tmp_path / "avg.pgt", Bundle(model=avg, meta={"scene": {"name": "sphere"}}))
    loaded = load_bundle(path, device="cpu").model
    for (n, p), q in zip(avg.named_parameters(), loaded.parameters()):
        assert torch.equal(p, q), n
    a = render_frame(avg, test.c2w[0], 32, 32, test.focal)["rgb"]
    assert torch.equal(a, render_frame(loaded, test.c2w[0], 32, 32, test.focal)["rgb"])
    extreme = fit_points(train, test, TINY_MODEL, _tiny_cfg(steps=5, ema=0.9999), show_progress=False)
    assert torch.isfinite(extreme[0].features).all()
    assert math.isfinite(extreme[1][-1]["psnr"]) and math.isfinite(extreme[1][-1]["raw"]["psnr"])


def test_step_views_are_distinct_and_include_the_first():
    gen = torch.Generator().manual_seed(0)
    for first in (0, 3, 9):
        for n in (1, 4, 10, 50):
            views = train_mod.step_views(first, n, 10, gen)
            assert views[0] == first and len(views) == min(n, 10)
            assert len(set(views)) == len(views) and all(0 <= v < 10 for v in views)
    assert train_mod.step_views(0, 5, 1, gen) == [0]  # a single view: nothing else to draw
    for n_patches, n_views in ((16, 1), (16, 5), (16, 16), (7, 3)):
        counts = train_mod.share_patches(n_patches, n_views)
        assert sum(counts) == n_patches and len(counts) == n_views and max(counts) - min(counts) <= 1


def test_views_per_step_draws_each_steps_patches_from_that_many_views(monkeypatch):
    cams = fibonacci_cameras(4, seed=3)
    split = render_split("sphere", cams, 32)
    seen = []  # per neighbour search: the camera and how many rays
    real = train_mod.patch_neighbors

    def spy(points, model_cfg, c2w, level, px, zoom=1):
        if torch.is_grad_enabled():  # a training step's search (test renders run without gradients)
            seen.append((c2w.clone(), px.shape[0]))
        return real(points, model_cfg, c2w, level, px, zoom)
    monkeypatch.setattr(train_mod, "patch_neighbors", spy)
    cfg = _tiny_cfg(steps=6, patches=4, patch_size=8, views_per_step=3)
    model, hist = fit_points(split, split, TINY_MODEL, cfg, show_progress=False)
    assert len(seen) == 6 * 3  # three searches a step, one per view
    for s in range(6):
        step = seen[3 * s: 3 * s + 3]
        assert sorted(n for _, n in step) == [64, 64, 128]  # the 4 patches shared 2 / 1 / 1, 8² rays each
        cams_of_step = {tuple(c.flatten().tolist()) for c, _ in step}
        assert len(cams_of_step) == 3  # three different training views
    assert torch.isfinite(model.xyz).all() and math.isfinite(hist[-1]["psnr"])
    again = fit_points(split, split, TINY_MODEL, cfg, show_progress=False)[0]
    assert torch.equal(model.xyz, again.xyz)  # deterministic for a seed
    one = fit_points(split, split, TINY_MODEL, dataclasses.replace(cfg, views_per_step=1), show_progress=False)[0]
    assert not torch.equal(model.features, one.features)
