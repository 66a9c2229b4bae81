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


def _attention_case(seed, inv_f: bool, n=300, r=500, k=8, far=False):
    m = _model(seed=seed)
    g = torch.Generator().manual_seed(seed + 100)
    with torch.no_grad():
        m.influence.normal_(0.0, 1.0, generator=g)
        m.bg_logit.fill_(0.3)
    pts = m.xyz.detach() * (40.0 if far else 1.0)  # far: features beyond the ±64 spacing clamp
    o = torch.tensor([0.1, -0.2, 3.0]) + 0.05 * torch.randn(r, 3, generator=g)
    d = torch.nn.functional.normalize(torch.randn(r, 3, generator=g) * 0.15 + torch.tensor([0.0, 0.0, -1.0]), dim=1)
    idx = torch.randint(0, n, (r, k), generator=g)
    idx[:50, 3:] = -1
    idx[50:60] = -1  # rays with no neighbour
    fi = None
    if inv_f:
        a = torch.eye(3) + 0.4 * torch.randn(n, 3, 3, generator=g)
        fi = torch.linalg.inv(a)
    return m, pts, o, d, idx, fi


@pytest.mark.parametrize("inv_f,rebase", [(False, False), (True, False), (True, True)])
@pytest.mark.parametrize("seed,far,temperature", [(0, False, None), (1, True, None), (2, False, 0.5)])
def test_compiled_attention_equals_attend(inv_f, rebase, seed, far, temperature):
    from core.points import attention_compiled

    if not attention_compiled.available():
        pytest.skip("numba is not installed")
    m, pts, o, d, idx, fi = _attention_case(seed, inv_f, far=far)
    with torch.no_grad():
        ref = m.attend(pts, m.influence, o, d, idx, temperature=temperature, inv_f=fi, rebase_depth=rebase)
    got = attention_compiled.attend_compiled(m, pts, m.influence, o, d, idx, temperature=temperature, inv_f=fi,
                                             rebase_depth=rebase)
    for key in ("weights", "fg_weights", "bg"):
        assert float((got[key] - ref[key]).abs().max()) <= 1e-5, key
    scale = float(pts.abs().max())
    assert float((got["x"] - ref["x"]).abs().max()) <= 1e-5 * max(scale, 1.0)
    assert float(ref["weights"][:50, 3:].abs().max()) == 0.0 == float(got["weights"][:50, 3:].abs().max())


def test_compiled_attention_frames_equal_torch_frames():
    """Whole frames (deformed, painted, with the decoder) by trace_frame's compiled attention equal the torch
    path's (≤ 1e-5), and the torch path is what `attention='torch'` runs."""
    from core.frames.edited import EditConfig, EditState, render_edited
    from core.points import attention_compiled
    from tests.helpers.tiny import tiny_bundle

    if not attention_compiled.available():
        pytest.skip("numba is not installed")
    bundle = tiny_bundle("fast", decoder="unet")[0]
    xyz = bundle.model.xyz.detach()
    bent = xyz + 0.05 * torch.sin(3 * xyz.flip(1))
    painted = bundle.atlas.packed_image().clone()
    painted[::3] = 1.0 - painted[::3]
    from core.images.cameras import focal_from_fov, look_at

    c2w = look_at((1.2, -2.0, 1.5)).float()
    focal = focal_from_fov(48, 0.69)
    outs = {}
    for mode in ("torch", "compiled"):
        st = EditState(bundle, points=bent, atlas=painted, cfg=EditConfig(attention=mode))
        outs[mode] = render_edited(st, c2w, 48, 48, focal)
    assert outs["torch"]["stats"]["texture_rays"] > 100
    for key in ("rgb", "alpha"):
        assert float((outs["torch"][key] - outs["compiled"][key]).abs().max()) <= 1e-5, key


