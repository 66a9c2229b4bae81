"""Rendering beyond the training resolution (core/points/resolution.py): the scale factor, the training size left
pixel-identical by every mode, and finite frames at extreme scale factors."""
import math

import numpy as np
import pytest
import torch

from core.images.cameras import look_at
from core.points.checkpoint import model_from_arrays, model_to_arrays
from core.points.render import RENDER_MODES, render_frame, shade_frame, trace_frame
from core.points.resolution import (MAX_SCALE, check_mode, decode_at_scale, decoder_scale, filter_sigma,
                                    gate_coverage,
                                    gaussian_blur, interior_weight, pixel_footprint, scale_factor,
                                    training_footprint, training_scale_coverage)
from core.util.errors import InputError
from tests.helpers.tiny import tiny_bundle


@pytest.fixture(scope="module")
def scene():
    bundle, train, test = tiny_bundle("fast")
    return bundle.model, train, test


@pytest.fixture(scope="module")
def unet_scene():
    bundle, train, test = tiny_bundle("fast", decoder="unet")
    return bundle.model, train, test


def test_training_sets_the_footprint_of_its_cameras(scene):
    model, train, _ = scene
    fp = float(model.train_footprint)
    assert fp > 0
    assert fp == pytest.approx(training_footprint(train.c2w, train.focal, model.xyz.detach()), rel=1e-6)
    # one pixel at the object: distance / focal
    d = float((train.c2w[0, :3, 3] - model.xyz.detach().mean(0)).norm())
    assert fp == pytest.approx(d / train.focal, rel=0.05)


def test_scale_factor_follows_the_focal_and_the_distance(scene):
    model, _, test = scene
    fp, pts, c2w, f = float(model.train_footprint), model.xyz.detach(), test.c2w[0], test.focal
    assert scale_factor(fp, c2w, f, pts) == 1.0
    assert scale_factor(fp, c2w, 4 * f, pts) == pytest.approx(4.0, rel=0.06)
    closer = c2w.clone()
    centre = pts.mean(0)
    closer[:3, 3] = centre + 0.5 * (c2w[:3, 3] - centre)
    assert scale_factor(fp, closer, f, pts) == pytest.approx(2.0, rel=0.06)
    assert scale_factor(fp, c2w, 0.5 * f, pts) == pytest.approx(0.5, rel=0.06)  # coarser: no change (F < 1)
    assert scale_factor(0.0, c2w, 4 * f, pts) == 1.0  # unknown footprint (older files)
    assert scale_factor(float("nan"), c2w, 4 * f, pts) == 1.0
    # extremes: a camera at the object's centre, an enormous focal length
    at_centre = c2w.clone()
    at_centre[:3, 3] = pts.mean(0)
    assert pixel_footprint(at_centre, f, pts.double().mean(0)) == pytest.approx(0.0, abs=1e-6)
    assert math.isfinite(scale_factor(fp, at_centre, f, pts)) and scale_factor(fp, at_centre, f, pts) <= MAX_SCALE
    assert scale_factor(fp, c2w, 1e30, pts) == MAX_SCALE


@pytest.mark.parametrize("decoder", ["none", "unet"])
def test_training_size_is_pixel_identical_in_every_mode(scene, unet_scene, decoder):
    model, _, test = scene if decoder == "none" else unet_scene
    c2w, h, w, f = test.c2w[0], test.height, test.width, test.focal
    tr = trace_frame(model, c2w, h, w, f)
    legacy = shade_frame(model, tr)  # the renderer before resolution modes: one ray per pixel, decoder as is
    for mode in ("auto", *RENDER_MODES):
        out = render_frame(model, c2w, h, w, f, mode=mode)
        assert out["scale"] == 1.0
        assert torch.equal(out["rgb"], legacy), mode
    # above the training scale the modes differ from `pixels` (the filter is on)
    big = {m: render_frame(model, c2w, 4 * h, 4 * w, 4 * f, mode=m) for m in ("pixels", "filtered")}
    assert big["pixels"]["scale"] == pytest.approx(4.0, rel=0.06)
    assert not torch.equal(big["pixels"]["rgb"], big["filtered"]["rgb"])


def test_check_mode():
    assert check_mode("auto") in RENDER_MODES
    with pytest.raises(InputError, match="render mode"):
        check_mode("sharp")


