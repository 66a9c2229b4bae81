"""Anti-aliased lookups: filter taps, sub-pixel interpolation and the filter against plain loop references."""
import math

import pytest
import torch

from core.images.filter import blackman_harris_taps, filter_down, subpixel_points


@pytest.mark.parametrize("sub", [1, 2, 3, 4])
def test_taps_are_a_normalised_symmetric_blackman_harris(sub):
    k = blackman_harris_taps(sub)
    m = round(3.0 * sub)
    assert k.shape == (m,) and abs(float(k.sum()) - 1.0) < 1e-6
    assert torch.allclose(k, k.flip(0), atol=1e-7)
    t = (torch.arange(m, dtype=torch.float64) + 0.5) / m  # plain formula, normalised
    w = torch.tensor([0.35875 - 0.48829 * math.cos(2 * math.pi * v) + 0.14128 * math.cos(4 * math.pi * v)
                      - 0.01168 * math.cos(6 * math.pi * v) for v in t], dtype=torch.float64)
    assert torch.allclose(k.double(), w / w.sum(), atol=1e-7)
    with pytest.raises(ValueError):
        blackman_harris_taps(0)


def _filter_reference(values, on, sub, width=3.0):
    """Loop over pixels and taps: each pixel's footprint centred on it, weights = outer product of the taps."""
    C, SH, SW = values.shape
    H, W = SH // sub, SW // sub
    k = blackman_harris_taps(sub, width).double()
    m = len(k)
    out = torch.full((C, H, W), float("nan"), dtype=torch.float64)
    for r in range(H):
        for c in range(W):
            num, den = torch.zeros(C, dtype=torch.float64), 0.0
            for i in range(m):
                for j in range(m):
                    y = sub * r - (m - sub) // 2 + i
                    x = sub * c - (m - sub) // 2 + j
                    if 0 <= y < SH and 0 <= x < SW and on[y, x]:
                        w = float(k[i] * k[j])
                        num += w * values[:, y, x].double()
                        den += w
            if den > 0:
                out[:, r, c] = num / den
    return out


@pytest.mark.parametrize("sub", [1, 2, 3])
def test_filter_down_matches_the_loop_reference(sub):
    g = torch.Generator().manual_seed(sub)
    H, W = 5, 7
    vals = torch.rand(4, sub * H, sub * W, generator=g)
    on = torch.rand(sub * H, sub * W, generator=g) > 0.3
    on[: sub * 2, : sub * 2] = False  # a region with no object at all -> NaN pixel
    got = filter_down(vals, on, sub)
    ref = _filter_reference(vals, on, sub)
    assert got.shape == (4, H, W)
    assert torch.equal(torch.isnan(got), torch.isnan(ref.float()))
    ok = ~torch.isnan(ref)
    assert torch.allclose(got[ok].double(), ref[ok], atol=1e-5)
    # values where `on` is False never leak in, even if they are NaN
    vals2 = vals.clone()
    vals2[:, ~on] = float("nan")
    assert torch.equal(torch.isnan(filter_down(vals2, on, sub)), torch.isnan(got))


def test_filter_of_a_constant_is_the_constant():
    on = torch.ones(8, 8, dtype=torch.bool)
    out = filter_down(torch.full((3, 8, 8), 0.25), on, 2)
    assert torch.allclose(out, torch.full((3, 4, 4), 0.25))


def test_subpixel_points_interpolate_a_plane_exactly():
    """A planar point map (linear in pixel coordinates) gives exactly the plane at every sub-pixel centre."""
    H, W, sub = 6, 5, 2
    r, c = torch.meshgrid(torch.arange(H) + 0.5, torch.arange(W) + 0.5, indexing="ij")
    plane = lambda rr, cc: torch.stack([0.1 * cc, -0.2 * rr, 1.0 + 0.03 * cc + 0.01 * rr], -1)
    pts = plane(r.double(), c.double())
    valid = torch.ones(H, W, dtype=torch.bool)
    sp = subpixel_points(pts, valid, pts[..., 2], sub, max_depth_step=1.0)
    sr, sc = torch.meshgrid((torch.arange(sub * H) + 0.5) / sub, (torch.arange(sub * W) + 0.5) / sub, indexing="ij")
    want = plane(sr.double(), sc.double())
    # the border sub-pixels (outside the outermost centres) are clamped to their pixel's row/column
    inner = (sr > 0.5) & (sr < H - 0.5) & (sc > 0.5) & (sc < W - 0.5)
    assert torch.allclose(sp[inner], want[inner], atol=1e-12)
    assert torch.isfinite(sp).all()