@pytest.mark.parametrize("attention", ["torch", "compiled"])
def test_rebased_depth_sees_the_canonical_geometry_of_an_affine_map(attention):
    """Points moved by one affine map A (a squash to 5 % across a rotated axis, plus a shear and a shift): with
    inv_f = A⁻¹ and rebase_depth, the attention of a deformed ray equals the canonical model's attention of the
    canonical ray (A⁻¹ o, A⁻¹ d normalised) over the same neighbours — depths from the nearest neighbour along the
    canonical ray, as the keys were trained. Without the rebase the depths are taken from the deformed ray's
    nearest neighbour, which A reorders, and the weights differ."""
    from core.points import attention_compiled

    if attention == "compiled" and not attention_compiled.available():
        pytest.skip("numba is not installed")
    m = _model(seed=5)
    with torch.no_grad():
        m.influence.normal_(0.0, 0.5, generator=torch.Generator().manual_seed(1))
    can = m.xyz.detach().double()
    rot = torch.linalg.qr(torch.randn(3, 3, generator=torch.Generator().manual_seed(2), dtype=torch.float64))[0]
    a = rot @ torch.diag(torch.tensor([1.0, 1.0, 0.05], dtype=torch.float64)) @ rot.T
    a = a + 0.3 * torch.tensor([[0, 1.0, 0], [0, 0, 0], [0, 0, 0]], dtype=torch.float64)
    shift = torch.tensor([0.2, -0.1, 0.3], dtype=torch.float64)
    pts = (can @ a.T + shift).float()
    g = torch.Generator().manual_seed(3)
    r, k = 400, 8
    o = (torch.tensor([0.0, 0.0, 3.0]) + 0.1 * torch.randn(r, 3, generator=g)).double()
    d = torch.nn.functional.normalize(torch.randn(r, 3, generator=g) * 0.3 + torch.tensor([0.0, 0.0, -1.0]),
                                      dim=1).double()
    idx = torch.randint(0, can.shape[0], (r, k), generator=g)
    idx[:40, 4:] = -1
    ai = torch.linalg.inv(a)
    o_c = ((o - shift) @ ai.T).float()
    d_c = torch.nn.functional.normalize(d @ ai.T, dim=1).float()
    fi = ai.float().expand(can.shape[0], 3, 3).contiguous()

    def run(points, oo, dd, inv_f, rebase):
        if attention == "compiled":
            return attention_compiled.attend_compiled(m, points, m.influence, oo, dd, idx, inv_f=inv_f,
                                                      rebase_depth=rebase)
        with torch.no_grad():
            return m.attend(points, m.influence, oo, dd, idx, inv_f=inv_f, rebase_depth=rebase)

    ref = run(can.float(), o_c, d_c, None, False)
    got = run(pts, o.float(), d.float(), fi, True)
    old = run(pts, o.float(), d.float(), fi, False)
    assert float((got["weights"] - ref["weights"]).abs().max()) <= 1e-4
    assert float((got["bg"] - ref["bg"]).abs().max()) <= 1e-4
    assert float((old["weights"] - ref["weights"]).abs().max()) > 1e-2
    # identity maps: the rebase changes nothing (the smallest depth is already the nearest neighbour's, 0)
    eye = torch.eye(3).expand(can.shape[0], 3, 3).contiguous()
    plain = run(pts, o.float(), d.float(), None, False)
    same = run(pts, o.float(), d.float(), eye, True)
    assert float((same["weights"] - plain["weights"]).abs().max()) <= 1e-5


def test_rebased_depth_is_finite_for_extreme_points_and_gradients():
    """rebase_depth with points sent to ±1e30 (a broken rig) and inverse gradients at the clamp's ends (20× and
    1/20 per axis, a mirror): finite weights and background in both paths (their float32 rounding differs at such
    scales, with or without the rebase, so only finiteness is compared here)."""
    from core.points import attention_compiled

    m, pts, o, d, idx, _ = _attention_case(7, False)
    pts = pts.clone()
    pts[::11] = 1e30
    pts[5::13] = -1e30
    n = pts.shape[0]
    scales = torch.tensor([[20.0, 1.0, 0.05], [-20.0, 20.0, 20.0], [0.05, 0.05, -0.05]])
    fi = torch.diag_embed(scales[torch.arange(n) % 3])
    with torch.no_grad():
        ref = m.attend(pts, m.influence, o, d, idx, inv_f=fi, rebase_depth=True)
    for key in ("weights", "fg_weights", "bg"):
        assert torch.isfinite(ref[key]).all(), key
    if attention_compiled.available():
        got = attention_compiled.attend_compiled(m, pts, m.influence, o, d, idx, inv_f=fi, rebase_depth=True)
        for key in ("weights", "fg_weights", "bg"):
            assert torch.isfinite(got[key]).all(), key
