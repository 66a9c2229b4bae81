"""Fast render paths against their plain-torch references (≤ 1e-5): the per-point value table blended by
embedding_bag in PointModel.shade (values and gradients); the decoder run on the active rays' box only."""
import pytest
import torch

from core.points.model import TRAIN_BACKGROUND, ModelConfig, PointModel, mean_spacing


def _model(seed=0, **kw):
    torch.manual_seed(seed)
    xyz = torch.rand(300, 3) - 0.5
    m = PointModel(ModelConfig(k=8, feature_dim=8, **kw), xyz, mean_spacing(xyz))
    if m.bg_value is not None:
        with torch.no_grad():
            m.bg_value.normal_()
    return m


def _shade_reference(m, att, dirs, idx, background, features=None):
    """The gather form: values per neighbour slot [R, K, C], weighted and summed."""
    v = m.point_values(dirs, idx, features)
    fv = (att["weights"][..., None] * v).sum(1)
    bg = att["bg"][:, None]
    if m.decoder is None:
        return fv + bg * background
    if m.cfg.decoder_residual:
        white = torch.tensor(TRAIN_BACKGROUND)
        return torch.cat([fv[:, :3] + bg * white, 1.0 - bg, fv[:, 3:] + bg * m.bg_value], dim=1)
    return fv + bg * m.bg_value


@pytest.mark.parametrize("kw", [dict(), dict(decoder="unet"), dict(decoder="unet", decoder_residual=False)])
@pytest.mark.parametrize("own_features", [False, True])
def test_shade_table_equals_the_gather_form(kw, own_features):
    m = _model(**kw)
    g = torch.Generator().manual_seed(3)
    r = 200
    idx = torch.randint(0, m.num_points, (r, 8), generator=g)
    idx[:20, 5:] = -1
    idx[20:30] = -1  # rays with no neighbour at all
    feats = torch.randn(m.num_points, 8, generator=g) if own_features else None
    logits = torch.randn(r, 9, generator=g).masked_fill(torch.cat([idx < 0, torch.zeros(r, 1, dtype=torch.bool)], 1),
                                                        float("-inf"))
    a = torch.softmax(logits, 1).requires_grad_(True)
    att = {"weights": a[:, :-1], "bg": a[:, -1]}
    dirs = torch.nn.functional.normalize(torch.randn(r, 3, generator=g), dim=1)
    bgc = torch.tensor([0.2, 0.4, 0.6])
    out = m.shade(att, dirs, idx, bgc, features=feats)
    got = out["rgb"] if m.decoder is None else out["feature"]
    ref = _shade_reference(m, att, dirs, idx, bgc, feats)
    assert float((got - ref).detach().abs().max()) <= 1e-5
    # the same gradients for training: attention weights and value network
    wts = torch.randn_like(ref)
    params = [a] + list(m.value_mlp.parameters())
    g_got = torch.autograd.grad((got * wts).sum(), params)
    g_ref = torch.autograd.grad((ref * wts).sum(), params)
    for x, y in zip(g_got, g_ref):
        assert float((x - y).abs().max()) <= 1e-5


@pytest.mark.parametrize("residual", [True, False])
@pytest.mark.parametrize("hw,box", [((96, 80), (30, 50, 20, 45)), ((97, 83), (41, 60, 3, 30)),
                                    ((90, 91), (0, 20, 70, 91)), ((64, 64), (10, 11, 60, 61))])
@torch.no_grad()
def test_decoder_on_the_active_box_equals_the_whole_frame(residual, hw, box):
    """decode_where_active (decoder on the active rays' box, cached background frame elsewhere) gives the whole
    frame's decoder output, with random (non-zero) weights so every layer matters, odd sizes, boxes at the border."""
    from core.points.render import decode_where_active

    m = _model(decoder="unet", decoder_residual=residual)
    g = torch.Generator().manual_seed(7)
    with torch.no_grad():
        for p in m.decoder.parameters():  # unit-scale activations: outputs O(1), like a trained decoder's
            std = 1.5 / p[0].numel() ** 0.5 if p.dim() > 1 else 0.1
            p.copy_(std * torch.randn(p.shape, generator=g))
    h, w = hw
    c = m.decoder.enc1[0].in_channels
    bg = torch.rand(c, generator=g)
    if residual:
        bg[3] = 0.0  # the coverage of a ray that saw no point
    feat = bg.view(1, c, 1, 1).expand(1, c, h, w).clone()
    active = torch.zeros(h, w, dtype=torch.bool)
    r0, r1, c0, c1 = box
    active[r0:r1, c0:c1] = torch.rand(r1 - r0, c1 - c0, generator=g) > 0.2
    feat[0][:, active] = torch.rand(c, int(active.sum()), generator=g)
    ref_rgb, ref_a = m.decode_with_alpha(feat)
    assert 0.05 < float(ref_rgb.std()) and float(ref_rgb.abs().max()) < 20
    for _ in range(2):  # the second call uses the cached background frame
        rgb, a = decode_where_active(m, feat, active)
        assert float((rgb - ref_rgb).abs().max()) <= 1e-5
        assert float((a - ref_a).abs().max()) <= 1e-5
    with torch.no_grad():  # new weights: the cache is not reused
        m.decoder.out.bias.add_(0.5)
    rgb, _ = decode_where_active(m, feat, active)
    assert float((rgb - m.decode_with_alpha(feat)[0]).abs().max()) <= 1e-5