def test_subpixel_points_do_not_mix_surfaces_across_an_occlusion_edge():
    """Left half near (depth 1), right half far (depth 5): sub-pixels stay on their own pixel's surface; invalid
    pixels give NaN."""
    H, W, sub = 4, 6, 2
    near = torch.zeros(H, W, dtype=torch.bool)
    near[:, :3] = True
    depth = torch.where(near, torch.tensor(1.0), torch.tensor(5.0))
    pts = torch.zeros(H, W, 3)
    pts[..., 2] = depth
    valid = torch.ones(H, W, dtype=torch.bool)
    valid[0, 5] = False
    sp = subpixel_points(pts, valid, depth, sub, max_depth_step=0.5)
    z = sp[..., 2]
    owner_near = near.repeat_interleave(sub, 0).repeat_interleave(sub, 1)
    owner_valid = valid.repeat_interleave(sub, 0).repeat_interleave(sub, 1)
    assert torch.isnan(z[~owner_valid]).all()
    assert torch.equal(z[owner_near & owner_valid], torch.ones(int((owner_near & owner_valid).sum())))
    assert torch.equal(z[~owner_near & owner_valid], torch.full((int((~owner_near & owner_valid).sum()),), 5.0))
    # a generous step would mix them: the check is what keeps the surfaces apart
    mixed = subpixel_points(pts, valid, depth, sub, max_depth_step=10.0)[..., 2]
    assert ((mixed[owner_valid] > 1.0) & (mixed[owner_valid] < 5.0)).any()


def test_off_centre_filters_are_refused():
    with pytest.raises(ValueError, match="centred"):
        filter_down(torch.zeros(1, 4, 4), torch.ones(4, 4, dtype=torch.bool), 2, width=1.5)


def test_subpixel_chart_uv_matches_the_nets_at_interpolated_points():
    """Interpolating the chart nets' outputs per pixel is what evaluating them at the interpolated sub-pixel
    points gives, to second order: on a finely sampled plane the two agree closely, and the layout matches."""
    from core.atlas.atlas import Atlas
    from core.atlas.subpixel import subpixel_chart_uv

    torch.manual_seed(0)
    atlas = Atlas(4, 16, 2, torch.zeros(3), 1.0, width_chart=16, depth_chart=2, width_map=16, depth_map=2,
                  fourier_chart=1, fourier_map=1)  # the default Fourier degrees of a fitted atlas
    H, W, sub = 12, 10, 2
    r, c = torch.meshgrid(torch.arange(H) + 0.5, torch.arange(W) + 0.5, indexing="ij")
    pts = torch.stack([0.01 * c - 0.05, 0.012 * r - 0.07, 0.5 + 0.002 * c], -1)  # pixels ~1 cm apart
    valid = torch.ones(H, W, dtype=torch.bool)
    valid[3, 4] = False
    depth = pts[..., 2]
    probs, uv, on = subpixel_chart_uv(atlas, pts, valid, depth, sub, 0.1)
    sp = subpixel_points(pts, valid, depth, sub, 0.1)
    assert torch.equal(on, torch.isfinite(sp).all(-1))
    p_ref, uv_ref = atlas.chart_uv(sp[on])
    assert probs.shape == p_ref.shape and uv.shape == uv_ref.shape
    assert (probs - p_ref).abs().max() < 1e-3 and (uv - uv_ref).abs().max() < 1e-3
    assert torch.allclose(probs.sum(-1), torch.ones(len(probs)), atol=1e-5)


def test_subpixel_chart_uv_leaves_out_what_a_non_finite_output_reaches(monkeypatch):
    """A chart network output that is not finite at one pixel: that pixel's sub-pixels and the neighbours' that
    blend it are left out (`on` False), every other sub-pixel is kept and finite."""
    from core.atlas.atlas import Atlas
    from core.atlas.subpixel import subpixel_chart_uv

    torch.manual_seed(0)
    atlas = Atlas(2, 16, 2, torch.zeros(3), 1.0, width_chart=16, depth_chart=2, width_map=16, depth_map=2,
                  fourier_chart=1, fourier_map=1)
    H, W, sub = 6, 7, 2
    r, c = torch.meshgrid(torch.arange(H) + 0.5, torch.arange(W) + 0.5, indexing="ij")
    pts = torch.stack([0.01 * c, 0.01 * r, 0.5 + 0 * c], -1)
    valid = torch.ones(H, W, dtype=torch.bool)
    clean = subpixel_chart_uv(atlas, pts, valid, pts[..., 2], sub, 0.1)[2]
    assert bool(clean.all())
    real = atlas.chart_uv

    def broken(x, placed=True):
        probs, uv = real(x, placed=placed)
        return probs, uv.clone().index_fill_(0, torch.tensor([2 * W + 3]), float("nan"))  # pixel (2, 3)
    monkeypatch.setattr(atlas, "chart_uv", broken)
    probs, uv, on = subpixel_chart_uv(atlas, pts, valid, pts[..., 2], sub, 0.1)
    assert not bool(on[4:6, 6:8].any())  # the pixel's own sub-pixels
    assert not bool(on[3, 6]) and not bool(on[6, 8])  # neighbours' sub-pixels towards it
    assert bool(on[0, 0]) and int(on.sum()) == len(probs) and torch.isfinite(uv).all()


