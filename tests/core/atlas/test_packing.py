import numpy as np
import torch

from core.atlas.packing import GridLayout, blend_charts, dilate_unused, pack, sample_charts, texel_uv, unpack, utilisation, uv_to_pixel


def _bilinear_ref(tex, u, v):
    """Plain bilinear with clamp-to-edge, texel centres at (i + 0.5) / R. tex [3, R, R]."""
    R = tex.shape[-1]
    fx, fy = u * R - 0.5, v * R - 0.5
    x0, y0 = int(np.floor(fx)), int(np.floor(fy))
    ax, ay = fx - x0, fy - y0
    cl = lambda i: min(max(i, 0), R - 1)  # noqa: E731
    t = lambda y, x: tex[:, cl(y), cl(x)]  # noqa: E731
    return ((1 - ay) * ((1 - ax) * t(y0, x0) + ax * t(y0, x0 + 1)) + ay * ((1 - ax) * t(y0 + 1, x0) + ax * t(y0 + 1, x0 + 1)))


def test_layout_shapes():
    assert GridLayout(4, 181, 4).shape == (2 * 189, 2 * 189)
    assert GridLayout(8, 128, 4).shape == (2 * 136, 4 * 136)


def test_pack_unpack_round_trip_is_bitwise_and_padding_replicates_edges():
    g = torch.Generator().manual_seed(0)
    for n, R, pad in [(4, 9, 2), (8, 6, 3), (4, 5, 0)]:
        L = GridLayout(n, R, pad)
        tex = torch.rand(n, 3, R, R, generator=g)
        img = pack(tex, L)
        assert img.shape == (*L.shape, 3)
        assert torch.equal(unpack(img, L), tex)
        if pad:
            r0, c0 = L.origin(1)
            assert torch.equal(img[r0 - pad, c0:c0 + R], tex[1, :, 0].T)  # row above = first row
            assert torch.equal(img[r0:r0 + R, c0 + R + pad - 1], tex[1, :, :, R - 1].T)  # right border


def test_sample_charts_matches_bilinear_reference():
    g = torch.Generator().manual_seed(1)
    tex = torch.rand(2, 3, 7, 7, generator=g)
    uv = torch.rand(20, 2, 2, generator=g) * 1.2 - 0.1  # include out-of-range coordinates (clamped)
    out = sample_charts(tex, uv)
    for m in range(20):
        for c in range(2):
            ref = _bilinear_ref(tex[c], float(uv[m, c, 0]), float(uv[m, c, 1]))
            assert torch.allclose(out[m, c], ref, atol=1e-5)


def test_blend_charts_is_the_probability_weighted_sum_of_the_lookups():
    g = torch.Generator().manual_seed(3)
    tex = torch.rand(3, 4, 9, 9, generator=g)  # rgb + mask channels
    uv = torch.rand(50, 3, 2, generator=g) * 1.2 - 0.1
    probs = torch.softmax(torch.randn(50, 3, generator=g), 1)
    out = blend_charts(tex, uv, probs)
    ref = torch.zeros(50, 4)
    for m in range(50):
        for c in range(3):
            ref[m] += probs[m, c] * _bilinear_ref(tex[c], float(uv[m, c, 0]), float(uv[m, c, 1]))
    assert out.shape == (50, 4) and torch.allclose(out, ref, atol=1e-5)
    assert torch.equal(out, (probs[..., None] * sample_charts(tex, uv)).sum(1))  # same sums, same order


def test_blend_charts_with_one_chart_per_point_reads_that_chart_only():
    """One-hot probabilities (island atlases): each point looked up in its own chart only gives exactly the
    probability-weighted sum over all charts; an infinite or NaN lookup in a chart a point does not use no longer
    reaches it."""
    g = torch.Generator().manual_seed(4)
    tex = torch.rand(4, 4, 9, 9, generator=g)
    uv = torch.rand(300, 4, 2, generator=g) * 1.2 - 0.1
    chart = torch.randint(0, 4, (300,), generator=g)
    probs = torch.nn.functional.one_hot(chart, 4).float()
    out = blend_charts(tex, uv, probs)
    assert torch.equal(out, (probs[..., None] * sample_charts(tex, uv)).sum(1))
    bad = uv.clone()
    bad[torch.arange(300), (chart + 1) % 4] = float("nan")  # another chart's coordinates unusable
    assert torch.equal(blend_charts(tex, bad, probs), out)
    assert blend_charts(tex, uv[:0], probs[:0]).shape == (0, 4)


def test_texel_centres_sample_exact_texels_and_pixel_coords():
    L = GridLayout(4, 8, 2)
    tex = torch.rand(4, 3, 8, 8, generator=torch.Generator().manual_seed(2))
    u = texel_uv(8)
    out = sample_charts(tex, u[:, None].expand(-1, 4, -1).contiguous())  # [64, 4, 3]
    assert torch.allclose(out[:, 2].T.reshape(3, 8, 8), tex[2], atol=1e-6)
    img = pack(tex, L)
    pix = uv_to_pixel(u, torch.full((64,), 3, dtype=torch.long), L)
    rows, cols = pix[:, 1].floor().long(), pix[:, 0].floor().long()
    assert torch.equal(img[rows, cols], tex[3].reshape(3, -1).T)


def test_dilation_fills_only_unused_texels():
    tex = torch.zeros(1, 3, 5, 5)
    tex[0, :, 2, 2] = torch.tensor([1.0, 0.5, 0.25])[:, None].squeeze()
    used = torch.zeros(1, 5, 5, dtype=torch.bool)
    used[0, 2, 2] = True
    out = dilate_unused(tex, used)
    assert torch.equal(out[0, :, 0, 4], tex[0, :, 2, 2])
    assert torch.equal(out[0, :, 2, 2], tex[0, :, 2, 2])


def test_utilisation_counts_distinct_pixels():
    pix = np.array([[0.2, 0.2], [0.7, 0.9], [3.5, 1.5]])
    assert utilisation(pix, (2, 4)) == 2 / 8