def test_gaussian_blur_keeps_constants_and_is_finite_at_any_sigma():
    img = torch.rand(9, 7, 3)
    assert gaussian_blur(img, 0.0) is img
    const = torch.full((9, 7, 3), 0.3)
    for sigma in (0.3, 2.0, 50.0, 1e9, float("inf")):
        out = gaussian_blur(const, sigma)
        assert out.shape == const.shape and torch.allclose(out, const, atol=1e-6), sigma
        out = gaussian_blur(img, sigma)
        assert bool(torch.isfinite(out).all()) and float(out.min()) >= -1e-6 and float(out.max()) <= 1 + 1e-6
    assert gaussian_blur(torch.full((1, 1), 0.5), 10.0).item() == pytest.approx(0.5)
    assert gaussian_blur(img[..., 0], 1.0).shape == (9, 7)
    # a blur of an impulse spreads it with unit sum (away from the edges)
    imp = torch.zeros(31, 31)
    imp[15, 15] = 1.0
    out = gaussian_blur(imp, 2.0)
    assert float(out.sum()) == pytest.approx(1.0, abs=1e-4) and float(out[15, 15]) < 0.1
    assert filter_sigma(1.0) == 0.0 and filter_sigma(0.5) == 0.0 and filter_sigma(5.0) > filter_sigma(2.0) > 0


@pytest.mark.parametrize("scale", [1.0, 1.5, 4.0, 1e3, 1e9])
def test_decoder_at_the_training_scale_is_finite(unet_scene, scale):
    model, _, test = unet_scene
    tr = trace_frame(model, test.c2w[0], test.height, test.width, test.focal)
    parts = model.shade({"weights": tr.weights, "bg": tr.bg}, tr.dirs, tr.idx, torch.ones(3))
    feat = parts["feature"].reshape(test.height, test.width, -1).permute(2, 0, 1)[None]
    with torch.no_grad():
        rgb, alpha = decode_at_scale(model, feat, scale)
        ref_rgb, ref_alpha = model.decode_with_alpha(feat)
    assert rgb.shape == ref_rgb.shape and bool(torch.isfinite(rgb).all())
    if alpha is not None:
        assert alpha.shape == ref_alpha.shape and bool(torch.isfinite(alpha).all())
        assert float(alpha.min()) >= 0 and float(alpha.max()) <= 1
    if scale == 1.0:
        assert torch.equal(rgb, ref_rgb)


def test_the_coverage_gate_hides_specks_the_training_scale_hides_and_keeps_the_object():
    """gate_coverage: an object covered at both scales keeps its full-size coverage up to its silhouette (also
    where the training-scale coverage, upsampled, is already blurred: the window reaches one training pixel), a
    speck the training scale does not cover fades to what that gives it, F <= 1 changes nothing, and extreme
    inputs stay finite in [0, 1]."""
    f = 4.0
    alpha = torch.zeros(40, 40)
    alpha[8:24, 8:24] = 1.0          # the object, sharp at the full size
    alpha[33:36, 33:36] = 0.9        # an isolated speck a few pixels wide
    low = torch.zeros(40, 40)
    low[10:22, 10:22] = 1.0          # the training-scale coverage: the object's edge blurred inwards by 2 px ...
    low[9, 9:23] = low[22, 9:23] = low[9:23, 9] = low[9:23, 22] = 0.5
    low[34, 34] = 0.05               # ... and the speck nearly hidden
    out = gate_coverage(alpha, low, f)
    assert torch.equal(out[:30, :30], alpha[:30, :30])  # object and silhouette untouched
    assert float(out[33:36, 33:36].max()) == pytest.approx(0.05)
    assert bool((out <= alpha).all())
    assert gate_coverage(alpha, low, 1.0) is alpha and gate_coverage(alpha, low, 0.5) is alpha
    bad = alpha.clone()
    bad[0, 0], bad[0, 1], bad[0, 2] = float("nan"), float("inf"), -float("inf")
    weird = low.clone()
    weird[5, 5], weird[6, 6] = float("nan"), float("inf")
    for scale in (1.5, 4.0, 1e9, float("inf")):
        out = gate_coverage(bad, weird, scale)
        assert out.shape == alpha.shape and bool(torch.isfinite(out).all())
        assert float(out.min()) >= 0 and float(out.max()) <= 1
    batch = gate_coverage(alpha[None], low[None], f)  # leading dimensions are kept
    assert batch.shape == (1, 40, 40) and torch.equal(batch[0], gate_coverage(alpha, low, f))
    # a faint blip at the training scale (one pixel of 0.3, its upsampled neighbours fading) under a speck the
    # full size covers 3x3: the speck keeps the blip's own shape, not 0.3 over the whole 3x3
    blip = torch.zeros(40, 40)
    blip[34, 34], blip[33, 34], blip[35, 34] = 0.3, 0.1, 0.1
    out = gate_coverage(alpha, blip, f)
    assert torch.allclose(out[33:36, 33:36], torch.minimum(alpha[33:36, 33:36], blip[33:36, 33:36]))
    assert float(out[33, 33]) == 0.0 and float(out[34, 34]) == pytest.approx(0.3)
    near = low.clone()  # ... while the same blip within a training pixel of the object keeps the window's maximum
    near[26:28, 8:24] = 0.6
    speck = alpha.clone()
    speck[29:32, 12:15] = 0.9
    assert float(gate_coverage(speck, near, f)[29:32, 12:15].min()) == pytest.approx(0.6)


