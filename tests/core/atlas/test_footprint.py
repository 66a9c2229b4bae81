"""Footprint texture refit: the assembled system equals filtered rendering done the plain way, and solving it
reproduces pixels made by a known texture."""
import torch

from core.atlas.atlas import Atlas
from core.atlas.footprint import FootprintView, footprint_system, solve_footprint_texture
from core.atlas.packing import sample_charts
from core.images.colour import linear_to_srgb
from core.images.filter import filter_down, subpixel_points


def _setup(H=10, W=12, sub=2):
    torch.manual_seed(0)
    atlas = Atlas(2, 16, 2, torch.zeros(3), 1.0, width_chart=16, depth_chart=1, width_map=16, depth_map=1)
    r, c = torch.meshgrid(torch.arange(H) + 0.5, torch.arange(W) + 0.5, indexing="ij")
    pts = torch.stack([0.05 * c - 0.3, 0.04 * r - 0.2, 1.0 + 0.01 * c], -1)  # a tilted plane seen head-on
    valid = torch.ones(H, W, dtype=torch.bool)
    valid[:, :2] = False  # some rays miss
    alpha = valid.float()
    alpha[0, 5] = 0.5     # a partly covered pixel: not used as a target
    view = FootprintView(points=pts, valid=valid, depth=pts[..., 2], image=torch.zeros(H, W, 3), alpha=alpha,
                         focal=100.0)
    return atlas, view, sub


def test_system_matches_plain_filtered_rendering():
    atlas, view, sub = _setup()
    F, B, _, _ = footprint_system(atlas, [view], sub)
    tex = torch.rand(atlas.n * atlas.layout.R ** 2, 3, generator=torch.Generator().manual_seed(1))
    pred = F @ (B @ tex)  # [P, 3] linear light
    # plain path, as core/frames/edited.py renders: chart nets at each pixel's point, their outputs interpolated
    # to the sub-pixels, one lookup each, filter down
    H, W = view.valid.shape
    p, u = atlas.chart_uv(view.points[view.valid])
    feat = torch.zeros(H, W, 3 * atlas.n)
    feat[view.valid] = torch.cat([p, u.reshape(-1, 2 * atlas.n)], 1)
    sp = subpixel_points(feat, view.valid, view.depth, sub, 3.0 * view.depth / view.focal)
    on = torch.isfinite(sp).all(-1)
    probs, uv = sp[on][:, :atlas.n], sp[on][:, atlas.n:].reshape(-1, atlas.n, 2)
    textures = tex.reshape(atlas.n, atlas.layout.R, atlas.layout.R, 3).permute(0, 3, 1, 2)
    vals = torch.zeros(3, *on.shape)
    vals[:, on] = (probs[..., None] * sample_charts(textures, uv)).sum(1).T
    ref = filter_down(vals, on, sub).permute(1, 2, 0)
    use = view.valid & (view.alpha > 0.99)
    assert pred.shape == (int(use.sum()), 3)
    assert torch.allclose(pred, ref[use], atol=1e-5)


def test_system_through_the_samples_matches_plain_filtered_rendering():
    """lookup "samples": each sub-pixel reads its nearest stored samples' texels, as edited frames do."""
    from core.atlas.sample_lookup import sample_lookup

    atlas, view, sub = _setup()
    g = torch.Generator().manual_seed(2)
    atlas.bake_samples = view.points[view.valid] + 0.01 * torch.randn(int(view.valid.sum()), 3, generator=g)
    F, B, _, _ = footprint_system(atlas, [view], sub, lookup="samples", k=3)
    tex = torch.rand(atlas.n * atlas.layout.R ** 2, 3, generator=torch.Generator().manual_seed(1))
    pred = F @ (B @ tex)
    lk = sample_lookup(atlas)
    sp = subpixel_points(view.points, view.valid, view.depth, sub, 3.0 * view.depth / view.focal)
    on = torch.isfinite(sp).all(-1)
    textures = tex.reshape(atlas.n, atlas.layout.R, atlas.layout.R, 3).permute(0, 3, 1, 2)
    vals = torch.zeros(3, *on.shape)
    vals[:, on] = lk.lookup(lk.read(textures), sp[on], 3).T.float()
    ref = filter_down(vals, on, sub).permute(1, 2, 0)
    use = view.valid & (view.alpha > 0.99)
    assert torch.allclose(pred, ref[use], atol=1e-5)
    charts = footprint_system(atlas, [view], sub, lookup="charts").B
    assert not torch.equal(B.to_dense(), charts.to_dense())


