"""The residual decoder (starts as, and cannot saturate below, the decoder-free render) and the stage-1 collapse
guard (detects a fit that renders the blank frame or loses its object, recovers, records what it did)."""
import math

import pytest
import torch

import core.points.train as train_mod
from core.points.render import render_frame
from core.points.model import PointModel, mean_spacing
from core.points.train import CollapseGuard, TrainConfig, collapse_reason, decline_reason, evaluate, fit_points
from tests.helpers.synthetic import fibonacci_cameras, render_split
from tests.helpers.tiny import model_config


def _split():
    return render_split("sphere", fibonacci_cameras(2, seed=3), 32)


def _pair():
    """A residual-UNet model and a decoder-free model sharing points, attention and point colours."""
    torch.manual_seed(0)
    xyz = torch.rand(500, 3) - 0.5
    dec = PointModel(model_config("fast", decoder="unet"), xyz, mean_spacing(xyz))
    plain = PointModel(model_config("fast", decoder="none"), xyz, mean_spacing(xyz))
    with torch.no_grad():
        for name in ("xyz", "features", "influence", "bg_logit"):
            getattr(plain, name).copy_(getattr(dec, name))
        plain.key_mlp.load_state_dict(dec.key_mlp.state_dict())
        plain.value_mlp[0].load_state_dict(dec.value_mlp[0].state_dict())
        plain.value_mlp[2].weight.copy_(dec.value_mlp[2].weight[:3])  # the colour rows of the residual's values
        plain.value_mlp[2].bias.copy_(dec.value_mlp[2].bias[:3])
    return dec, plain


def test_residual_decoder_starts_as_the_decoder_free_render():
    dec, plain = _pair()
    split = _split()
    for i in range(2):
        for bg in ((1.0, 1.0, 1.0), (0.0, 0.0, 0.0)):  # colour and coverage: the same over any background
            a = render_frame(dec, split.c2w[i], 32, 32, split.focal, background=bg)
            b = render_frame(plain, split.c2w[i], 32, 32, split.focal, background=bg)
            assert float((a["rgb"] - b["rgb"]).abs().max()) < 1e-5
            assert float((a["alpha"] - b["alpha"]).abs().max()) < 1e-3  # the coverage logit is clamped at 1e-6
            assert float((a["rgb"] - torch.tensor(bg)).abs().mean()) > 0.01  # not trivially the blank frame


def _train_decoder(model, steps=100):
    torch.manual_seed(1)
    c = model.decoder.out.in_channels
    feat = torch.rand(2, 4 + model.cfg.feature_dim if model.cfg.decoder_residual else model.cfg.feature_dim, 16, 16)
    target = torch.rand(2, 3, 16, 16) * 0.8 + 0.1
    opt = torch.optim.Adam(model.decoder.parameters(), lr=5e-2)
    losses = []
    for _ in range(steps):
        loss = torch.nn.functional.mse_loss(model.decode(feat), target)
        opt.zero_grad()
        loss.backward()
        opt.step()
        losses.append(float(loss.detach()))
    assert c > 0
    return losses


@pytest.mark.parametrize("residual", [True, False])
def test_decoder_forced_into_saturation(residual):
    """Pushed far outside [0, 1] (the blank-white collapse), the residual decoder still gets a gradient and trains
    back; the older sigmoid decoder does not move (why it used to collapse for good)."""
    torch.manual_seed(0)
    xyz = torch.rand(200, 3) - 0.5
    m = PointModel(model_config("fast", decoder="unet", decoder_residual=residual), xyz, mean_spacing(xyz))
    with torch.no_grad():
        m.decoder.out.bias.fill_(20.0)
    losses = _train_decoder(m)
    if residual:
        assert losses[-1] < 0.5 * losses[0]
    else:
        assert losses[-1] > 0.99 * losses[0]