def test_filtered_frames_gate_the_decoder_coverage(unet_scene, scene):
    """Above the training scale `filtered` limits the mask head's coverage by the training-scale one (never
    raising it) and keeps the object colour where it is not limited; `pixels` and models without a mask head are
    not gated."""
    model, _, test = unet_scene
    c2w, h, w, f = test.c2w[0], 4 * test.height, 4 * test.width, 4 * test.focal
    out = render_frame(model, c2w, h, w, f, mode="filtered")
    scale = out["scale"]
    assert scale == pytest.approx(4.0, rel=0.06)
    tr = trace_frame(model, c2w, h, w, f)
    rgb0, a0 = shade_frame(model, tr, with_alpha=True)
    rgb1, a1 = shade_frame(model, tr, with_alpha=True, coverage_scale=scale)
    assert bool((a1 <= a0 + 1e-6).all())
    assert float((a0 - a1).max()) > 1e-4  # the tiny model's decoder covers some rays only at the full size
    same = (a1 - a0).abs() < 1e-6
    assert bool(same.any())
    assert torch.allclose(rgb1[same], rgb0[same], atol=1e-5)
    parts = model.shade({"weights": tr.weights, "bg": tr.bg}, tr.dirs, tr.idx, torch.ones(3))
    feat = parts["feature"].reshape(h, w, -1).permute(2, 0, 1)[None]
    with torch.no_grad():
        low = training_scale_coverage(model, feat, scale)
        assert torch.allclose(a1, gate_coverage(a0, low[0], scale), atol=1e-5)
        assert training_scale_coverage(model, feat, 1.0) is None
    plain, _, _ = scene  # no decoder: nothing to gate
    tr = trace_frame(plain, c2w, h, w, f)
    assert torch.equal(shade_frame(plain, tr), shade_frame(plain, tr, coverage_scale=scale))
    sigma = filter_sigma(scale)
    assert not torch.allclose(gaussian_blur(a0, sigma), gaussian_blur(a1, sigma), atol=1e-5)
    assert torch.allclose(out["alpha"], gaussian_blur(a1, sigma).clamp(0, 1), atol=1e-5)
    assert torch.allclose(out["rgb"], gaussian_blur(rgb1, sigma).clamp(0, 1), atol=1e-5)


