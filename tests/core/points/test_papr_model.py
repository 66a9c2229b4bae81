"""PAPR model: attention shapes and invariants, gradients, stability of the attention maths."""
import math

import pytest
import torch

from core.points.model import ModelConfig, PointModel, fourier, mean_spacing


def _model(n=200, seed=0, **kw):
    torch.manual_seed(seed)
    xyz = torch.rand(n, 3) - 0.5
    return PointModel(ModelConfig(k=8, **kw), xyz, mean_spacing(xyz))


def _rays(r=32, seed=1):
    g = torch.Generator().manual_seed(seed)
    o = torch.tensor([0.0, 0.0, 3.0]).expand(r, 3).clone()
    d = torch.nn.functional.normalize(torch.randn(r, 3, generator=g) * 0.1 + torch.tensor([0.0, 0.0, -1.0]), dim=1)
    return o, d


def test_attention_weights_sum_to_one_and_shapes():
    m = _model()
    o, d = _rays()
    idx = torch.randint(0, m.num_points, (32, 8))
    idx[0, 4:] = -1  # a ray with empty slots
    att = m.attend(m.xyz, m.influence, o, d, idx)
    assert att["weights"].shape == (32, 8) and att["bg"].shape == (32,) and att["x"].shape == (32, 3)
    total = att["weights"].sum(1) + att["bg"]
    assert torch.allclose(total, torch.ones(32), atol=1e-5)
    assert float(att["weights"][0, 4:].detach().abs().max()) == 0.0
    # x is a convex combination of the valid neighbours
    lo = m.xyz[idx[1]].min(0).values
    hi = m.xyz[idx[1]].max(0).values
    assert bool(((att["x"][1] >= lo - 1e-5) & (att["x"][1] <= hi + 1e-5)).all())


def test_no_neighbours_gives_background_and_finite_point():
    m = _model()
    o, d = _rays(4)
    idx = torch.full((4, 8), -1)
    att = m.attend(m.xyz, m.influence, o, d, idx)
    assert torch.allclose(att["bg"], torch.ones(4))
    assert torch.isfinite(att["x"]).all()


@pytest.mark.stability
def test_extreme_positions_stay_finite():
    m = _model()
    o, d = _rays(16)
    pts = m.xyz.detach().clone()
    pts[:50] = 1e30                     # sent far away
    pts[50:100] = pts[100:101]          # coincident
    pts[100:] *= 1e-7                   # squashed to a point
    idx = torch.randint(0, m.num_points, (16, 8))
    att = m.attend(pts, m.influence, o, d, idx)
    for key in ("weights", "bg"):
        assert torch.isfinite(att[key]).all(), key
    # huge logits through the influence must not give NaN either
    infl = torch.full((m.num_points,), 1e30)
    att = m.attend(m.xyz, infl, o, d, idx)
    assert torch.isfinite(att["weights"]).all() and torch.isfinite(att["x"]).all()


def test_gradients_reach_points_features_and_attention():
    m = _model()
    o, d = _rays()
    idx = torch.randint(0, m.num_points, (32, 8))
    att = m.attend(m.xyz, m.influence, o, d, idx)
    sh = m.shade(att, d, idx, torch.ones(3))
    (sh["rgb"].sum() + att["x"].sum()).backward()
    for name in ("xyz", "features", "influence", "bg_logit"):
        g = getattr(m, name).grad
        assert g is not None and torch.isfinite(g).all() and float(g.abs().sum()) > 0, name
    key_grads = [p.grad for p in m.key_mlp.parameters()]
    assert all(g is not None and float(g.abs().sum()) > 0 for g in key_grads)


def test_unet_decoder_any_size():
    m = _model(decoder="unet", decoder_residual=False)
    feat = torch.randn(2, m.cfg.feature_dim, 17, 23)
    out = m.decode(feat)
    assert out.shape == (2, 3, 17, 23) and bool(((out >= 0) & (out <= 1)).all())
    r = _model(decoder="unet")  # residual: base colour and coverage before the features
    feat = torch.randn(2, 4 + r.cfg.feature_dim, 17, 23)
    assert r.decode(feat).shape == (2, 3, 17, 23)


def test_fourier_shape():
    x = torch.randn(5, 2)
    assert fourier(x, 3).shape == (5, 2 * 7)
    assert math.isclose(float(fourier(torch.zeros(1, 1), 2)[0, 3]), 1.0)  # cos(0)


def test_unet_mask_head_and_older_files_without_it():
    """The UNet's 4th channel is the foreground alpha; files written before the mask head (no `decoder_alpha` in
    the header, 3-channel UNet) still load, with no alpha."""
    from core.points.checkpoint import model_from_arrays, model_to_arrays

    m = _model(decoder="unet")
    feat = torch.randn(1, 4 + m.cfg.feature_dim, 9, 8)
    rgb, alpha = m.decode_with_alpha(feat)
    assert rgb.shape == (1, 3, 9, 8) and alpha.shape == (1, 9, 8)
    assert torch.equal(rgb, m.decode(feat)) and bool(((alpha >= 0) & (alpha <= 1)).all())
    arrays, meta = model_to_arrays(m)
    back = model_from_arrays(arrays, meta)
    assert back.cfg.decoder_alpha and torch.equal(back.decode_with_alpha(feat)[1], alpha)
    old = _model(decoder="unet", decoder_alpha=False, decoder_residual=False)
    feat = torch.randn(1, m.cfg.feature_dim, 9, 8)
    arrays, meta = model_to_arrays(old)
    del meta["model"]["decoder_alpha"]  # as an older file's header
    del meta["model"]["decoder_residual"]
    back = model_from_arrays(arrays, meta)
    assert not back.cfg.decoder_alpha and back.decode_with_alpha(feat)[1] is None
    assert torch.equal(back.decode(feat), old.decode(feat))


def test_unet_decoder_width_and_files_without_it():
    """`decoder_width` sets the UNet's channels; files written before the setting load with the 32 they had."""
    from core.points.checkpoint import model_from_arrays, model_to_arrays

    narrow = _model(decoder="unet", decoder_width=8)
    assert narrow.decoder.enc1[0].out_channels == 8 and narrow.decoder.enc2[0].out_channels == 16
    wide = _model(decoder="unet")
    assert wide.decoder.enc1[0].out_channels == 32
    assert sum(p.numel() for p in narrow.decoder.parameters()) < sum(p.numel() for p in wide.decoder.parameters())
    with torch.no_grad():
        for p in narrow.decoder.parameters():
            p.normal_(0.0, 0.3)
    feat = torch.randn(1, 4 + narrow.cfg.feature_dim, 9, 8)
    back = model_from_arrays(*model_to_arrays(narrow))
    assert back.cfg.decoder_width == 8 and torch.equal(back.decode(feat), narrow.decode(feat))
    arrays, meta = model_to_arrays(wide)
    del meta["model"]["decoder_width"]  # as an older file's header
    assert model_from_arrays(arrays, meta).cfg.decoder_width == 32