def test_reset_decoder_correction_restores_the_base_render():
    dec, plain = _pair()
    with torch.no_grad():
        for p in dec.decoder.parameters():
            p.add_(0.5 * torch.randn_like(p))
    split = _split()
    assert float((render_frame(dec, split.c2w[0], 32, 32, split.focal)["rgb"]
                  - render_frame(plain, split.c2w[0], 32, 32, split.focal)["rgb"]).abs().max()) > 1e-3
    dec.reset_decoder_correction()
    a = render_frame(dec, split.c2w[0], 32, 32, split.focal)["rgb"]
    b = render_frame(plain, split.c2w[0], 32, 32, split.focal)["rgb"]
    assert float((a - b).abs().max()) < 1e-5


FLOOR = {"psnr": 20.0, "psnr_object": 8.0}
GOOD = {"psnr": 30.0, "psnr_object": 20.0, "coverage": 0.97, "blank_distance": 0.4, "object_contrast": 0.45}


def test_decline_reason_cases():
    assert decline_reason(None, GOOD, 3.0) is None  # nothing to fall from yet
    assert decline_reason((300, 22.9), GOOD, 3.0) is None  # 2.9 dB: a healthy fit's dip
    assert decline_reason((300, 30.0), GOOD, 0.0) is None  # off
    assert decline_reason((300, 30.0), {**GOOD, "psnr_object": float("nan")}, 3.0) is None  # collapse_reason's case
    why = decline_reason((330, 23.5), {**GOOD, "coverage": 0.87}, 3.0)
    assert "from 23.50 dB at step 330 to 20.00 dB" in why and "coverage 0.87" in why

def test_collapse_reason_cases():
    assert collapse_reason(GOOD, FLOOR, 1.0) is None
    assert "blank frame" in collapse_reason({**GOOD, "psnr_object": 8.2, "blank_distance": 0.01}, FLOOR, 1.0)
    assert "covers 10 %" in collapse_reason({**GOOD, "coverage": 0.1}, FLOOR, 1.0)
    assert "not finite" in collapse_reason({**GOOD, "psnr": float("nan")}, FLOOR, 1.0)
    # an undertrained grey render near the floor is poor, not blank
    assert collapse_reason({**GOOD, "psnr_object": 8.5, "blank_distance": 0.3}, FLOOR, 1.0) is None
    # a near-white object on white, rendered right: its truth is as close to the background as the render
    white = {"psnr": 40.0, "psnr_object": 31.0, "coverage": 0.99, "blank_distance": 0.02, "object_contrast": 0.021}
    assert collapse_reason(white, {"psnr": 39.5, "psnr_object": 30.5}, 1.0) is None


def test_guard_actions_order():
    torch.manual_seed(0)
    xyz = torch.rand(200, 3) - 0.5
    dec = PointModel(model_config("fast", decoder="unet"), xyz, mean_spacing(xyz))
    g = CollapseGuard(FLOOR, 1.0)
    blank = {**GOOD, "psnr_object": 8.0, "blank_distance": 0.0}
    assert g.check(dec, blank, step=10, frac=0.5) == (None, None)  # too early for a verdict
    assert g.check(dec, GOOD, step=500, frac=0.5) == (None, None)
    action, reason = g.check(dec, blank, step=500, frac=0.5)
    assert action == "reset_decoder" and "blank frame" in reason
    g.decoder_resets = 1
    assert g.check(dec, blank, step=600, frac=0.6)[0] == "restart"
    assert not g.step_ok(torch.tensor(float("nan")), dec) and g.skipped_steps == 1


def test_guard_refits_a_fit_that_loses_its_object_while_budget_is_left():
    torch.manual_seed(0)
    xyz = torch.rand(200, 3) - 0.5
    dec = PointModel(model_config("fast", decoder="unet"), xyz, mean_spacing(xyz))
    g = CollapseGuard(FLOOR, 1.0, 3.0)
    assert g.check(dec, {**GOOD, "psnr_object": 30.0}, step=10, frac=0.01) == (None, None)  # too early: no best
    assert g.check(dec, GOOD, step=300, frac=0.1) == (None, None) and g.best == (300, 20.0)
    assert g.check(dec, {**GOOD, "psnr_object": 17.5}, step=400, frac=0.2) == (None, None)  # 2.5 dB below
    assert g.best == (300, 20.0)
    action, reason = g.check(dec, {**GOOD, "psnr_object": 16.5}, step=600, frac=0.4)
    assert action == "refit" and "from 20.00 dB at step 300" in reason
    assert g.check(dec, {**GOOD, "psnr_object": 16.5}, step=900, frac=0.7)[0] is None  # too late to start again
    g.restarts = CollapseGuard.MAX_RESTARTS
    assert g.check(dec, {**GOOD, "psnr_object": 16.5}, step=600, frac=0.4)[0] is None
    off = CollapseGuard(FLOOR, 1.0, 0.0)
    off.check(dec, GOOD, step=300, frac=0.1)
    assert off.check(dec, {**GOOD, "psnr_object": 5.0, "blank_distance": 0.4}, step=600, frac=0.4) == (None, None)


