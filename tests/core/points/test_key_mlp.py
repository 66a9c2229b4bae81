"""The chunked key MLP of training (core/points/key_mlp.py) against autograd through the module: logits, and the
gradients of the key features, the MLP's weights and a whole training step's parameters, to 1e-5 relative."""
import pytest
import torch

from core.points.key_mlp import key_logits, standard_key_mlp
from core.points.model import ModelConfig, PointModel, _mlp, fourier, mean_spacing
from core.points.train import TrainConfig, fit_points
from core.util.errors import InputError
from tests.helpers.synthetic import fibonacci_cameras, render_split
from tests.helpers.tiny import model_config

RTOL = 1e-5  # relative to the largest entry of each tensor: float32 sums over the slots in another order


def _close(a: torch.Tensor, b: torch.Tensor, what: str) -> None:
    scale = max(float(b.abs().max()), 1e-12)
    err = float((a - b).abs().max()) / scale
    assert err <= RTOL, f"{what}: relative error {err:.2e}"


def _reference(seq, feats, freqs, g):
    f = feats.clone().requires_grad_()
    seq.zero_grad()
    y = seq(fourier(f, freqs)).squeeze(-1)
    y.backward(g)
    return y.detach(), f.grad, [p.grad.clone() for p in seq.parameters()]


def _chunked(seq, feats, freqs, g, valid, chunk):
    f = feats.clone().requires_grad_()
    seq.zero_grad()
    y = key_logits(seq, f, freqs, valid, chunk)
    y.backward(g)
    return y.detach(), f.grad, [p.grad.clone() for p in seq.parameters()]


@pytest.mark.parametrize("freqs,chunk,empty", [(4, 4096, 0.3), (4, 7, 0.0), (2, 1, 0.5), (0, 64, 0.2),
                                               (4, 64, 1.0)])
def test_key_logits_equal_autograd_through_the_module(freqs, chunk, empty):
    torch.manual_seed(freqs + chunk)
    seq = _mlp(2 * (1 + 2 * freqs), 32, 1)
    r, k = 50, 12
    # key features over their clamped range (distances 0..64, depths ±64 spacings), a few at the clamps
    feats = torch.stack([torch.rand(r, k) * 64.0, (torch.rand(r, k) - 0.5) * 128.0], dim=-1)
    feats[0, :3] = torch.tensor([64.0, -64.0])
    feats[1, :3] = 0.0
    valid = torch.rand(r, k) >= empty
    g = torch.randn(r, k) * valid  # the caller's softmax gives empty slots no gradient
    y0, gf0, gp0 = _reference(seq, feats, freqs, g)
    y1, gf1, gp1 = _chunked(seq, feats, freqs, g, valid, chunk)
    if bool(valid.any()):
        _close(y1[valid], y0[valid], "logits")
        _close(gf1, gf0, "feature gradient")
        for name, a, b in zip(("w1", "b1", "w2", "b2", "w3", "b3"), gp1, gp0):
            _close(a, b, name)
    assert bool((y1[~valid] == 0).all())  # empty slots: logit 0, no gradient
    assert bool((gf1[~valid] == 0).all())
    # without a mask every slot is evaluated and gets its gradient
    g = torch.randn(r, k)
    y0, gf0, gp0 = _reference(seq, feats, freqs, g)
    y2, gf2, gp2 = _chunked(seq, feats, freqs, g, None, chunk)
    _close(y2, y0, "logits without mask")
    _close(gf2, gf0, "feature gradient without mask")
    for name, a, b in zip(("w1", "b1", "w2", "b2", "w3", "b3"), gp2, gp0):
        _close(a, b, name + " without mask")


def _attend_pair(m, pts, o, d, idx, **kw):
    outs = []
    for keys in ("torch", "chunked"):
        m.zero_grad()
        p = pts.clone().requires_grad_()
        infl = m.influence.detach().clone().requires_grad_()
        att = m.attend(p, infl, o, d, idx, keys=keys, **kw)
        sh = m.shade(att, d, idx, torch.ones(3))
        loss = (sh["rgb"] ** 2).sum() + att["x"].square().sum() + 0.1 * att["bg"].sum()
        loss.backward()
        grads = {"points": p.grad, "influence": infl.grad, "bg_logit": m.bg_logit.grad.clone(),
                 **{f"key_mlp.{n}": q.grad.clone() for n, q in m.key_mlp.named_parameters()},
                 **{f"value_mlp.{n}": q.grad.clone() for n, q in m.value_mlp.named_parameters()}}
        outs.append(({k: v.detach() for k, v in att.items() if torch.is_tensor(v)}, grads))
    return outs


