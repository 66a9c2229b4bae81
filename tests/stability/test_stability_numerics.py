"""Float precision and stiff cases of the atlas distortion loss beyond the plain-J cases of
tests/core/atlas/test_distortion.py: half-precision Jacobians (the reference ran this under fp16 autocast),
Jacobians taken through the real texture-coordinate network at degenerate sample sets, with finite losses and
finite gradients reaching the network weights (double backward), and degenerate chart weights."""
import pytest
import torch

from core.atlas.distortion import distortion_terms, uv_jacobian
from core.atlas.networks import TexCoordNet

pytestmark = pytest.mark.stability


# float16 Jacobians: the distortion guards (1e-12, 1e-8) would underflow to 0 in half precision; the module
# computes in float32 (the gradient flows back to the half input), so zero, rank-1 and huge Jacobians stay finite.
LOW_PRECISION = [(torch.bfloat16, k) for k in ("random", "zero", "rank1", "huge", "denormal")] + [
    (torch.float16, "random"), (torch.float16, "denormal"),
    (torch.float16, "zero"), (torch.float16, "rank1"), (torch.float16, "huge")]


@pytest.mark.parametrize("dtype,kind", LOW_PRECISION)
def test_low_precision_jacobians_give_finite_loss_and_gradient(dtype, kind):
    g = torch.Generator().manual_seed(0)
    J = {"random": torch.randn(16, 2, 3, generator=g),
         "zero": torch.zeros(16, 2, 3),
         "rank1": torch.tensor([[1.0, 2.0, 3.0], [-2.0, -4.0, -6.0]]).expand(16, 2, 3),
         "huge": torch.randn(16, 2, 3, generator=g).clamp(-2, 2) * 3e4,  # up to 6e4, near the float16 maximum
         "denormal": torch.randn(16, 2, 3, generator=g) * 1e-6}[kind].to(dtype).requires_grad_(True)
    assert bool(torch.isfinite(J).all())
    ls, la = distortion_terms(J)
    (ls + la).backward()
    assert torch.isfinite(ls) and torch.isfinite(la)
    assert bool(torch.isfinite(J.grad).all())


def _net(seed=0):
    torch.manual_seed(seed)
    return TexCoordNet(4, 32, 2, 1)


SAMPLES = {
    "coincident": lambda: torch.full((16, 3), 0.3),
    "origin": lambda: torch.zeros(16, 3),
    "collinear": lambda: torch.linspace(-1, 1, 16)[:, None] * torch.tensor([1.0, 2.0, -1.0]),
    "huge_coordinates": lambda: torch.randn(16, 3, generator=torch.Generator().manual_seed(1)) * 1e6,
    "denormal_coordinates": lambda: torch.randn(16, 3, generator=torch.Generator().manual_seed(2)) * 1e-39,
}


@pytest.mark.parametrize("name", list(SAMPLES))
@pytest.mark.parametrize("weighting", ["prob", "uniform"])
def test_distortion_through_the_network_has_finite_weight_gradients(name, weighting):
    net = _net()
    x = SAMPLES[name]()
    J, uv = uv_jacobian(net, x)
    w = torch.softmax(torch.randn(len(x), 4, generator=torch.Generator().manual_seed(3)), -1) \
        if weighting == "prob" else None
    ls, la = distortion_terms(J * 7.0, w)
    (ls + la).backward()  # second-order: the loss is a function of the Jacobian
    assert torch.isfinite(ls) and torch.isfinite(la) and bool(torch.isfinite(uv).all())
    # biases change J only through the ReLUs' on/off pattern (a zero derivative): the weights carry the loss
    grads = [p.grad for p in net.parameters() if p.grad is not None]
    assert len(grads) >= 3 and all(bool(torch.isfinite(gr).all()) for gr in grads)
    assert any(float(gr.abs().max()) > 0 for gr in grads)  # the loss does reach the weights


def test_network_with_zero_weights_gives_zero_jacobian_and_finite_gradients():
    """A chart map that is constant (all weights zero): J = 0 everywhere, the worst case of the area term."""
    net = _net()
    with torch.no_grad():
        for p in net.parameters():
            p.zero_()
    J, _ = uv_jacobian(net, torch.randn(8, 3))
    assert float(J.detach().abs().max()) == 0.0
    ls, la = distortion_terms(J)
    (ls + la).backward()
    assert torch.isfinite(ls) and torch.isfinite(la)
    assert all(bool(torch.isfinite(p.grad).all()) for p in net.parameters() if p.grad is not None)


@pytest.mark.parametrize("weights", ["one_hot", "all_zero", "tiny"])
def test_degenerate_chart_weights(weights):
    J = torch.randn(8, 4, 2, 3, generator=torch.Generator().manual_seed(4)).requires_grad_(True)
    w = {"one_hot": torch.eye(4)[torch.arange(8) % 4], "all_zero": torch.zeros(8, 4),
         "tiny": torch.full((8, 4), 1e-38)}[weights]
    ls, la = distortion_terms(J, w)
    (ls + la).backward()
    assert torch.isfinite(ls) and torch.isfinite(la) and bool(torch.isfinite(J.grad).all())


def test_sample_lookups_at_extreme_points_and_degenerate_samples():
    """Lookups through the stored samples (core/atlas/sample_lookup.py): no points, NaN and infinite points, points
    1e6 away, a k larger than the samples, and samples stacked on one spot (every distance 0) give finite weights
    that sum to 1 and finite colours (NaN rows exactly for the non-finite points); the fitted bake of a constant
    colour over duplicated samples stays finite and in range."""
    import copy

    from core.atlas.packing import unpack
    from core.atlas.sample_lookup import SampleLookup, fit_texels
    from tests.helpers.tiny import tiny_bundle

    atlas = copy.deepcopy(tiny_bundle("fast")[0].atlas)
    lk = SampleLookup(atlas)
    reads = lk.read(unpack(atlas.packed_image(), atlas.layout))
    S = lk.samples
    assert lk.lookup(reads, torch.zeros(0, 3), 4).shape == (0, 3)
    pts = torch.cat([torch.tensor([[float("nan"), 0, 0], [float("inf"), 0, 0], [1e6, -1e6, 1e6]]), S[:3]])
    out = lk.lookup(reads, pts, 4)
    assert torch.isnan(out[:2]).all() and torch.isfinite(out[2:]).all()
    _, w = lk.neighbours(pts[2:], 10 * len(S))
    assert torch.isfinite(w).all() and torch.allclose(w.sum(1), torch.ones(len(w), dtype=w.dtype))
    atlas.bake_samples = S[:1].expand(50, 3).clone()  # one spot, fifty times
    stacked = SampleLookup(atlas)
    j, w = stacked.neighbours(S[:2], 8)
    assert torch.isfinite(w).all() and torch.allclose(w.sum(1), torch.ones(2, dtype=w.dtype))
    img = fit_texels(atlas, atlas.packed_image(), torch.full((50, 3), 0.25))
    assert torch.isfinite(img).all() and img.min() >= 0 and img.max() <= 1