def test_a_declining_fit_is_restarted_with_its_settings_and_a_late_decline_reported(monkeypatch):
    """The test curve as the fit sees it (a scripted `evaluate`): 20 dB, then 15 at half the budget (restart with
    the same settings, decoder kept), 18 on the new course, 14 after 0.6 of what was left (reported, not acted
    on)."""
    calls = []

    def scripted(model, split, views, background):
        n = len(calls)
        calls.append(n)
        return {**GOOD, "ssim": 0.9, "psnr_object": 20.0 if n < 60 else 15.0 if n == 60 else 18.0 if n < 100 else 14.0}

    monkeypatch.setattr(train_mod, "evaluate", scripted)
    split = _split()
    cfg = TrainConfig(steps=120, patches=1, patch_size=16, eval_every=0.0, eval_views=1, device="cpu", seed=1,
                      threads=1, prune_every=0, clone_every=0, ema=0.0)
    model, hist = fit_points(split, split, model_config("fast", decoder="unet"), cfg, show_progress=False)
    guard = hist[-1]["guard"]
    assert [e["action"] for e in guard["events"]] == ["restarted the fit with the same settings"]
    assert guard["events"][0]["step"] == 60 and model.decoder is not None
    assert "from 18.00 dB" in guard["declined"] and guard["collapsed"] is None


@pytest.mark.parametrize("ema", [0.0, 0.9])
def test_a_saturated_decoder_fit_is_caught_and_recovers(monkeypatch, ema):
    """The collapse that used to ship: a sigmoid decoder stuck on the white background. The guard notices it at a
    checkpoint, restarts without a decoder, and the fit ends well above the blank floor, with the event recorded;
    with a moving average of the parameters (--ema), the average restarts with the new model."""

    class Saturated(PointModel):
        def __init__(self, cfg, xyz, spacing):
            super().__init__(cfg, xyz, spacing)
            if self.decoder is not None:
                with torch.no_grad():
                    self.decoder.out.bias.fill_(30.0)

    monkeypatch.setattr(train_mod, "PointModel", Saturated)
    split = _split()
    mcfg = model_config("fast", decoder="unet", decoder_residual=False)
    cfg = TrainConfig(steps=400, patches=1, patch_size=32, eval_every=0.0, eval_views=2, device="cpu", seed=1,
                      threads=1, prune_every=0, clone_every=0, lr_final=0.2, ema=ema)
    model, hist = fit_points(split, split, mcfg, cfg, show_progress=False)
    guard = hist[-1]["guard"]
    assert [e["action"] for e in guard["events"]] == ["restarted the fit without a decoder"]
    assert model.decoder is None and guard["collapsed"] is None
    assert hist[-1]["psnr_object"] > guard["blank_floor"]["psnr_object"] + 8
    if ema:
        assert hist[-1]["raw"]["psnr_object"] > guard["blank_floor"]["psnr_object"] + 8


def test_evaluate_reports_what_the_guard_reads():
    dec, _ = _pair()
    split = _split()
    s = evaluate(dec, split, [0, 1], (1.0, 1.0, 1.0))
    for key in ("coverage", "blank_distance", "object_contrast"):
        assert math.isfinite(s[key]) and 0.0 <= s[key] <= 1.0
    _, plain = _pair()
    with torch.no_grad():
        plain.bg_logit.fill_(80.0)  # every ray takes the background: renders nothing
    s = evaluate(plain, split, [0, 1], (1.0, 1.0, 1.0))
    assert s["coverage"] < 0.3