def test_interior_weight_is_the_coverage_eroded_by_one_training_pixel():
    """interior_weight: 1 deep inside a covered region, 0 within ⌈F⌉ pixels of its silhouette and outside, the
    coverage itself where it is partial, no rim at the frame's border, zeros for F <= 1, finite in [0, 1]."""
    cov = torch.zeros(30, 30)
    cov[5:25, 5:25] = 1.0
    cov[12:18, 12:18] = 0.6          # a partially covered patch well inside
    w = interior_weight(cov, 3.0)   # erosion by 3 pixels
    assert float(w[8:22, 8:22].min()) == pytest.approx(0.6) and float(w[8, 8:22].min()) == 1.0
    assert float(w[:8].max()) == 0.0 and float(w[:, 22:].max()) == 0.0  # the silhouette band and outside
    assert float(w[8, 8]) == 1.0 and float(w[7, 10]) == 0.0
    assert torch.equal(interior_weight(cov, 2.5), w)  # ⌈F⌉ pixels
    full = torch.ones(6, 8)          # an object filling the frame: its border is no silhouette
    assert torch.equal(interior_weight(full, 4.0), full)
    assert torch.equal(interior_weight(cov, 1.0), torch.zeros_like(cov))
    assert torch.equal(interior_weight(cov, 0.5), torch.zeros_like(cov))
    bad = cov.clone()
    bad[0, 0], bad[1, 1], bad[20, 20] = float("nan"), float("inf"), -float("inf")
    for scale in (1.5, 4.0, 1e9, float("inf"), float("nan")):
        out = interior_weight(bad, scale)
        assert out.shape == cov.shape and bool(torch.isfinite(out).all())
        assert float(out.min()) >= 0 and float(out.max()) <= 1
    assert float(interior_weight(bad, 4.0)[16:25, 16:25].max()) == 0.0  # -inf counts as uncovered
    assert interior_weight(cov[None], 3.0).shape == (1, 30, 30)


def test_interior_mode_decodes_the_inside_at_the_training_scale_and_the_silhouette_at_the_full_size(unet_scene):
    """shade_frame with interior_scale F: the full-size decode and the training-scale one (`decode_at_scale`)
    mixed per pixel by interior_weight of the training scale's coverage, colour and coverage, then composited over
    the background — the full-size frame where the weight is 0 (the silhouette band, the background); the render
    mode `interior` is that frame."""
    from core.points.render import decode_where_active

    model, _, test = unet_scene
    c2w, h, w, f = test.c2w[0], 4 * test.height, 4 * test.width, 4 * test.focal
    tr = trace_frame(model, c2w, h, w, f)
    scale = render_frame(model, c2w, h, w, f, mode="pixels")["scale"]
    full, a_full = shade_frame(model, tr, with_alpha=True)
    mixed, a_mix = shade_frame(model, tr, with_alpha=True, interior_scale=scale)
    parts = model.shade({"weights": tr.weights, "bg": tr.bg}, tr.dirs, tr.idx, torch.ones(3))
    feat = parts["feature"].reshape(h, w, -1).permute(2, 0, 1)[None]
    with torch.no_grad():
        rgb_lo, alpha_lo = decode_at_scale(model, feat, scale)
        rgb_hi, alpha_hi = decode_where_active(model, feat, tr.active.reshape(h, w))
    wgt = interior_weight(alpha_lo[0], scale)
    assert float(wgt.max()) > 0.3 and float(wgt.min()) < 1e-5  # the tiny model's interior is partly covered
    rgb = wgt[..., None] * rgb_lo[0].permute(1, 2, 0) + (1 - wgt[..., None]) * rgb_hi[0].permute(1, 2, 0)
    cover = (wgt * alpha_lo[0] + (1 - wgt) * alpha_hi[0])[..., None]
    c = ((rgb - (1 - cover)) / cover.clamp_min(1e-4)).clamp(0, 1)  # over white, composited over white again
    ref = (cover * c + (1 - cover)).clamp(0, 1)
    assert torch.allclose(mixed, ref, atol=1e-5) and torch.allclose(a_mix, cover[..., 0], atol=1e-6)
    zero = wgt < 1e-5
    assert torch.allclose(mixed[zero], full[zero], atol=1e-4) and torch.allclose(a_mix[zero], a_full[zero], atol=1e-5)
    assert not torch.allclose(mixed, full, atol=1e-3)  # the interior differs
    out = render_frame(model, c2w, h, w, f, mode="interior")
    assert torch.allclose(out["rgb"], mixed, atol=1e-6) and torch.allclose(out["alpha"], a_mix, atol=1e-6)
    plain = render_frame(model, c2w, h, w, f, mode="pixels")  # `pixels` is the full-size frame
    assert torch.allclose(plain["rgb"], full, atol=1e-6)


