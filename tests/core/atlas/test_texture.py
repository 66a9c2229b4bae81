"""Kernel-regression textures: the splat is the adjoint of the bilinear lookup, the blur matches a dense reference,
spacing estimates, noise averaging, and finite results for degenerate samples."""
import math

import torch
import torch.nn.functional as F

from core.atlas.packing import sample_charts
from core.atlas.texture import filled_kernel_texture, gaussian_blur, kernel_texture, splat, texel_spacing


def _samples(S=500, n=3, seed=0):
    g = torch.Generator().manual_seed(seed)
    probs = torch.softmax(3 * torch.randn(S, n, generator=g), -1)
    uv = torch.rand(S, n, 2, generator=g) * 1.2 - 0.1  # some outside [0, 1]: clamp to edge like the lookup
    rgb = torch.rand(S, 3, generator=g)
    return probs, uv, rgb


def test_splat_is_the_adjoint_of_the_bilinear_lookup():
    probs, uv, rgb = _samples()
    R = 7
    csum, wsum = splat(probs, uv, rgb, R, min_prob=0.0)
    T = torch.rand(3, 3, R, R, dtype=torch.float64)
    # <splat weights, T> == sum_s sum_c P_sc * bilinear(T_c, uv_sc), per channel and with colours.
    look = sample_charts(T, uv.double())  # [S, n, 3]
    lhs_w = (wsum.double()[:, None] * T).sum((0, 2, 3))
    rhs_w = (probs.double()[..., None] * look).sum((0, 1))
    assert torch.allclose(lhs_w, rhs_w, atol=1e-4)
    lhs_c = (csum.double() * T).sum((0, 2, 3))
    rhs_c = (probs.double()[..., None] * rgb.double()[:, None] * look).sum((0, 1))
    assert torch.allclose(lhs_c, rhs_c, atol=1e-4)


def test_splat_drops_low_probability_charts():
    probs, uv, rgb = _samples()
    _, w0 = splat(probs, uv, rgb, 5, min_prob=0.0)
    _, w1 = splat(probs, uv, rgb, 5, min_prob=0.3)
    kept = (probs * (probs > 0.3)).sum(0)
    assert torch.allclose(w1.sum((1, 2)), kept, atol=1e-4) and (w1 <= w0 + 1e-6).all()


def test_gaussian_blur_matches_a_dense_convolution():
    img = torch.rand(2, 3, 20, 17)
    s = 1.7
    r = math.ceil(3 * s)
    x = torch.arange(-r, r + 1, dtype=torch.float32)
    k2 = torch.exp(-0.5 * (x[:, None] ** 2 + x[None] ** 2) / s**2)
    k2 = k2 / k2.sum()
    ref = F.conv2d(img.reshape(6, 1, 20, 17), k2[None, None], padding=r).view(2, 3, 20, 17)
    assert torch.allclose(gaussian_blur(img, s), ref, atol=1e-5)
    assert torch.equal(gaussian_blur(img, 0.0), img)


def test_texel_spacing_of_a_regular_grid():
    h = 2.5
    g = torch.stack(torch.meshgrid(torch.arange(60.0), torch.arange(60.0), indexing="ij"), -1).reshape(-1, 2) * h
    assert abs(texel_spacing(g) / h - 1) < 0.15
    assert abs(texel_spacing(g, max_points=900) / h - 1) < 0.2  # subset corrected for its lower density
    assert texel_spacing(torch.zeros(3, 2)) == 1.0


def test_kernel_texture_reproduces_a_constant_and_averages_noise():
    g = torch.Generator().manual_seed(1)
    S, R = 20000, 32
    uv = torch.rand(S, 1, 2, generator=g) * 0.8 + 0.1
    probs = torch.ones(S, 1)
    const = torch.tensor([0.2, 0.5, 0.7])
    tex, cov, _ = kernel_texture(probs, uv, const.expand(S, 3), R, sigma=1.0)
    assert torch.allclose(tex[0][:, cov[0]], const[:, None].expand(-1, int(cov[0].sum())), atol=1e-5)
    assert not cov[0, 0, 0]  # far from every sample: not covered, neutral grey
    truth = torch.stack([uv[:, 0, 0], uv[:, 0, 1], 1 - uv[:, 0, 0]], -1)  # a smooth colour ramp
    noisy = truth + 0.1 * torch.randn(S, 3, generator=g)
    err_in = (noisy - truth).pow(2).mean()
    for sigma in (0.0, 2.0):
        tex, _, st = kernel_texture(probs, uv, noisy, R, sigma=sigma)
        err = ((probs[..., None] * sample_charts(tex, uv)).sum(1) - truth).pow(2).mean()
        assert err < (0.5 if sigma == 0 else 0.1) * err_in, (sigma, float(err), float(err_in))
    assert st > 0