def test_solving_reproduces_pixels_of_a_known_texture():
    atlas, view, sub = _setup()
    F, B, _, _ = footprint_system(atlas, [view], sub)
    T = atlas.n * atlas.layout.R ** 2
    truth = torch.rand(T, 3, generator=torch.Generator().manual_seed(2))
    y = F @ (B @ truth)
    t0 = torch.full((T, 3), 0.5)
    t, info = solve_footprint_texture(F, B, y, t0, lam=1e-4, iters=300)
    assert info["rmse_after"] < 0.1 * info["rmse_before"] and info["rmse_after"] < 5e-3
    assert torch.isfinite(t).all() and bool(((t >= 0) & (t <= 1)).all())
    untouched = torch.ones(T, dtype=torch.bool)
    untouched[B.col_indices()] = False
    assert torch.allclose(t[untouched], t0[untouched])  # the prior holds texels no pixel sees
    assert linear_to_srgb(t).shape == (T, 3)


def test_no_covered_pixel_gives_no_system():
    atlas, view, sub = _setup()
    view.alpha = torch.zeros_like(view.alpha)
    assert footprint_system(atlas, [view], sub) is None


def _plain_cg(F, B, y, t0, lam, iters):
    """The refit's equations solved the plain way: dense AᵀA over every texel, the same conjugate gradients, in
    double precision."""
    A = (F.to_dense() @ B.to_dense()).double()
    AtA, Aty = A.T @ A, A.T @ y.double()
    reg = lam * float((AtA @ torch.ones(len(AtA), dtype=torch.float64)).mean())
    M = AtA + reg * torch.eye(len(AtA), dtype=torch.float64)
    t = t0.double().clone()
    r = Aty + reg * t0.double() - M @ t
    p, rs = r.clone(), (r * r).sum(0)
    for _ in range(iters):
        Mp = M @ p
        a = rs / (p * Mp).sum(0).clamp_min(1e-30)
        t, r = t + a * p, r - a * Mp
        rs_new = (r * r).sum(0)
        if float(rs_new.max()) < 1e-20:
            break
        p, rs = r + (rs_new / rs.clamp_min(1e-30)) * p, rs_new
    return t.clamp(0, 1).float()


def test_solving_on_the_read_texels_alone_equals_the_plain_solve_over_all_texels():
    """The iterations run only on the texels some lookup reads; the answer is the plain full solve's (most of the
    atlas here is never read: 2 charts of 16² texels, a 10 x 12 view)."""
    atlas, view, sub = _setup()
    F, B, _, _ = footprint_system(atlas, [view], sub)
    T = atlas.n * atlas.layout.R ** 2
    g = torch.Generator().manual_seed(3)
    y = F @ (B @ torch.rand(T, 3, generator=g)) + 0.05 * torch.randn(F.shape[0], 3, generator=g)
    t0 = torch.rand(T, 3, generator=g)
    assert len(torch.unique(B.col_indices())) < T // 2
    for lam, iters in ((1.0, 100), (0.1, 300)):
        t, _ = solve_footprint_texture(F, B, y, t0, lam=lam, iters=iters, tol=0.0)
        assert torch.allclose(t, _plain_cg(F, B, y, t0, lam, iters), atol=2e-4)
        # stopping once converged (the default tolerance) gives the same texture to well within a colour step
        t_tol, _ = solve_footprint_texture(F, B, y, t0, lam=lam, iters=iters)
        assert float((t_tol - t).abs().max()) < 2e-3


def _views_of_a_known_texture(noise: float, seed: int):
    """Eight views (the same plane) of a known texture with `noise` added to each view's pixels independently, and
    the system over them."""
    atlas, view, sub = _setup()
    system = footprint_system(atlas, [view] * 8, sub)
    T = atlas.n * atlas.layout.R ** 2
    g = torch.Generator().manual_seed(seed)
    truth = 0.2 + 0.6 * torch.rand(T, 3, generator=g)
    y = (system.F @ (system.B @ truth) + noise * torch.randn(system.F.shape[0], 3, generator=g)).clamp(0, 1)
    return system._replace(y=y), truth, T, g


def test_the_held_out_views_choose_a_weak_pull_for_clean_pixels_and_a_strong_one_for_noisy_pixels():
    """Clean pixels and a wrong prior: the fit should follow the pixels (smallest λ). Noisy pixels and the true
    texture as the prior: it should stay at the prior (largest λ)."""
    from core.atlas.footprint import choose_footprint_lambda

    lambdas = [1e-3, 1.0, 1e3]
    system, truth, T, g = _views_of_a_known_texture(0.0, 4)
    lam, scores = choose_footprint_lambda(system, torch.rand(T, 3, generator=g), lambdas, iters=300)
    assert lam == 1e-3 and set(scores) == set(lambdas) and scores[1e-3] > scores[1e3] + 3.0
    system, truth, T, g = _views_of_a_known_texture(0.2, 5)
    lam, scores = choose_footprint_lambda(system, truth, lambdas, iters=300)
    assert lam == 1e3 and scores[1e3] > scores[1e-3] + 0.2  # the held-out pixels carry the noise too
    assert all(torch.isfinite(torch.tensor(list(scores.values()))))