def test_a_multi_scale_model_runs_its_decoder_at_the_training_size(unet_scene):
    """A model whose decoder_footprint is 4x its train_footprint (a multi-scale fit from 4x images: the
    footprint is the finest level's, the decoder's the training size's) renders the training size in every mode
    as it is, and at 4x that size (its finest level: scale factor 1, nothing filtered) the `interior` and
    `decoder` modes decode at the training size; without a decoder_footprint (older files, single-scale fits) the
    decoder's scale factor is the frame's."""
    import copy

    model, _, test = unet_scene
    c2w, h, w, f, pts = test.c2w[0], test.height, test.width, test.focal, model.xyz.detach()
    assert float(model.decoder_footprint) == float(model.train_footprint)  # the fit's own, one scale
    for times in (0.5, 1.0, 4.0):
        assert decoder_scale(model, None, c2w, times * f, pts) == max(1.0, scale_factor(
            float(model.train_footprint), c2w, times * f, pts))  # F <= 1: the training scale
    multi = copy.deepcopy(model)
    multi.train_footprint.fill_(float(model.train_footprint) / 4)
    assert decoder_scale(multi, None, c2w, f, pts) == 1.0
    assert decoder_scale(multi, None, c2w, 4 * f, pts) == pytest.approx(4.0, rel=0.06)
    assert decoder_scale(multi, 1.0, c2w, 4 * f, pts) == pytest.approx(4.0, rel=1e-5)  # the caller's F, scaled
    assert decoder_scale(multi, 0.25, c2w, f, pts) == 1.0
    legacy = shade_frame(multi, trace_frame(multi, c2w, h, w, f))
    for mode in RENDER_MODES:
        out = render_frame(multi, c2w, h, w, f, mode=mode)
        assert torch.equal(out["rgb"], legacy), mode
    big = {m: render_frame(multi, c2w, 4 * h, 4 * w, 4 * f, mode=m) for m in ("pixels", "filtered", "interior")}
    assert all(o["scale"] == 1.0 for o in big.values())
    tr = trace_frame(multi, c2w, 4 * h, 4 * w, 4 * f)
    fd = decoder_scale(multi, None, c2w, 4 * f, pts)
    # the finest level: no blur, the mask head's coverage gated by the one it gives at the decoder's size
    gated, gated_alpha = shade_frame(multi, tr, with_alpha=True, coverage_scale=fd)
    assert torch.allclose(big["filtered"]["rgb"], gated, atol=1e-6)
    assert torch.allclose(big["filtered"]["alpha"], gated_alpha, atol=1e-6)
    assert torch.equal(big["pixels"]["rgb"], shade_frame(multi, tr))
    assert torch.allclose(big["interior"]["rgb"], shade_frame(multi, tr, interior_scale=fd), atol=1e-6)
    assert not torch.allclose(big["interior"]["rgb"], big["pixels"]["rgb"], atol=1e-3)
    arrays, meta = model_to_arrays(multi)  # the model file keeps it; older files load with 0 (= train_footprint)
    assert float(model_from_arrays(arrays, meta).decoder_footprint) == pytest.approx(float(model.train_footprint))
    old = model_from_arrays({k: v for k, v in arrays.items() if k != "net/decoder_footprint"}, meta)
    assert float(old.decoder_footprint) == 0.0 and decoder_scale(old, 1.0, c2w, 4 * f, pts) == 1.0
    multi.decoder_footprint.fill_(float("nan"))  # not finite: the frame's own scale factor
    assert decoder_scale(multi, 3.0, c2w, f, pts) == 3.0