def test_kernel_texture_is_finite_for_degenerate_samples():
    S, R = 50, 8
    uv = torch.full((S, 2, 2), 0.5)  # every sample at one point
    probs = torch.tensor([[1.0, 0.0]]).expand(S, 2)  # chart 1 gets nothing
    rgb = torch.rand(S, 3)
    for sigma in (0.0, 1.0, 100.0):
        tex, cov, st = kernel_texture(probs, uv, rgb, R, sigma)
        assert torch.isfinite(tex).all() and math.isfinite(st)
        assert cov[0].any() and not cov[1].any()
        assert torch.allclose(tex[1], torch.full_like(tex[1], 0.5))


def test_filled_kernel_texture_fills_every_gutter_texel_from_its_nearest_covered_one():
    """Against a plain reference: covered texels keep the kernel colour (clamped), every other texel of a chart
    with coverage takes the colour of a covered texel at the smallest distance; a chart nobody reaches stays grey."""
    g = torch.Generator().manual_seed(3)
    S, R = 300, 12
    uv = torch.rand(S, 2, 2, generator=g) * 0.4 + 0.3          # samples in the middle of each chart
    probs = torch.tensor([[1.0, 0.0]]).expand(S, 2).clone()    # chart 1 gets nothing
    rgb = torch.rand(S, 3, generator=g) * 1.4 - 0.2              # some outside [0, 1]
    tex, cov, st = filled_kernel_texture(probs, uv, rgb, R, 0.5)
    raw, raw_cov, raw_st = kernel_texture(probs, uv, rgb, R, 0.5)
    assert torch.equal(cov, raw_cov) and st == raw_st and cov[0].any() and not cov[0].all()
    assert torch.equal(tex[0][:, cov[0]], raw[0].clamp(0, 1)[:, cov[0]])
    src = torch.nonzero(cov[0]).float()                                  # [C, 2] covered (row, col)
    for r in range(R):
        for c in range(R):
            if cov[0, r, c]:
                continue
            d = ((src - torch.tensor([r, c], dtype=torch.float32)) ** 2).sum(1)
            near = src[d == d.min()].long()                             # ties: any nearest one will do
            cands = raw[0].clamp(0, 1)[:, near[:, 0], near[:, 1]].T       # [T, 3]
            assert bool((cands - tex[0][:, r, c]).abs().max(1).values.min() < 1e-6), (r, c)
    assert torch.allclose(tex[1], torch.full_like(tex[1], 0.5))


def _kernel_texture_whole_image(probs, uv, rgb, R, sigma, labels, min_prob=1e-3, min_weight=1e-3):
    """kernel_texture's definition on the whole R x R image of every chart (no window)."""
    from core.atlas.texture import blur_within
    csum, wsum = splat(probs, uv, rgb, R, min_prob)
    owner = probs.argmax(-1)
    out, cov = [], []
    for c in range(probs.shape[1]):
        s = sigma * texel_spacing(uv[owner == c, c] * R)
        num = blur_within(csum[c][None], s, labels)[0]
        den = blur_within(wsum[c][None, None], s, labels)[0, 0]
        ok = den > min_weight * max(float(den.max()), 1e-30)
        out.append(torch.where(ok[None], num / den.clamp_min(1e-30)[None], torch.full_like(num, 0.5)))
        cov.append(ok)
    return torch.stack(out), torch.stack(cov)


def test_kernel_texture_in_the_samples_window_equals_the_whole_image_form():
    """Each chart's sums are formed only in the window its samples reach grown by the blur's reach (an island
    layout's charts each cover a small part of the image): the same texture and coverage as on the whole image,
    with and without island labels, for charts in a corner, at the edge (clamped), spread out and empty."""
    from core.atlas.texture import splat_box
    g = torch.Generator().manual_seed(3)
    R, S = 64, 600
    uv = torch.rand(S, 4, 2, generator=g)
    uv[:, 0] = 0.1 + 0.1 * uv[:, 0]          # a small window
    uv[:, 1] = 0.9 + 0.2 * uv[:, 1]          # past the edge: clamped
    chart = torch.randint(0, 3, (S,), generator=g)  # chart 3 owns no sample
    probs = torch.nn.functional.one_hot(chart, 4).float()
    rgb = torch.rand(S, 3, generator=g)
    labels = torch.full((R, R), -1, dtype=torch.long)
    labels[4:20, 4:20], labels[50:, 50:], labels[20:50, 10:60] = 0, 1, 2
    for lab in (None, labels):
        for sigma in (0.7, 2.5):
            got = kernel_texture(probs, uv, rgb, R, sigma, labels=lab)
            want = _kernel_texture_whole_image(probs, uv, rgb, R, sigma, lab)
            assert torch.equal(got[1], want[1])
            assert torch.allclose(got[0], want[0], atol=1e-6)
    # the window holds every texel a sample's bilinear footprint reaches, and only those grown by the margin
    r0, r1, c0, c1 = splat_box(uv[chart == 0, 0], R, 2)
    _, w = splat(probs[chart == 0], uv[chart == 0], rgb[chart == 0], R, 0.0)
    rows, cols = torch.nonzero(w[0] > 0, as_tuple=True)
    assert (r0, r1, c0, c1) == (int(rows.min()) - 2, int(rows.max()) + 3, int(cols.min()) - 2, int(cols.max()) + 3)
    assert splat_box(uv[:0, 0], R, 2) == (0, R, 0, R)