def _subpixel_loop_reference(points, valid, depth, sub, step):
    """Per sub-pixel, plainly: bilinear weights of the pixel and its 3 neighbours towards the sub-pixel, keeping
    neighbours inside the image, valid and within `step` in depth of the owning pixel; renormalised."""
    H, W, C = points.shape
    out = torch.full((sub * H, sub * W, C), float("nan"), dtype=points.dtype)
    for r in range(H):
        for c in range(W):
            if not valid[r, c]:
                continue
            for a in range(sub):
                for b in range(sub):
                    fy, fx = (a + 0.5) / sub - 0.5, (b + 0.5) / sub - 0.5
                    dy, dx = (1 if fy >= 0 else -1), (1 if fx >= 0 else -1)
                    num, den = torch.zeros(C, dtype=points.dtype), 0.0
                    for oy, wy in ((0, 1 - abs(fy)), (dy, abs(fy))):
                        for ox, wx in ((0, 1 - abs(fx)), (dx, abs(fx))):
                            r2, c2 = r + oy, c + ox
                            if 0 <= r2 < H and 0 <= c2 < W and valid[r2, c2] and abs(depth[r2, c2] - depth[r, c]) <= step:
                                num += wy * wx * points[r2, c2]
                                den += wy * wx
                    out[sub * r + a, sub * c + b] = num / den
    return out


@pytest.mark.parametrize("sub, channels", [(1, 3), (2, 3), (2, 12), (3, 5)])
def test_subpixel_points_match_the_loop_reference(sub, channels):
    g = torch.Generator().manual_seed(sub * 10 + channels)
    H, W = 5, 6
    pts = torch.randn(H, W, channels, generator=g, dtype=torch.float64)
    valid = torch.rand(H, W, generator=g) > 0.25
    depth = torch.rand(H, W, generator=g, dtype=torch.float64) * 2
    got = subpixel_points(pts, valid, depth, sub, 0.7)
    want = _subpixel_loop_reference(pts, valid, depth, sub, 0.7)
    assert torch.equal(torch.isnan(got), torch.isnan(want))
    assert torch.allclose(got.nan_to_num(0), want.nan_to_num(0), atol=1e-12)


@pytest.mark.parametrize("sub", [1, 2, 3])
def test_filter_down_equals_the_strided_conv2d_form(sub):
    """The per-tap strided sums give the separable strided conv2d's numbers (≤ 1e-5) on a frame-sized input."""
    import torch.nn.functional as F

    from core.images.filter import FILTER_WIDTH, blackman_harris_taps

    g = torch.Generator().manual_seed(10 + sub)
    H, W = 37, 52
    vals = torch.rand(4, sub * H, sub * W, generator=g)
    on = torch.rand(sub * H, sub * W, generator=g) > 0.4
    k = blackman_harris_taps(sub)
    pad = (k.numel() - sub) // 2
    w = on.float()[None]
    stack = F.pad(torch.cat([vals * w, w], 0)[:, None], (pad, pad, pad, pad))
    y = F.conv2d(F.conv2d(stack, k.view(1, 1, 1, -1), stride=(1, sub)), k.view(1, 1, -1, 1), stride=(sub, 1))[:, 0]
    ref = torch.where(y[-1] > 1e-8, y[:-1] / y[-1].clamp_min(1e-12), torch.full_like(y[:-1], float("nan")))
    got = filter_down(vals, on, sub, FILTER_WIDTH)
    assert torch.equal(torch.isnan(got), torch.isnan(ref))
    ok = ~torch.isnan(ref)
    assert float((got[ok] - ref[ok]).abs().max()) <= 1e-5