def test_the_fit_measures_which_decode_auto_uses(unet_scene, scene):
    """`auto` follows the interior gain a multi-scale fit stores (core.points.train.interior_gain:
    `interior+filtered` − `filtered` in object PSNR on views finer than the decoder's training size):
    `interior+filtered` when it is positive, `filtered` otherwise; a single-scale fit (with or without a decoder,
    nothing measured) renders `upsampled`, the training-size frame upsampled."""
    import copy

    from core.images.metrics import mean_scores, score_views
    from core.points.resolution import auto_mode
    from core.points.train import INTERIOR_VIEWS, interior_gain

    model, train, test = unet_scene
    assert float(model.interior_gain) == 0.0 and auto_mode(model) == "upsampled"  # one scale: nothing measured
    assert math.isnan(interior_gain(model, train))  # the decoder runs at these views' size: nothing to compare
    multi = copy.deepcopy(model)  # as if its decoder had trained at half these views' size (a coarser level)
    multi.decoder_footprint.fill_(2 * float(model.train_footprint))
    gain = interior_gain(multi, train)
    ids = sorted({int(i) for i in torch.linspace(0, len(train.c2w) - 1, INTERIOR_VIEWS).round().tolist()})

    def score(mode):
        def render(i):
            return render_frame(multi, train.c2w[i], train.height, train.width, train.focal, mode=mode)
        return mean_scores(score_views(render, train.images, train.alphas, ids))["psnr_object"]
    assert math.isfinite(gain) and abs(gain) > 1e-4
    assert gain == pytest.approx(score("interior+filtered") - score("filtered"), abs=1e-6)
    c2w, h, w, f = test.c2w[0], 3 * test.height, 3 * test.width, 3 * test.focal
    for g, mode in ((0.3, "interior+filtered"), (-0.3, "filtered"), (0.0, "filtered")):
        m = copy.deepcopy(multi)
        m.interior_gain.fill_(g)
        assert auto_mode(m) == check_mode("auto", m) == mode
        assert torch.equal(render_frame(m, c2w, h, w, f)["rgb"], render_frame(m, c2w, h, w, f, mode=mode)["rgb"])
    plain, ptrain, _ = scene
    assert math.isnan(interior_gain(plain, ptrain)) and float(plain.interior_gain) == 0.0
    assert auto_mode(plain) == "upsampled"  # a single-scale fit, no decoder
    assert torch.equal(render_frame(model, c2w, h, w, f)["rgb"], render_frame(model, c2w, h, w, f, mode="upsampled")["rgb"])
    for fp in (0.0, float("nan"), float("inf")):  # older or damaged files: a single-scale fit's mode, never raises
        m = copy.deepcopy(model)
        m.decoder_footprint.fill_(fp)
        assert auto_mode(m) == "upsampled"


@pytest.mark.parametrize("decoder", ["none", "unet"])
@pytest.mark.parametrize("factor", [3, 4.1])
def test_upsampled_frames_are_the_training_size_frame_upsampled(scene, unet_scene, decoder, factor):
    """`upsampled` renders the frame at the training scale (H/F, F within 5 % of a whole number counting as it)
    and upsamples it bicubically; x (the surface per pixel) stays at the full size."""
    from core.points.resolution import low_size, upsample_frame

    model, _, test = scene if decoder == "none" else unet_scene
    c2w, h, w, f = test.c2w[0], test.height, test.width, test.focal
    big = render_frame(model, c2w, 3 * h, 3 * w, factor * f, mode="upsampled")
    lh, lw, s = low_size(3 * h, 3 * w, big["scale"])
    assert (lh, lw) == ((h, w) if factor == 3 else (lh, lw)) and big["x"].shape == (3 * h, 3 * w, 3)
    low = render_frame(model, c2w, lh, lw, factor * f * s, mode="pixels")
    assert torch.equal(big["rgb"], upsample_frame(low["rgb"], 3 * h, 3 * w))
    assert torch.equal(big["alpha"], upsample_frame(low["alpha"], 3 * h, 3 * w))
    for k in ("rgb", "alpha"):
        assert bool(torch.isfinite(big[k]).all()) and float(big[k].min()) >= 0 and float(big[k].max()) <= 1


def test_upsample_frame_keeps_constants_and_pixel_centres():
    """The bicubic of `upsampled` (and of the resolution benchmark's bar): constants stay, pixel centres align."""
    from core.points.resolution import upsample_frame

    img = torch.full((4, 5, 3), 0.25)
    assert upsample_frame(img, 4, 5) is not None and torch.equal(upsample_frame(img, 4, 5), img)
    up = upsample_frame(img, 12, 15)
    assert up.shape == (12, 15, 3) and torch.allclose(up, img[:1, :1].expand(12, 15, 3))
    ramp = torch.linspace(0, 1, 8)[None, :, None].expand(8, 8, 3).contiguous()
    up = upsample_frame(ramp, 16, 16)
    # fine pixels 2c and 2c + 1 sit a quarter coarse pixel either side of coarse pixel c's centre
    assert torch.allclose((up[:, 2:14:2] + up[:, 3:15:2]) / 2, ramp[:1, 1:7].expand(16, 6, 3), atol=5e-3)
    assert bool((up[0, 3:14, 0] > up[0, 2:13, 0]).all())  # and the ramp stays increasing
    assert upsample_frame(img[..., 0], 8, 10).shape == (8, 10)