def test_choosing_needs_held_out_views():
    """Fewer views than one held-out in four, or no candidates: nothing to choose by (None), no error."""
    from core.atlas.footprint import choose_footprint_lambda

    atlas, view, sub = _setup()
    system = footprint_system(atlas, [view] * 3, sub)
    t0 = torch.full((atlas.n * atlas.layout.R ** 2, 3), 0.5)
    assert choose_footprint_lambda(system, t0, [0.1, 1.0]) == (None, {})
    system = footprint_system(atlas, [view] * 4, sub)
    assert choose_footprint_lambda(system, t0, []) == (None, {})
    lam, scores = choose_footprint_lambda(system, t0, [0.1, 1.0])
    assert lam in (0.1, 1.0) and len(scores) == 2


def test_refit_reports_the_lambda_it_used():
    from core.atlas.footprint import refit_texture_footprint

    atlas, view, sub = _setup()
    g = torch.Generator().manual_seed(6)
    view.image = torch.rand(*view.valid.shape, 3, generator=g)
    info = refit_texture_footprint(atlas, [view] * 4, sub, lam=2.0, lambdas=[0.5, 8.0])
    assert info["lambda"] in (0.5, 8.0) and set(info["holdout_psnr"]) == {"0.5", "8"}
    info = refit_texture_footprint(atlas, [view] * 4, sub, lam=2.0, lambdas=[])
    assert info["lambda"] == 2.0 and "holdout_psnr" not in info
    info = refit_texture_footprint(atlas, [view] * 4, sub, lam=2.0, lambdas=[25.0])  # one candidate: that λ
    assert info["lambda"] == 25.0 and "holdout_psnr" not in info
    info = refit_texture_footprint(atlas, [view] * 3, sub, lam=2.0, lambdas=[0.5, 8.0])  # too few views to choose
    assert info["lambda"] == 2.0 and "holdout_psnr" not in info
    assert torch.isfinite(atlas.textures).all()


def test_lambda_candidates_parse_and_refuse_bad_lists():
    import pytest

    from core.atlas.config import AtlasConfig
    from core.util.errors import InputError

    assert AtlasConfig(footprint_lambdas="").lambda_candidates() == []
    assert AtlasConfig(footprint_lambdas=" 0.25, 1,4 ,").lambda_candidates() == [0.25, 1.0, 4.0]
    for bad in ("1,x", "-1", "nan", "1,inf"):
        with pytest.raises(InputError, match="footprint-lambdas"):
            AtlasConfig(footprint_lambdas=bad).lambda_candidates()


def test_csr_from_row_sorted_entries_equals_the_coalesced_matrix():
    """_csr takes entries sorted by row — columns ascending (the fast path) or not, with repeats (clamped bilinear
    corners) — and gives the matrix COO coalescing gives, repeats summed; _bilinear_rows at and beyond the image's
    edges (every corner clamp) is one such input."""
    from core.atlas.footprint import _bilinear_rows, _csr

    g = torch.Generator().manual_seed(3)
    S, n, R = 400, 3, 8
    probs = torch.softmax(4 * torch.randn(S, n, generator=g), -1)
    uv = 1.4 * torch.rand(S, n, 2, generator=g) - 0.2  # a fifth of the corners clamped onto their neighbour
    for rows, cols, vals in (_bilinear_rows(probs, uv, R),
                             (torch.tensor([0, 0, 0, 1, 1, 2]), torch.tensor([0, 2, 2, 1, 3, 5]), torch.arange(6.0))):  # ascending, a repeat
        shape = (int(rows.max()) + 1, n * R * R)
        ref = torch.sparse_coo_tensor(torch.stack([rows, cols]), vals, shape, check_invariants=True).coalesce()
        got = _csr(rows, cols, vals, shape).to_sparse_coo().coalesce()
        assert torch.equal(got.indices(), ref.indices())
        assert torch.allclose(got.values(), ref.values(), rtol=0, atol=1e-7)
        assert got._nnz() == _csr(rows, cols, vals, shape).values().numel()  # no repeated entry left
    r, c, _ = _bilinear_rows(probs, uv, R)
    key = r * n * R * R + c
    assert not bool((key[1:] >= key[:-1]).all())  # the test reaches the sorting path
