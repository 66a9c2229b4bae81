import math

import pytest
import torch

from core.atlas.distortion import distortion_terms, singular_values_2x3, uv_jacobian
from core.atlas.networks import TexCoordNet


def _grad_of_loss(J):
    J = J.clone().requires_grad_(True)
    ls, la = distortion_terms(J)
    (ls + la).backward()
    return ls, la, J.grad


def test_closed_form_matches_svd():
    g = torch.Generator().manual_seed(0)
    J = torch.randn(500, 2, 3, generator=g) * torch.rand(500, 1, 1, generator=g) * 5
    s1, s2, log_area = singular_values_2x3(J)
    ref = torch.linalg.svdvals(J.double())  # brute-force reference
    assert torch.allclose(s1.double(), ref[:, 0], rtol=1e-4, atol=1e-5)
    assert torch.allclose(s2.double(), ref[:, 1], rtol=1e-3, atol=1e-4)
    assert torch.allclose(log_area.double(), torch.log(ref[:, 0] * ref[:, 1]), atol=1e-3)


@pytest.mark.stability
@pytest.mark.parametrize("kind", ["zero", "rank1", "huge", "tiny", "rank1_huge", "equal_rows"])
def test_degenerate_jacobians_give_finite_loss_and_gradient(kind):
    J = {
        "zero": torch.zeros(8, 2, 3),
        "rank1": torch.tensor([[1.0, 2.0, 3.0], [2.0, 4.0, 6.0]]).expand(8, 2, 3),
        "huge": torch.randn(8, 2, 3, generator=torch.Generator().manual_seed(1)) * 1e15,
        "tiny": torch.randn(8, 2, 3, generator=torch.Generator().manual_seed(2)) * 1e-20,
        "rank1_huge": torch.tensor([[1e18, 0.0, 0.0], [1e18, 0.0, 0.0]]).expand(8, 2, 3),
        "equal_rows": torch.tensor([[1.0, 0.0, 0.0], [0.0, 1.0, 0.0]]).expand(8, 2, 3),  # sigma1 == sigma2
    }[kind].float()
    ls, la, grad = _grad_of_loss(J)
    assert torch.isfinite(ls) and torch.isfinite(la)
    assert torch.isfinite(grad).all()
    if kind == "equal_rows":
        assert ls.item() < 1e-10 and la.item() < 1e-10  # an isometry costs nothing


def test_rank1_is_penalised_and_isometry_is_not():
    iso = torch.tensor([[[0.6, 0.8, 0.0], [0.0, 0.0, 1.0]]])
    flat = torch.tensor([[[1.0, 0.0, 0.0], [1.0, 0.0, 0.0]]])
    assert sum(distortion_terms(iso)).item() < 1e-8
    ls, la = distortion_terms(flat)
    assert ls.item() > 0.5 and la.item() > 10  # collapsed area -> large log penalty


def test_weighted_terms_sum_over_charts():
    J = torch.randn(4, 3, 2, 3, generator=torch.Generator().manual_seed(3))
    w = torch.softmax(torch.randn(4, 3, generator=torch.Generator().manual_seed(4)), -1)
    s1, s2, la = singular_values_2x3(J)
    ls, lar = distortion_terms(J, w)
    assert torch.allclose(ls, (w * (s1 - s2) ** 2).sum(1).mean(), atol=1e-6)
    assert torch.allclose(lar, (w * la ** 2).sum(1).mean(), atol=1e-6)


def test_autograd_jacobian_matches_jacrev_and_double_backward_reaches_weights():
    torch.manual_seed(0)
    net = TexCoordNet(3, 32, 2, 2)
    x = torch.randn(16, 3)
    J, uv = uv_jacobian(net, x)
    ref = torch.func.vmap(torch.func.jacrev(lambda p: net(p[None])[0]))(x)  # [16, 3, 2, 3]
    assert J.shape == (16, 3, 2, 3)
    assert torch.allclose(J, ref, atol=1e-5)
    ls, la = distortion_terms(J)
    (ls + la).backward()
    w = net.mlp[0].weight.grad
    assert w is not None and torch.isfinite(w).all() and w.abs().sum() > 0
    assert not math.isnan(ls.item())


@pytest.mark.parametrize("fourier", [0, 1, 4])
def test_forward_mode_jacobian_matches_autograd_and_its_weight_gradients(fourier):
    """TexCoordNet.jacobian (three input directions carried through the network) against the batched
    vector-Jacobian products uv_jacobian uses for any other map: the same J and the same gradient of a loss on J
    with respect to every weight (float64, to rounding)."""
    from core.atlas.networks import TexCoordNet

    torch.manual_seed(fourier)
    net = TexCoordNet(5, 24, 3, fourier).double()
    x = torch.rand(40, 3, dtype=torch.float64) * 2 - 1
    J1, uv1 = net.jacobian(x)
    J2, uv2 = uv_jacobian(lambda z: net(z), x)  # a plain function: the autograd path
    assert J1.shape == (40, 5, 2, 3) and torch.allclose(J1, J2, atol=1e-12) and torch.allclose(uv1, uv2, atol=1e-12)
    params = list(net.parameters())
    g1 = torch.autograd.grad(J1.pow(2).sum() + J1[..., 0, 1].sum(), params, allow_unused=True)
    g2 = torch.autograd.grad(J2.pow(2).sum() + J2[..., 0, 1].sum(), params, allow_unused=True)
    for a, b in zip(g1, g2):
        a = torch.zeros(()) if a is None else a
        b = torch.zeros(()) if b is None else b
        assert torch.allclose(a.double(), b.double(), atol=1e-10)