def test_low_size_snaps_to_whole_factors_and_stays_positive():
    from core.points.resolution import low_size

    assert low_size(256, 256, 4.09) == (64, 64, 0.25)
    assert low_size(256, 128, 3.9) == (64, 32, 0.25)
    h, w, s = low_size(256, 256, 3.5)
    assert (h, w) == (73, 73) and s == pytest.approx(73 / 256)
    assert low_size(10, 20, 1e9)[:2] == (1, 2) and low_size(10, 10, 0.5) == (10, 10, 1.0)


@pytest.mark.parametrize("mode", RENDER_MODES)
@pytest.mark.parametrize("focal_times", [3.0, 1e4, 1e12])
def test_extreme_scale_factors_render_finite_frames(unet_scene, mode, focal_times):
    model, _, test = unet_scene
    out = render_frame(model, test.c2w[0], 12, 12, test.focal * focal_times, mode=mode)
    assert out["scale"] > 1 and out["scale"] <= MAX_SCALE
    for k in ("rgb", "alpha"):
        assert bool(torch.isfinite(out[k]).all()) and float(out[k].min()) >= 0 and float(out[k].max()) <= 1, k
    # a camera inside the point cloud (distance ~ 0: the largest scale factors)
    inside = look_at(model.xyz.detach().mean(0) + torch.tensor([0.0, 0.0, 1e-7]), model.xyz.detach().mean(0))
    out = render_frame(model, inside, 12, 12, test.focal, mode=mode)
    assert bool(torch.isfinite(out["rgb"]).all()) and bool(torch.isfinite(out["alpha"]).all())


def test_model_files_without_a_footprint_still_load(scene):
    model, _, _ = scene
    arrays, meta = model_to_arrays(model)
    assert float(arrays["net/train_footprint"]) == pytest.approx(float(model.train_footprint))
    back = model_from_arrays(arrays, meta)
    assert float(back.train_footprint) == pytest.approx(float(model.train_footprint))
    old = {k: v for k, v in arrays.items() if k != "net/train_footprint"}
    legacy = model_from_arrays(old, meta)
    assert float(legacy.train_footprint) == 0.0  # unknown: every size renders as the training size
    assert np.array_equal(legacy.xyz.detach().numpy(), model.xyz.detach().numpy())


@pytest.mark.parametrize("method", ["screen", "screen_depth", "perpendicular"])
def test_soft_selection_without_width_keeps_the_k_nearest_and_fades_with_it(scene, method):
    from core.points.neighbors.select import select_neighbors, select_neighbors_soft
    from core.points.render import pixel_grid
    from core.images.cameras import pixel_rays

    model, _, test = scene
    c2w, h, w, f = test.c2w[0], test.height, test.width, test.focal
    o, d = pixel_rays(c2w, h, w, f)
    o, d, px = o.reshape(-1, 3), d.reshape(-1, 3), pixel_grid(h, w, "cpu")
    k = model.cfg.k
    hard = select_neighbors(model.xyz.detach(), method, k, c2w, h, w, f, px, o, d)
    idx, log_w = select_neighbors_soft(model.xyz.detach(), method, k, c2w, h, w, f, px, o, d, width_px=0.0)
    kept = [set(r[r >= 0].tolist()) for r in idx]
    assert kept == [set(r[r >= 0].tolist()) for r in hard]
    assert bool((log_w == 0).all())
    idx, log_w = select_neighbors_soft(model.xyz.detach(), method, k, c2w, h, w, f, px, o, d, width_px=3.0)
    assert bool(torch.isfinite(log_w).all()) and float(log_w.max()) <= 0
    if method != "perpendicular":
        assert idx.shape[1] == 2 * k and float(log_w.min()) < 0  # some neighbours fade
        # every hard neighbour is still there
        soft = [set(r[r >= 0].tolist()) for r in idx]
        assert all(a <= b for a, b in zip([set(r[r >= 0].tolist()) for r in hard], soft))