@pytest.mark.parametrize("deformed", [False, True])
def test_attend_chunked_keys_equal_torch_keys(deformed):
    torch.manual_seed(3)
    xyz = torch.rand(300, 3) - 0.5
    m = PointModel(ModelConfig(k=8), xyz, mean_spacing(xyz))
    with torch.no_grad():
        m.influence.normal_()
    g = torch.Generator().manual_seed(4)
    r = 64
    o = torch.tensor([0.0, 0.0, 3.0]).expand(r, 3).clone()
    d = torch.nn.functional.normalize(torch.randn(r, 3, generator=g) * 0.1 + torch.tensor([0.0, 0.0, -1.0]), dim=1)
    idx = torch.randint(0, 300, (r, 8), generator=g)
    idx[0] = -1          # a ray without neighbours
    idx[1, 3:] = -1      # rays with empty slots
    idx[5, ::2] = -1
    kw = {}
    if deformed:
        kw["inv_f"] = torch.eye(3) + 0.2 * torch.randn(300, 3, 3, generator=g)
        kw["log_window"] = -torch.rand(r, 8, generator=g)
    (att0, g0), (att1, g1) = _attend_pair(m, xyz, o, d, idx, **kw)
    for key in ("weights", "fg_weights", "bg", "x"):
        _close(att1[key], att0[key], key)
    for name in g0:
        _close(g1[name], g0[name], name)


def test_attend_keys_choice_is_checked():
    torch.manual_seed(0)
    xyz = torch.rand(50, 3)
    m = PointModel(ModelConfig(k=4), xyz, mean_spacing(xyz))
    o, d = torch.zeros(2, 3), torch.tensor([[0.0, 0.0, 1.0]] * 2)
    idx = torch.zeros(2, 4, dtype=torch.long)
    with pytest.raises(InputError, match="keys"):
        m.attend(m.xyz, m.influence, o, d, idx, keys="fast")
    assert standard_key_mlp(m.key_mlp)
    m.key_mlp = torch.nn.Sequential(torch.nn.Linear(18, 1))
    assert not standard_key_mlp(m.key_mlp)
    with pytest.raises(InputError, match="standard key MLP"):
        m.attend(m.xyz, m.influence, o, d, idx, keys="chunked")
    assert m.attend(m.xyz, m.influence, o, d, idx)["weights"].shape == (2, 4)  # auto falls back to torch


def test_training_steps_equal_and_both_converge():
    """A whole stage-1 fit (UNet decoder, regularizers, dropout, densification) with either key path: the first
    steps' points and weights agree to float rounding, and both fits reach the same quality."""
    cams = fibonacci_cameras(6, seed=3)
    train = test = render_split("sphere", cams, 32)
    mcfg = model_config("card", num_points=500, decoder="unet")
    base = dict(patches=2, patch_size=16, eval_every=1e9, eval_views=2, device="cpu", seed=0, threads=1,
                prune_every=20, clone_every=30, reg_start=0.0, max_points=600)
    short = {}
    for keys in ("torch", "chunked"):
        model, _ = fit_points(train, test, mcfg, TrainConfig(steps=3, key_path=keys, **base), show_progress=False)
        short[keys] = model
    for name, p in short["torch"].named_parameters():
        p, q = p.detach(), dict(short["chunked"].named_parameters())[name].detach()
        assert p.shape == q.shape
        err = float((p - q).abs().max()) / max(float(p.abs().max()), 1e-12)
        assert err <= 1e-4, f"{name} after 3 steps: {err:.2e}"  # Adam's first steps amplify rounding a little
    # convergence: the two-view overfit of tests/core/points/test_train.py, with either key path
    cams = fibonacci_cameras(2, seed=3)
    two = render_split("sphere", cams, 32)
    final = {}
    for keys in ("torch", "chunked"):
        cfg = TrainConfig(steps=200, patches=1, patch_size=32, eval_every=1e9, eval_views=2, device="cpu", seed=0,
                          threads=1, prune_every=0, clone_every=0, lr_final=0.2, key_path=keys)
        _, hist = fit_points(two, two, model_config("card", num_points=600), cfg, show_progress=False)
        final[keys] = hist
    for keys, hist in final.items():
        assert hist[-1]["psnr"] > 22.0 and hist[-1]["psnr"] > hist[0]["psnr"] + 8.0, (keys, hist[0], hist[-1])
    assert abs(final["chunked"][-1]["psnr"] - final["torch"][-1]["psnr"]) < 1.0


@pytest.mark.stability
def test_chunked_keys_finite_on_extreme_points():
    """Points sent far away, coincident or squashed together, and huge influences: finite attention and
    finite gradients through the chunked key MLP, as through the module."""
    torch.manual_seed(1)
    xyz = torch.rand(200, 3) - 0.5
    m = PointModel(ModelConfig(k=8), xyz, mean_spacing(xyz))
    pts = xyz.clone()
    pts[:50] = 1e30
    pts[50:100] = pts[100:101]
    pts[100:] *= 1e-7
    g = torch.Generator().manual_seed(2)
    o = torch.tensor([0.0, 0.0, 3.0]).expand(16, 3).clone()
    d = torch.nn.functional.normalize(torch.randn(16, 3, generator=g) * 0.1 + torch.tensor([0.0, 0.0, -1.0]), dim=1)
    idx = torch.randint(0, 200, (16, 8), generator=g)
    for infl in (m.influence.detach(), torch.full((200,), 1e30)):
        p = pts.clone().requires_grad_()
        att = m.attend(p, infl, o, d, idx, keys="chunked")
        (att["weights"].sum() + att["bg"].sum()).backward()
        assert torch.isfinite(att["weights"]).all() and torch.isfinite(att["bg"]).all()
        assert all(torch.isfinite(q.grad).all() for q in m.key_mlp.parameters())
        m.zero_grad()