def test_edited_frames_follow_the_render_mode():
    from core.frames.edited import EditConfig, EditState, render_edited

    bundle, _, test = tiny_bundle("card")
    c2w, h, w, f = test.c2w[0], test.height, test.width, test.focal
    frames = {}
    for mode in ("pixels", "filtered", "upsampled"):
        state = EditState(bundle, atlas=bundle.atlas.packed_image(), cfg=EditConfig(render_mode=mode))
        one = render_edited(state, c2w, h, w, f)
        assert one["stats"]["scale"] == 1.0
        frames[mode, 1] = one["rgb"]
        four = render_edited(state, c2w, 3 * h, 3 * w, 3 * f)
        assert four["stats"]["scale"] == pytest.approx(3.0, rel=0.06)
        assert bool(torch.isfinite(four["rgb"]).all()) and bool(torch.isfinite(four["alpha"]).all())
        frames[mode, 3] = four["rgb"]
    assert torch.equal(frames["pixels", 1], frames["filtered", 1])  # the training size: the same in every mode
    assert torch.equal(frames["pixels", 1], frames["upsampled", 1])
    assert not torch.equal(frames["pixels", 3], frames["filtered", 3])
    # upsampled: the unedited frame is render_frame's (the training-size frame upsampled)
    state = EditState(bundle, atlas=bundle.atlas.packed_image(), cfg=EditConfig(render_mode="upsampled"))
    plain = render_frame(bundle.model, c2w, 3 * h, 3 * w, 3 * f, mode="upsampled")
    assert torch.allclose(frames["upsampled", 3], plain["rgb"], atol=1e-5)


def test_upsampled_edited_frames_keep_the_painted_texture_at_the_full_size():
    """The model's colour comes from the training scale; a texture painted on the atlas is looked up per ray of the
    full-size frame, so a fine pattern stays as sharp as in the `pixels` mode."""
    from core.frames.edited import EditConfig, EditState, render_edited

    bundle, _, test = tiny_bundle("card")
    c2w, h, w, f = test.c2w[0], 4 * test.height, 4 * test.width, 4 * test.focal

    def checker(x):  # a pattern finer than a training pixel on the card
        v = (torch.floor(x[:, 0] * 40) + torch.floor(x[:, 1] * 40)) % 2
        return torch.stack([v, 1 - v, 0.5 * torch.ones_like(v)], 1)
    painted = bundle.atlas.packed_image().clone()
    painted[::2] = 1.0 - painted[::2]  # an edited atlas: the frame looks its texture up
    out = {}
    for mode in ("pixels", "upsampled"):
        state = EditState(bundle, atlas=painted, cfg=EditConfig(render_mode=mode))
        out[mode] = render_edited(state, c2w, h, w, f, texture_fn=checker)
    painted = torch.isfinite(out["pixels"]["x_can"]).all(-1)
    up = torch.isfinite(out["upsampled"]["x_can"]).all(-1)
    # the upsampled trace is interpolated from the training-scale rays: it textures the same rays, and a band of
    # at most one training pixel (4 pixels) beyond them where the coverage falls off
    grown = torch.nn.functional.max_pool2d(painted[None, None].float(), 9, stride=1, padding=4)[0, 0] > 0
    assert int(painted.sum()) > 50 and bool(up[painted].all()) and bool(grown[up].all())

    def detail(img):  # mean absolute difference between neighbouring pixels over the painted rays
        d = (img[1:, :] - img[:-1, :]).abs().sum(-1)
        return float(d[painted[1:, :] & painted[:-1, :]].mean())
    assert detail(out["upsampled"]["rgb"]) > 0.8 * detail(out["pixels"]["rgb"])


@pytest.mark.parametrize("s", [0.1, 10.0])
def test_a_scaled_object_keeps_its_scale_factor(scene, s):
    """Points scaled by s (an object scaled in Blender) seen from s times the distance: the same picture, so the
    same scale factor — the training pixel counts in the points' own size."""
    from core.frames.edited import EditState, render_edited

    model, _, test = scene
    bundle, _, _ = tiny_bundle("fast")
    xyz = model.xyz.detach()
    cam = test.c2w[0].clone()
    cam[:3, 3] *= s
    state = EditState(bundle, points=xyz * s)
    assert state.local_scale == pytest.approx(s, rel=1e-3)
    for size, want in ((test.width, 1.0), (3 * test.width, 3.0)):
        f = test.focal * size / test.width
        edited = render_edited(state, cam, size, size, f)
        assert edited["stats"]["scale"] == pytest.approx(want, rel=0.06)
    assert EditState(bundle).local_scale == 1.0
