"""Neighbour search: the fast paths return the same neighbour sets as plain-torch brute force (ties aside).

Screen searches are checked uncapped (k-d tree, max_radius_px = inf) and with a pixel radius cap (pixel grid and
capped brute force); the references below apply the same cap."""
from __future__ import annotations

import itertools
import math

import pytest
import torch

from core.config import from_dict, to_dict
from core.images.cameras import look_at, pixel_rays, rays_for_pixels
from core.points.neighbors import compiled
from core.points.neighbors import grid
from core.points import neighbors as nb
from core.points.model import ModelConfig
from core.util.errors import InputError

H = W = 24
FOCAL = 1.1 * W
BACKENDS = ("kdtree", "torch")
# capped screen searches: the torch grid everywhere, the compiled (numba) grid where numba is installed
GRIDS = ("grid", "compiled") if compiled.available() else ("grid",)
INF = math.inf


# ------------------------------------------------------------------------------- plain-torch references (float64)
def _absent(points):
    return ~(torch.isfinite(points) & (points.abs() <= 1e18)).all(dim=1)


def _topk_ref(d, k):
    """d [R, N] float64 (inf = not a candidate) -> idx [R, k] (-1 pad), dist [R, k] (inf pad)."""
    r, n = d.shape
    vals, ids = torch.topk(d, min(k, n), dim=1, largest=False) if n else (d.new_empty(r, 0), d.new_empty(r, 0).long())
    idx = torch.full((r, k), -1, dtype=torch.int64)
    dist = torch.full((r, k), math.inf, dtype=torch.float64)
    idx[:, :vals.shape[1]], dist[:, :vals.shape[1]] = ids, vals
    idx[~torch.isfinite(dist)] = -1
    return idx, dist


def ref_perpendicular(points, origins, dirs, k):
    p, o, d = points.double(), origins.double(), dirs.double()
    d = d / d.norm(dim=1, keepdim=True)
    v = p[None] - o[:, None]  # [R, N, 3]
    along = (v * d[:, None]).sum(-1)
    perp = (v - along[..., None] * d[:, None]).norm(dim=-1)
    perp = perp.masked_fill(~(along > 0) | _absent(points)[None] | ~torch.isfinite(perp), math.inf)
    return _topk_ref(perp, k)


def ref_screen(points, c2w, query_px, k, depth_factor, cap=INF):
    """Brute-force screen search; cap: pixel radius, a number or per point [1, N]."""
    p, m = points.double(), c2w.double()
    cam = (p - m[:3, 3]) @ m[:3, :3]
    z = -cam[:, 2]
    col = FOCAL * cam[:, 0] / z + 0.5 * W
    row = -FOCAL * cam[:, 1] / z + 0.5 * H
    keep = (z > 0) & (col >= -1) & (col <= W + 1) & (row >= -1) & (row <= H + 1) & ~_absent(points)
    px = torch.stack([col, row], -1)
    d = (query_px.double()[:, None, :] - px[None]).norm(dim=-1)
    keep = keep[None] & (d <= cap)
    if depth_factor:
        d = d * (z / FOCAL)[None]
    d = d.masked_fill(~keep | ~torch.isfinite(d), math.inf)
    return _topk_ref(d, k)


def assert_same(got, ref, rtol=1e-4):
    """Same sorted distances and the same neighbour sets, except for members tied with the K-th distance."""
    ref_idx, ref_dist = ref
    assert got.idx.dtype == torch.int64 and got.dist.dtype == torch.float32
    assert torch.equal(got.valid, ref_idx >= 0)
    assert torch.equal(got.idx < 0, ~torch.isfinite(got.dist))
    fin = torch.isfinite(ref_dist)
    tol = rtol * (1 + ref_dist[fin].abs())
    assert torch.all((got.dist.double()[fin] - ref_dist[fin]).abs() <= tol)
    assert torch.all(got.dist[:, 1:] >= got.dist[:, :-1])  # ascending
    kth = ref_dist.masked_fill(~fin, -math.inf).max(dim=1, keepdim=True).values
    sure = fin & (ref_dist < kth - rtol * (1 + kth.abs()))  # strictly inside: not a tie
    member = (ref_idx[:, :, None] == got.idx[:, None, :]).any(-1)
    assert torch.all(member[sure])
    valid_idx = got.idx.masked_fill(~got.valid, -1)
    for_dupes = valid_idx.sort(dim=1).values
    assert not torch.any((for_dupes[:, 1:] == for_dupes[:, :-1]) & (for_dupes[:, 1:] >= 0))  # no duplicates


# ---------------------------------------------------------------------------------------------------- scenes
def scene(kind: str, n: int, seed: int) -> torch.Tensor:
    g = torch.Generator().manual_seed(seed)
    if kind == "blob":
        return torch.randn(n, 3, generator=g) * 0.6
    if kind == "sphere":
        p = torch.randn(n, 3, generator=g)
        return p / p.norm(dim=1, keepdim=True)
    if kind == "plane":  # thin, planar cloud: many near-equal depths
        p = torch.rand(n, 3, generator=g) * 2 - 1
        p[:, 2] = 0.0
        return p
    if kind == "line":
        t = torch.rand(n, 1, generator=g) * 2 - 1
        return t * torch.tensor([[1.0, 0.5, 0.2]]) + 1e-3 * torch.randn(n, 3, generator=g)
    raise ValueError(kind)


def camera(seed: int) -> torch.Tensor:
    g = torch.Generator().manual_seed(seed + 100)
    eye = torch.randn(3, generator=g)
    eye = 3.5 * eye / eye.norm()
    return look_at(eye.tolist()).float()


def random_px(r: int, seed: int) -> torch.Tensor:
    g = torch.Generator().manual_seed(seed + 200)
    return torch.rand(r, 2, generator=g) * torch.tensor([W + 6.0, H + 6.0]) - 3.0  # some outside the frame


def rays(c2w):
    o, d = pixel_rays(c2w, H, W, FOCAL)
    return o.reshape(-1, 3), d.reshape(-1, 3)


# ---------------------------------------------------------------------------------------------- equality
@pytest.mark.parametrize("backend", BACKENDS)
@pytest.mark.parametrize("kind", ["blob", "sphere", "plane", "line"])
@pytest.mark.parametrize("seed", [0, 1, 2])
def test_perpendicular_matches_brute_force(kind, seed, backend):
    pts = scene(kind, 800, seed)
    o, d = rays(camera(seed))
    d = d * (1 + torch.rand(d.shape[0], 1))  # non-unit directions are normalised
    got = nb.rays_knn_perpendicular(pts, o, d, 12, backend=backend)
    assert_same(got, ref_perpendicular(pts, o, d, 12))


@pytest.mark.parametrize("backend", BACKENDS)
@pytest.mark.parametrize("depth_factor", [False, True])
@pytest.mark.parametrize("kind", ["blob", "sphere", "plane", "line"])
@pytest.mark.parametrize("seed", [0, 1, 2])
def test_screen_uncapped_matches_brute_force(kind, seed, depth_factor, backend):
    pts = scene(kind, 800, seed)
    c2w = camera(seed)
    q = random_px(700, seed)
    got = nb.screen_knn(pts, c2w, H, W, FOCAL, q, 12, depth_factor=depth_factor, backend=backend, max_radius_px=INF)
    assert_same(got, ref_screen(pts, c2w, q, 12, depth_factor))


def test_rays_from_several_origins_and_small_groups():
    pts = scene("blob", 800, 3)
    o1, d1 = rays(camera(1))
    o2, d2 = rays(camera(2))
    o3, d3 = rays(camera(3))
    o = torch.cat([o1, o2[:200], o3[:5]])  # the 5 rays of camera 3 take the brute-force path
    d = torch.cat([d1, d2[:200], d3[:5]])
    perm = torch.randperm(o.shape[0], generator=torch.Generator().manual_seed(0))
    got = nb.rays_knn_perpendicular(pts, o[perm], d[perm], 9)
    assert_same(got, ref_perpendicular(pts, o[perm], d[perm], 9))


def test_stray_point_next_to_the_camera():
    """A point almost at the origin makes the search ball huge unless handled apart; results stay exact."""
    pts = scene("sphere", 1200, 4)
    c2w = camera(4)
    o, d = rays(c2w)
    stray = c2w[:3, 3] - 1e-3 * c2w[:3, 2]  # 1 mm in front of the camera
    pts = torch.cat([pts, stray[None], stray[None] + 1e-4])
    assert_same(nb.rays_knn_perpendicular(pts, o, d, 10), ref_perpendicular(pts, o, d, 10))
    q = random_px(500, 4)
    assert_same(nb.screen_knn(pts, c2w, H, W, FOCAL, q, 10, True, max_radius_px=INF),
                ref_screen(pts, c2w, q, 10, True))
    cap = nb.ScreenIndex(pts, c2w, H, W, FOCAL).radius_px(10)
    assert_same(nb.screen_knn(pts, c2w, H, W, FOCAL, q, 10, True), ref_screen(pts, c2w, q, 10, True, cap))


def test_index_reused_across_chunks_equals_one_call():
    pts = scene("blob", 1000, 5)
    c2w = camera(5)
    q = random_px(600, 5)
    for cap in (INF, "auto"):
        index = nb.ScreenIndex(pts, c2w, H, W, FOCAL, depth_factor=True, max_radius_px=cap)
        parts = [index.query(q[i:i + 150], 7) for i in range(0, 600, 150)]
        whole = nb.screen_knn(pts, c2w, H, W, FOCAL, q, 7, depth_factor=True, max_radius_px=cap)
        assert torch.equal(torch.cat([p.idx for p in parts]), whole.idx)
        index.query(q, 3)  # another K (another auto cap) in between changes nothing
        assert torch.equal(index.query(q, 7).idx, whole.idx)
    o, d = rays(c2w)
    pidx = nb.PerpendicularIndex(pts, c2w[:3, 3])
    assert_same(pidx.query(d, 7), ref_perpendicular(pts, o, d, 7))


@pytest.mark.parametrize("method", nb.METHODS)
def test_selector_dispatch(method):
    pts = scene("sphere", 900, 6)
    c2w = camera(6)
    rows, cols = torch.meshgrid(torch.arange(H), torch.arange(W), indexing="ij")
    q = torch.stack([cols.flatten() + 0.5, rows.flatten() + 0.5], -1).float()
    o, d = rays(c2w)  # the rays through those pixels (cameras.pixel_rays)
    cfg = ModelConfig(neighbors=method, k=6)
    assert from_dict(ModelConfig, to_dict(cfg)) == cfg
    got = nb.select_neighbors(pts, cfg.neighbors, cfg.k, c2w, H, W, FOCAL, q, o, d, cfg.neighbor_radius_px)
    if method == "perpendicular":
        want = nb.rays_knn_perpendicular(pts, o, d, 6)
        ref = ref_perpendicular(pts, o, d, 6)
    else:  # default cap: auto
        assert cfg.neighbor_radius_px == 0.0
        want = nb.screen_knn(pts, c2w, H, W, FOCAL, q, 6, depth_factor=method == "screen_depth")
        cap = nb.ScreenIndex(pts, c2w, H, W, FOCAL).radius_px(6)
        ref = ref_screen(pts, c2w, q, 6, method == "screen_depth", cap)
    assert torch.equal(got, want.idx)
    assert_same(want, ref)


# ------------------------------------------------------------------------------------------- degenerate input
# (backend, max_radius_px) of the screen searches; "perpendicular" runs on the k-d tree where the grid is asked
SEARCHES = [("kdtree", INF), ("torch", INF), ("torch", "auto")] + [(g, c) for g in GRIDS for c in ("auto", 2.5)]


def resolved_cap(pts, c2w, k, cap):
    return nb.ScreenIndex(pts, c2w, H, W, FOCAL, max_radius_px=cap).radius_px(k)


def _all_methods(pts, k, search):
    backend, cap = search
    c2w = camera(0)
    o, d = rays(c2w)
    q = random_px(50, 0)
    r = resolved_cap(pts, c2w, k, cap)
    perp = "kdtree" if backend in GRIDS else backend
    return {
        "perpendicular": (nb.rays_knn_perpendicular(pts, o, d, k, backend=perp), ref_perpendicular(pts, o, d, k)),
        "screen": (nb.screen_knn(pts, c2w, H, W, FOCAL, q, k, backend=backend, max_radius_px=cap),
                   ref_screen(pts, c2w, q, k, False, r)),
        "screen_depth": (nb.screen_knn(pts, c2w, H, W, FOCAL, q, k, True, backend=backend, max_radius_px=cap),
                         ref_screen(pts, c2w, q, k, True, r)),
    }


@pytest.mark.stability
@pytest.mark.parametrize("search", SEARCHES)
def test_empty_point_set(search):
    for name, (got, ref) in _all_methods(torch.empty(0, 3), 5, search).items():
        assert got.idx.shape == (got.idx.shape[0], 5), name
        assert not got.valid.any() and torch.isinf(got.dist).all(), name
        assert_same(got, ref)


@pytest.mark.stability
@pytest.mark.parametrize("search", SEARCHES)
def test_k_larger_than_n_pads(search):
    pts = scene("blob", 7, 1) * 0.2
    for name, (got, ref) in _all_methods(pts, 20, search).items():
        assert got.idx.shape[1] == 20
        assert (got.valid.sum(1) <= 7).all() and not got.valid[:, 7:].any(), name
        assert_same(got, ref)


@pytest.mark.stability
@pytest.mark.parametrize("search", SEARCHES)
def test_non_finite_and_diverged_points_are_absent(search):
    pts = scene("blob", 300, 2)
    bad = torch.tensor([[math.nan, 0, 0], [0, math.inf, 0], [-math.inf, 1, 2], [1e30, 1e30, 1e30], [0, 0, -1e30]])
    pts = torch.cat([pts[:150], bad, pts[150:]])
    bad_ids = torch.arange(150, 155)
    for name, (got, ref) in _all_methods(pts, 8, search).items():
        assert not torch.isin(got.idx, bad_ids).any(), name
        assert torch.isfinite(got.dist[got.valid]).all(), name
        assert_same(got, ref)
    only_bad = _all_methods(bad, 3, search)
    assert all(not got.valid.any() for got, _ in only_bad.values())


@pytest.mark.stability
@pytest.mark.parametrize("search", SEARCHES)
def test_everything_behind_the_camera(search):
    c2w = camera(0)
    behind = c2w[:3, 3] + c2w[:3, 2] * 2.0 + 0.3 * torch.randn(100, 3, generator=torch.Generator().manual_seed(0))
    for name, (got, ref) in _all_methods(behind, 4, search).items():
        if name != "perpendicular":  # wide pixel rays may still see a few; the screen path must see none
            assert not got.valid.any(), name
        assert_same(got, ref)


@pytest.mark.stability
@pytest.mark.parametrize("search", SEARCHES)
def test_coincident_points(search):
    pts = torch.zeros(40, 3) + torch.tensor([0.1, -0.2, 0.05])
    for name, (got, ref) in _all_methods(pts, 10, search).items():
        v = got.idx[got.valid].reshape(-1) if got.valid.any() else got.idx[:0]
        assert ((v >= 0) & (v < 40)).all(), name
        rowsorted = got.idx.sort(1).values
        assert not ((rowsorted[:, 1:] == rowsorted[:, :-1]) & (rowsorted[:, 1:] >= 0)).any(), name
        assert torch.allclose(got.dist[got.valid].double(), ref[1][ref[0] >= 0], rtol=1e-4, atol=1e-5), name
        assert torch.equal(got.valid, ref[0] >= 0), name


@pytest.mark.stability
@pytest.mark.parametrize("search", SEARCHES)
def test_bad_rays_and_queries_get_no_neighbours(search):
    backend, cap = search
    pts = scene("blob", 200, 0)
    o, d = rays(camera(0))
    o, d = o[:6].clone(), d[:6].clone()
    d[0] = 0.0
    d[1, 0] = math.nan
    o[2, 1] = math.inf
    got = nb.rays_knn_perpendicular(pts, o, d, 5, backend="kdtree" if backend in GRIDS else backend)
    assert not got.valid[:3].any() and got.valid[3:].all()
    q = torch.tensor([[math.nan, 3.0], [12.0, 12.0], [3.0, -math.inf], [1e6, 5.0], [-1e6, -1e6], [12.5, 11.5]])
    for df in (False, True):
        got = nb.screen_knn(pts, camera(0), H, W, FOCAL, q, 5, df, backend=backend, max_radius_px=cap)
        assert not got.valid[[0, 2]].any() and torch.isfinite(got.dist[[1, 5]]).all()
        far = got.valid[[3, 4]]  # far outside the frame: beyond any cap, but an uncapped search finds the K nearest
        assert bool(far.all()) if cap == INF else not far.any()


DEVICES = ["cpu"] + (["cuda"] if torch.cuda.is_available() else [])


@pytest.mark.parametrize("device", DEVICES)
def test_outputs_follow_the_input_device_and_backends_agree(device):
    dev = torch.device(device)
    pts = scene("sphere", 500, 7)
    c2w = camera(7)
    q = random_px(200, 7)
    a = nb.screen_knn(pts, c2w, H, W, FOCAL, q, 5, True, backend="kdtree", max_radius_px=INF)
    b = nb.screen_knn(pts.to(dev), c2w.to(dev), H, W, FOCAL, q.to(dev), 5, True, backend="torch", max_radius_px=INF)
    c = nb.screen_knn(pts, c2w, H, W, FOCAL, q, 5, True, backend="auto", max_radius_px=-1)
    assert b.idx.device.type == dev.type and b.dist.device.type == dev.type
    assert torch.equal(a.idx, c.idx)
    assert_same(b._replace(idx=b.idx.cpu(), dist=b.dist.cpu()), (a.idx, a.dist.double()))
    cap = resolved_cap(pts, c2w, 5, "auto")
    g = nb.screen_knn(pts.to(dev), c2w.to(dev), H, W, FOCAL, q.to(dev), 5, True)  # auto: the grid
    assert g.idx.device.type == dev.type and g.dist.device.type == dev.type
    assert_same(g._replace(idx=g.idx.cpu(), dist=g.dist.cpu()), ref_screen(pts, c2w, q, 5, True, cap))


# --------------------------------------------------------------------------------------- capped: pixel grid
@pytest.mark.parametrize("cap", ["auto", 1.7, 4.0])
@pytest.mark.parametrize("depth_factor", [False, True])
@pytest.mark.parametrize("kind", ["blob", "sphere", "plane", "line"])
@pytest.mark.parametrize("seed", [0, 1, 2])
def test_grid_matches_capped_brute_force(kind, seed, depth_factor, cap):
    pts = scene(kind, 800, seed)
    c2w = camera(seed)
    q = random_px(700, seed)
    r = resolved_cap(pts, c2w, 12, cap)
    ref = ref_screen(pts, c2w, q, 12, depth_factor, r)
    for backend in GRIDS + ("torch",):
        got = nb.screen_knn(pts, c2w, H, W, FOCAL, q, 12, depth_factor, backend=backend, max_radius_px=cap)
        assert_same(got, ref)


@pytest.mark.parametrize("backend", GRIDS)
@pytest.mark.parametrize("depth_factor", [False, True])
def test_grid_on_a_pixel_grid_of_queries_and_a_large_frame(depth_factor, backend):
    """Every pixel centre of a 96 × 80 frame (most of the work in training and rendering), two stages at work."""
    h, w, f = 80, 96, 90.0
    pts = scene("sphere", 3000, 8) * torch.tensor([1.0, 0.6, 0.8])
    c2w = look_at([2.2, -2.0, 1.0]).float()
    rows, cols = torch.meshgrid(torch.arange(h), torch.arange(w), indexing="ij")
    q = torch.stack([cols.flatten() + 0.5, rows.flatten() + 0.5], -1).float()
    index = nb.ScreenIndex(pts, c2w, h, w, f, depth_factor, backend=backend)
    got = index.query(q, 16)
    p, m = pts.double(), c2w.double()
    cam = (p - m[:3, 3]) @ m[:3, :3]
    z = -cam[:, 2]
    px = torch.stack([f * cam[:, 0] / z + 0.5 * w, -f * cam[:, 1] / z + 0.5 * h], -1)
    d = (q.double()[:, None, :] - px[None]).norm(dim=-1)
    keep = (z > 0)[None] & (d <= index.radius_px(16))
    if depth_factor:
        d = d * (z / f)[None]
    ref = _topk_ref(d.masked_fill(~keep, math.inf), 16)
    assert_same(got, ref)
    assert 0.2 < float(got.valid[:, 0].float().mean()) < 0.9  # object and background both present


@pytest.mark.stability
@pytest.mark.parametrize("backend", GRIDS)
@pytest.mark.parametrize("depth_factor", [False, True])
def test_grid_very_dense_cell_is_exact_and_chunked(depth_factor, backend, monkeypatch):
    """3000 points inside 0.01 px next to a sparse cloud: every query near the clump has thousands of candidates.
    A tiny table budget forces one query per chunk there; results stay exact."""
    g = torch.Generator().manual_seed(9)
    c2w = camera(0)
    sparse = scene("blob", 400, 9)
    centre = sparse[:1]
    clump = centre + 1e-5 * torch.randn(3000, 3, generator=g)
    pts = torch.cat([sparse, clump])
    index = nb.ScreenIndex(pts, c2w, H, W, FOCAL, depth_factor, backend=backend)
    cpx = index.px[index.ids == 0][0].float()
    q = torch.cat([cpx + torch.randn(60, 2, generator=g) * 1.5, random_px(200, 9)])
    monkeypatch.setattr(grid, "_GRID_BUDGET", 256)
    got = index.query(q, 25)
    ref = ref_screen(pts, c2w, q, 25, depth_factor, index.radius_px(25))
    assert_same(got, ref)
    assert int(got.valid.sum(1).max()) == 25


@pytest.mark.stability
@pytest.mark.parametrize("cap", [1e-6, 0.3, 1e6])
def test_grid_extreme_caps(cap):
    pts = scene("sphere", 600, 10)
    c2w = camera(10)
    q = random_px(300, 10)
    for df, backend in itertools.product((False, True), GRIDS):
        got = nb.screen_knn(pts, c2w, H, W, FOCAL, q, 9, df, max_radius_px=cap, backend=backend)
        assert_same(got, ref_screen(pts, c2w, q, 9, df, cap))
        assert torch.isfinite(got.dist[got.valid]).all()
    if cap == 1e6:  # a cap beyond the frame is no cap
        uncapped = nb.screen_knn(pts, c2w, H, W, FOCAL, q, 9, True, max_radius_px=INF)
        assert_same(nb.screen_knn(pts, c2w, H, W, FOCAL, q, 9, True, max_radius_px=cap),
                    (uncapped.idx, uncapped.dist.double()))


def test_grid_fewer_candidates_than_k_pads():
    pts = scene("plane", 150, 11) * 3.0  # sparse: ~0.3 points per pixel
    c2w = camera(11)
    q = random_px(400, 11)
    got = nb.screen_knn(pts, c2w, H, W, FOCAL, q, 30, True, max_radius_px=3.0)
    assert_same(got, ref_screen(pts, c2w, q, 30, True, 3.0))
    n = got.valid.sum(1)
    assert (n < 30).all() and (n > 0).any() and (n == 0).any()


def _lattice(spacing: float, lo: float, hi: float) -> torch.Tensor:
    """Points at depth 2 in front of an identity camera projecting onto a square pixel lattice [lo, hi)²."""
    t = torch.arange(lo, hi, spacing, dtype=torch.float64)
    col, row = torch.meshgrid(t, t, indexing="xy")
    x, y = (col.flatten() - 0.5 * W) / FOCAL, -(row.flatten() - 0.5 * H) / FOCAL
    return torch.stack([x, y, -torch.ones_like(x)], -1) * 2.0


@pytest.mark.parametrize("spacing", [0.25, 0.5, 1.0])
def test_auto_radius_follows_the_projected_density(spacing):
    """A lattice of `spacing` pixels covering half the frame: density 1 / spacing², so the auto cap is 2 × the
    radius of a disc holding K points there (at least 1.5 px), and every interior pixel sees about 4 K points."""
    pts = _lattice(spacing, 4.0, 20.0)
    index = nb.ScreenIndex(pts, torch.eye(4), H, W, FOCAL)
    for k in (4, 20):
        expect = max(1.5, 2.0 * math.sqrt(k * spacing ** 2 / math.pi))
        assert index.radius_px(k) == pytest.approx(expect, rel=0.1)
    assert index.radius_px(20) >= index.radius_px(4)
    centre = index.query(torch.tensor([[12.1, 11.9]]), 20)
    assert bool(centre.valid.all())
    assert nb.ScreenIndex(pts, torch.eye(4), H, W, FOCAL, max_radius_px=2.0).radius_px(20) == 2.0
    assert nb.ScreenIndex(pts, torch.eye(4), H, W, FOCAL, max_radius_px=-1).radius_px(20) == INF


@pytest.mark.stability
@pytest.mark.parametrize("pts", [torch.empty(0, 3), torch.tensor([[0.1, 0.2, -2.0]]), torch.zeros(50, 3) - 2.0])
def test_auto_radius_of_degenerate_clouds_is_finite(pts):
    r = nb.ScreenIndex(pts, torch.eye(4), H, W, FOCAL).radius_px(10)
    assert math.isfinite(r) and r >= 1.5


def test_model_config_cap_round_trips_and_is_used():
    cfg = ModelConfig(neighbors="screen", k=5, neighbor_radius_px=2.0)
    assert from_dict(ModelConfig, to_dict(cfg)) == cfg
    pts, c2w, q = scene("sphere", 700, 12), camera(12), random_px(300, 12)
    o, d = rays_for_pixels(c2w, q, H, W, FOCAL)
    for radius, backend, cap in ((2.0, "auto", 2.0), (-1.0, "kdtree", INF)):  # no cap: the k-d tree
        cfg = ModelConfig(neighbors="screen", k=5, neighbor_radius_px=radius)
        got = nb.select_neighbors(pts, cfg.neighbors, cfg.k, c2w, H, W, FOCAL, q, o, d, cfg.neighbor_radius_px)
        want = nb.screen_knn(pts, c2w, H, W, FOCAL, q, 5, backend=backend, max_radius_px=radius)
        assert torch.equal(got, want.idx)
        assert_same(want, ref_screen(pts, c2w, q, 5, False, cap))
    with pytest.raises(InputError, match="neighbor_radius_px"):
        from_dict(ModelConfig, dict(to_dict(cfg), neighbor_radius_px=-2.0))
    older = {k: v for k, v in to_dict(cfg).items() if k != "neighbor_radius_px"}  # a file from before the setting
    assert from_dict(ModelConfig, older).neighbor_radius_px == 0.0  # auto, as such models were trained


@pytest.mark.parametrize("call, match", [
    (lambda: nb.screen_knn(torch.zeros(5, 2), camera(0), H, W, FOCAL, torch.zeros(3, 2), 4), "points"),
    (lambda: nb.screen_knn(torch.zeros(5, 3), camera(0), H, W, FOCAL, torch.zeros(3, 3), 4), "query_px"),
    (lambda: nb.screen_knn(torch.zeros(5, 3), camera(0), H, W, 0.0, torch.zeros(3, 2), 4), "focal"),
    (lambda: nb.screen_knn(torch.zeros(5, 3), torch.eye(3), H, W, FOCAL, torch.zeros(3, 2), 4), "c2w"),
    (lambda: nb.screen_knn(torch.zeros(5, 3), camera(0), H, W, FOCAL, torch.zeros(3, 2), 0), "k must"),
    (lambda: nb.rays_knn_perpendicular(torch.zeros(5, 3), torch.zeros(4, 3), torch.ones(3, 3), 2), "differ"),
    (lambda: nb.select_neighbors(torch.zeros(5, 3), "nearest", 4, camera(0), H, W, FOCAL, torch.zeros(3, 2),
                                 torch.zeros(3, 3), torch.ones(3, 3)), "method"),
    (lambda: nb.rays_knn_perpendicular(torch.zeros(5, 3), torch.zeros(4, 3), torch.ones(4, 3), 2, "gpu"),
     "backend"),
    (lambda: nb.rays_knn_perpendicular(torch.zeros(5, 3), torch.zeros(4, 3), torch.ones(4, 3), 2, "grid"),
     "grid"),
    (lambda: nb.screen_knn(torch.zeros(5, 3), camera(0), H, W, FOCAL, torch.zeros(3, 2), 4, max_radius_px="big"),
     "max_radius_px"),
    (lambda: nb.screen_knn(torch.zeros(5, 3), camera(0), H, W, FOCAL, torch.zeros(3, 2), 4, max_radius_px=math.nan),
     "max_radius_px"),
    (lambda: nb.screen_knn(torch.zeros(5, 3), camera(0), H, W, FOCAL, torch.zeros(3, 2), 4, backend="kdtree"),
     "kdtree"),
    (lambda: nb.screen_knn(torch.zeros(5, 3), camera(0), H, W, FOCAL, torch.zeros(3, 2), 4, backend="grid",
                           max_radius_px=INF), "grid"),
    (lambda: nb.screen_knn(torch.zeros(5, 3), camera(0), H, W, FOCAL, torch.zeros(3, 2), 4, backend="compiled",
                           max_radius_px=INF), "compiled"),
    (lambda: nb.rays_knn_perpendicular(torch.zeros(5, 3), torch.zeros(4, 3), torch.ones(4, 3), 2, "compiled"),
     "compiled"),
])
def test_bad_input_is_a_clear_error(call, match):
    with pytest.raises(InputError, match=match):
        call()


# ------------------------------------------------------------------ general intrinsics: non-square, off-centre
def ref_screen_k(points, c2w, k_cam, h, w, query_px, k, depth_factor):
    """Brute force written from the pinhole formula with fx, fy, cx, cy (not through cameras.project_points)."""
    p, m = points.double(), c2w.double()
    cam = (p - m[:3, 3]) @ m[:3, :3]
    z = -cam[:, 2]
    col = k_cam.fx * cam[:, 0] / z + k_cam.cx
    row = -k_cam.fy * cam[:, 1] / z + k_cam.cy
    keep = (z > 0) & (col >= -1) & (col <= w + 1) & (row >= -1) & (row <= h + 1) & ~_absent(points)
    d = (query_px.double()[:, None, :] - torch.stack([col, row], -1)[None]).norm(dim=-1)
    if depth_factor:
        d = d * (z / math.sqrt(k_cam.fx * k_cam.fy))[None]
    return _topk_ref(d.masked_fill(~keep[None] | ~torch.isfinite(d), math.inf), k)


@pytest.mark.parametrize("method", nb.METHODS)
def test_intrinsics_non_square_off_centre_match_brute_force(method):
    from core.images.cameras import Intrinsics

    h, w = 18, 31
    k_cam = Intrinsics(1.3 * w, 0.9 * w, 0.62 * w, 0.35 * h)
    pts, c2w = scene("blob", 700, 9), camera(9)
    rows, cols = torch.meshgrid(torch.arange(h), torch.arange(w), indexing="ij")
    q = torch.stack([cols.flatten() + 0.5, rows.flatten() + 0.5], -1).float()
    if method == "perpendicular":
        o32, d32 = pixel_rays(c2w, h, w, k_cam)
        got = nb.rays_knn_perpendicular(pts, o32.reshape(-1, 3), d32.reshape(-1, 3), 5)
    else:  # uncapped: the reference has no cap
        got = nb.screen_knn(pts, c2w, h, w, k_cam, q, 5, depth_factor=method == "screen_depth", max_radius_px=-1.0)
    if method == "perpendicular":
        o, d = pixel_rays(c2w.double(), h, w, k_cam)
        ref = ref_perpendicular(pts, o.reshape(-1, 3), d.reshape(-1, 3), 5)
    else:
        ref = ref_screen_k(pts, c2w, k_cam, h, w, q, 5, method == "screen_depth")
    assert_same(got, ref)


@pytest.mark.parametrize("method", ["screen", "screen_depth"])
@pytest.mark.parametrize("scale", [1.0, 1.7])
def test_a_shared_screen_index_searches_as_select_neighbors_does(method, scale):
    """screen_index (the index a second search of some rays reuses): queried with K it gives select_neighbors'
    answer; queried with 2K for the same rays its first K are those, and all 2K lie within the K search's cap."""
    from core.points.neighbors.select import screen_index

    pts, c2w, q = scene("sphere", 700, 4), camera(4), random_px(300, 4)
    o, d = rays_for_pixels(c2w, q, H, W, FOCAL)
    want = nb.select_neighbors(pts, method, 6, c2w, H, W, FOCAL, q, o, d, "auto", radius_scale=scale)
    index = screen_index(pts, method, 6, c2w, H, W, FOCAL, "auto", radius_scale=scale)
    got = nb.select_neighbors(pts, method, 6, c2w, H, W, FOCAL, q, o, d, index=index)
    assert torch.equal(got, want) and int((got >= 0).sum()) > 300
    more = index.query(q, 12).idx
    assert torch.equal(more[:, :6], want)
    cap = nb.ScreenIndex(pts, c2w, H, W, FOCAL).radius_px(6) * scale
    from core.images.cameras import project_points
    px, _ = project_points(pts.double(), c2w.double(), H, W, FOCAL)
    far = (px[more.clamp_min(0)] - q.double()[:, None]).norm(dim=-1)
    assert bool((far[more >= 0] <= cap + 1e-6).all())
    assert nb.select_neighbors is not None and screen_index(pts, "perpendicular", 6, c2w, H, W, FOCAL) is None


def ref_screen_reach(points, c2w, query_px, k, depth_factor, cap, reach):
    """ref_screen with a per-point cap: point n is a candidate within cap × reach[n] pixels."""
    return ref_screen(points, c2w, query_px, k, depth_factor, cap * reach.double()[None])


@pytest.mark.skipif(not compiled.available(), reason="the per-point reach is applied by the compiled grid")
@pytest.mark.parametrize("depth_factor", [False, True])
@pytest.mark.parametrize("kind", ["blob", "plane"])
@pytest.mark.parametrize("seed", [0, 1])
def test_compiled_grid_per_point_reach_matches_brute_force(kind, seed, depth_factor):
    """reach [N]: each point is a candidate within the cap × its own reach (cells still sized by the cap); all ones
    is the plain capped search bit for bit; the other backends use the cap × the largest reach for every point."""
    pts = scene(kind, 800, seed)
    c2w = camera(seed)
    q = random_px(600, seed)
    g = torch.Generator().manual_seed(seed + 10)
    reach = torch.where(torch.rand(800, generator=g) < 0.3, 1.0 + 4.0 * torch.rand(800, generator=g),
                        torch.ones(800))
    reach[::97] = float("nan")  # a non-finite reach counts as 1
    plain = nb.ScreenIndex(pts, c2w, H, W, FOCAL, depth_factor, backend="compiled")
    cap = plain.radius_px(12)
    index = nb.ScreenIndex(pts, c2w, H, W, FOCAL, depth_factor, backend="compiled", reach=reach)
    assert index.radius_px(12) == cap
    got = index.query(q, 12)
    ref = ref_screen_reach(pts, c2w, q, 12, depth_factor, cap, torch.nan_to_num(reach, nan=1.0))
    assert_same(got, ref)
    assert not torch.equal(got.idx, plain.query(q, 12).idx)  # the reach mattered somewhere
    ones = nb.ScreenIndex(pts, c2w, H, W, FOCAL, depth_factor, backend="compiled", reach=torch.ones(800))
    a, b = ones.query(q, 12), plain.query(q, 12)
    assert torch.equal(a.idx, b.idx) and torch.equal(a.dist, b.dist)
    big = float(torch.nan_to_num(reach, nan=1.0).max())
    uniform = nb.ScreenIndex(pts, c2w, H, W, FOCAL, depth_factor, backend="grid", reach=reach)
    assert_same(uniform.query(q, 12), ref_screen(pts, c2w, q, 12, depth_factor, cap * big))


@pytest.mark.stability
def test_reach_input_checks_and_hostile_values():
    pts = scene("blob", 200, 3)
    c2w = camera(3)
    with pytest.raises(InputError):
        nb.ScreenIndex(pts, c2w, H, W, FOCAL, True, reach=torch.ones(199))
    wild = torch.full((200,), float("inf"))
    wild[::2] = -5.0  # below 1: raised to 1
    index = nb.ScreenIndex(pts, c2w, H, W, FOCAL, True, reach=wild)
    assert index.reach is None  # nothing above 1 is left: the plain search
    got = index.query(random_px(50, 3), 8)
    assert torch.isfinite(got.dist[got.valid]).all()
    far = torch.full((200,), 3.0)
    q = random_px(50, 3)
    open_ = nb.ScreenIndex(pts, c2w, H, W, FOCAL, True, reach=far).query(q, 8)
    for gate in (float("nan"), float("inf"), -1.0, 0.0):  # no gate
        idx = nb.ScreenIndex(pts, c2w, H, W, FOCAL, True, reach=far, reach_gate=gate)
        assert idx.reach_gate == 0.0 and torch.equal(idx.query(q, 8).idx, open_.idx)
    huge = nb.ScreenIndex(pts, c2w, H, W, FOCAL, True, reach=far, reach_gate=1e12).query(q, 8)
    assert torch.equal(huge.idx, open_.idx)  # a gate wider than every reach gates nothing
    corners = torch.tensor([[0.5, 0.5], [W - 0.5, H - 0.5], [-40.0, -40.0], [W + 40.0, 5.0]])
    for r, g in ((1e6, 1e12), (1e12, 0.0)):  # empty queries stop at the grid's edge, however far the reach
        got = nb.ScreenIndex(pts[:3], c2w, H, W, FOCAL, True, reach=torch.full((3,), r),
                             reach_gate=g).query(corners, 4)
        assert got.idx.shape == (4, 4) and torch.isfinite(got.dist[got.valid]).all()


def _gated(ref, plain):
    """ref's rows emptied where the capped search `plain` (the gate's radius) found no candidate."""
    idx, dist = ref
    near = (plain[0] >= 0).any(1, keepdim=True)
    return torch.where(near, idx, -1), torch.where(near, dist, math.inf)


def _reach_case(backend: str, seed: int, reach_seed: int, spread: float, share: float = 0.5):
    """A reach test's inputs: (points [800, 3] of the blob scene, camera, 600 query pixels, reach [800]: a share of
    the points reach 1 + spread × U(0, 1), the others 1); skips the compiled backend where numba is missing."""
    if backend == "compiled" and not compiled.available():
        pytest.skip("numba missing")
    g = torch.Generator().manual_seed(reach_seed)
    reach = torch.where(torch.rand(800, generator=g) < share, 1.0 + spread * torch.rand(800, generator=g),
                        torch.ones(800))
    return scene("blob", 800, seed), camera(seed), random_px(600, seed), reach


@pytest.mark.parametrize("backend", ["compiled", "grid", "torch"])
@pytest.mark.parametrize("depth_factor", [False, True])
@pytest.mark.parametrize("most", [False, True])
@pytest.mark.parametrize("gate", [1.0, 2.5])
def test_reach_gate_keeps_rays_without_a_plain_candidate_empty(backend, depth_factor, most, gate):
    """reach_gate: a query with no point within gate × the plain cap gets no neighbours, the others the reach
    search's answer (compiled: per point; the one-cap backends: the cap × the largest reach). most: nearly every
    point reaches far (the compiled grid then sizes its cells by the median reach; the answer must not change)."""
    pts, c2w, q, reach = _reach_case(backend, 5, 15, 4.0, share=0.95 if most else 0.3)
    plain = nb.ScreenIndex(pts, c2w, H, W, FOCAL, depth_factor, backend=backend)
    cap = plain.radius_px(12)
    index = nb.ScreenIndex(pts, c2w, H, W, FOCAL, depth_factor, backend=backend, reach=reach, reach_gate=gate)
    got = index.query(q, 12)
    per_point = cap * (reach if backend == "compiled" else torch.full_like(reach, float(reach.max())))
    ref = _gated(ref_screen(pts, c2w, q, 12, depth_factor, per_point.double()[None]),
                 ref_screen(pts, c2w, q, 12, depth_factor, cap * gate))
    assert_same(got, ref)
    open_ = nb.ScreenIndex(pts, c2w, H, W, FOCAL, depth_factor, backend=backend, reach=reach).query(q, 12)
    assert_same(open_, ref_screen(pts, c2w, q, 12, depth_factor, per_point.double()[None]))
    shut = (got.idx < 0).all(1)
    assert bool(shut.any()) and bool(((open_.idx >= 0).any(1) & shut).any())  # the gate emptied some rays
    kept = ~shut
    assert torch.equal(got.idx[kept], open_.idx[kept])  # the others are the plain reach search's


def _surrounded_ref(offsets, valid):
    """Brute force: offsets [R, M, 2] to the candidates (valid [R, M]) surround the query when, of the 45° sectors
    around it, no three in a row (around the turn) are empty."""
    deg = torch.rad2deg(torch.atan2(offsets[..., 1].double(), offsets[..., 0].double()))
    sector = torch.floor(deg / 45.0).long() % 8
    out = torch.zeros(offsets.shape[0], dtype=torch.bool)
    for r in range(offsets.shape[0]):
        full = set(sector[r][valid[r]].tolist())
        out[r] = all(any((s + t) % 8 in full for t in range(3)) for s in range(8))
    return out


def _projected(pts, c2w):
    """pixel positions [N, 2] of the points, NaN for those the search leaves out (as ref_screen)."""
    p, m = pts.double(), c2w.double()
    cam = (p - m[:3, 3]) @ m[:3, :3]
    z = -cam[:, 2]
    px = torch.stack([FOCAL * cam[:, 0] / z + 0.5 * W, -FOCAL * cam[:, 1] / z + 0.5 * H], -1)
    keep = (z > 0) & (px[:, 0] >= -1) & (px[:, 0] <= W + 1) & (px[:, 1] >= -1) & (px[:, 1] <= H + 1) & ~_absent(pts)
    return torch.where(keep[:, None], px, math.nan)


@pytest.mark.parametrize("backend", ["compiled", "grid", "torch"])
@pytest.mark.parametrize("depth_factor", [False, True])
def test_reach_surround_lets_through_rays_their_neighbours_surround(backend, depth_factor):
    """reach_surround: of the rays the gate empties, those whose candidates (every point within its reach of the
    ray) surround them (brute force here) keep their K reach neighbours; every other row is the gated search's."""
    pts, c2w, q, reach = _reach_case(backend, 5, 16, 4.0)
    cap = nb.ScreenIndex(pts, c2w, H, W, FOCAL, depth_factor, backend=backend).radius_px(8)
    per_point = cap * (reach if backend == "compiled" else torch.full_like(reach, float(reach.max())))
    open_ = ref_screen(pts, c2w, q, 8, depth_factor, per_point.double()[None])
    near = (ref_screen(pts, c2w, q, 8, depth_factor, cap)[0] >= 0).any(1)
    px = _projected(pts, c2w)
    off = px[None] - q.double()[:, None]
    inside = _surrounded_ref(off, (off.norm(dim=-1) <= per_point.double()[None]) & torch.isfinite(off).all(-1))
    keep = (near | inside)[:, None]
    ref = torch.where(keep, open_[0], -1), torch.where(keep, open_[1], math.inf)
    index = nb.ScreenIndex(pts, c2w, H, W, FOCAL, depth_factor, backend=backend, reach=reach, reach_gate=1.0,
                           reach_surround=True)
    assert_same(index.query(q, 8), ref)
    assert bool((inside & ~near).any()) and bool(((open_[0] >= 0).any(1) & ~near & ~inside).any())
    ungated = nb.ScreenIndex(pts, c2w, H, W, FOCAL, depth_factor, backend=backend, reach=reach, reach_surround=True)
    assert not ungated.reach_surround  # without a gate the switch does nothing: the open search
    assert_same(ungated.query(q, 8), open_)


def test_reach_surround_fills_a_hole_but_not_the_outline():
    """A sheet facing the camera, points 2 px apart, with a hole of radius 3 px; cap 1.5 px, reach 4: the gate
    empties the hole's centre and rays 3 px outside the sheet's edge; surround gives the hole its neighbours
    (candidates all around it), never the rays outside; hostile positions stay finite."""
    c2w = torch.eye(4)
    col, row = torch.meshgrid(torch.arange(4.0, 21.0, 2.0), torch.arange(4.0, 21.0, 2.0), indexing="xy")
    keep = ((col - 12) ** 2 + (row - 12) ** 2) > 9
    col, row = col[keep], row[keep]
    z = 2.0
    pts = torch.stack([(col - 0.5 * W) * z / FOCAL, -(row - 0.5 * H) * z / FOCAL, torch.full_like(col, -z)], 1)
    reach = torch.full((pts.shape[0],), 4.0)
    q = torch.tensor([[12.0, 12.0], [12.0, 1.0], [23.5, 12.0], [8.0, 8.0]])  # hole, above, right edge, on the sheet
    out = {}
    for surround in (False, True):
        index = nb.ScreenIndex(pts, c2w, H, W, FOCAL, True, max_radius_px=1.5, reach=reach, reach_gate=1.0,
                               reach_surround=surround)
        out[surround] = index.query(q, 8)
    assert bool((out[False].idx[:3] < 0).all()) and bool((out[False].idx[3] >= 0).all())
    assert bool((out[True].idx[0] >= 0).all()) and bool((out[True].idx[1:3] < 0).all())
    assert torch.equal(out[True].idx[3], out[False].idx[3])
    wild = pts.clone()
    wild[::5] = float("nan")
    wild[1::7] = 1e30
    far = torch.full((pts.shape[0],), 1e9)
    far[::3] = float("nan")
    for gate, own in ((1.0, False), (1e12, True), (2.0, True)):
        got = nb.ScreenIndex(wild, c2w, H, W, FOCAL, True, max_radius_px=1.5, reach=far, reach_gate=gate,
                             reach_surround=True, reach_gate_own=own).query(random_px(50, 3), 8)
        assert torch.isfinite(got.dist[got.valid]).all()


@pytest.mark.parametrize("backend", ["compiled", "grid", "torch"])
@pytest.mark.parametrize("depth_factor", [False, True])
@pytest.mark.parametrize("gate", [1.5, 2.5])
def test_reach_gate_own_gates_each_point_at_most_at_its_reach(backend, depth_factor, gate):
    """reach_gate_own: a query keeps the reach search's neighbours when some point lies within the cap × min(gate,
    that point's reach) of it (brute force here), else none; points of reach 1 gate at the plain cap."""
    pts, c2w, q, reach = _reach_case(backend, 6, 17, 3.0)
    cap = nb.ScreenIndex(pts, c2w, H, W, FOCAL, depth_factor, backend=backend).radius_px(8)
    per_point = cap * (reach if backend == "compiled" else torch.full_like(reach, float(reach.max())))
    open_ = ref_screen(pts, c2w, q, 8, depth_factor, per_point.double()[None])
    d = (_projected(pts, c2w)[None] - q.double()[:, None]).norm(dim=-1)
    near = (d <= (cap * reach.clamp_max(gate)).double()[None]).any(1, keepdim=True)
    ref = torch.where(near, open_[0], -1), torch.where(near, open_[1], math.inf)
    got = nb.ScreenIndex(pts, c2w, H, W, FOCAL, depth_factor, backend=backend, reach=reach, reach_gate=gate,
                         reach_gate_own=True).query(q, 8)
    assert_same(got, ref)
    wide = ref_screen(pts, c2w, q, 8, depth_factor, cap * gate)
    plain = ref_screen(pts, c2w, q, 8, depth_factor, cap)
    assert bool(((wide[0] >= 0).any(1) & ~near[:, 0]).any())  # the own-reach gate is narrower than gate × cap ...
    assert bool((near[:, 0] & ~(plain[0] >= 0).any(1)).any())  # ... and wider than the plain cap


@pytest.mark.parametrize("backend", ["compiled", "grid", "torch"])
@pytest.mark.parametrize("own", [False, True])
@pytest.mark.parametrize("gate", [1.5, 2.0])
def test_reach_between_opens_the_gate_only_between_points(backend, own, gate):
    """reach_between: a query keeps the reach search's neighbours when a point lies within the plain cap, or two
    points within the gate (gate × cap; with own at most each one's reach) lie more than 120° apart as seen from
    it (brute force here); else none."""
    pts, c2w, q, reach = _reach_case(backend, 7, 18, 3.0)
    cap = nb.ScreenIndex(pts, c2w, H, W, FOCAL, True, backend=backend).radius_px(8)
    per_point = cap * (reach if backend == "compiled" else torch.full_like(reach, float(reach.max())))
    open_ = ref_screen(pts, c2w, q, 8, True, per_point.double()[None])
    off = _projected(pts, c2w)[None] - q.double()[:, None]
    d = off.norm(dim=-1)
    radius = cap * (reach.clamp_max(gate) if own else torch.full_like(reach, gate))
    within = d <= radius.double()[None]
    near = (d <= cap).any(1)
    for r in range(q.shape[0]):
        u = off[r][within[r]] / d[r][within[r]][:, None]
        near[r] |= bool(((u @ u.T) < -0.5).any())
    ref = torch.where(near[:, None], open_[0], -1), torch.where(near[:, None], open_[1], math.inf)
    got = nb.ScreenIndex(pts, c2w, H, W, FOCAL, True, backend=backend, reach=reach, reach_gate=gate,
                         reach_gate_own=own, reach_between=True).query(q, 8)
    assert_same(got, ref)
    plain = (ref_screen(pts, c2w, q, 8, True, cap)[0] >= 0).any(1)
    assert bool((within.any(1) & ~near).any())  # the gate kept some rays with points within it shut ...
    assert own or bool((near & ~plain).any())  # ... and opened some beyond the plain cap


def _depths(points, c2w):
    """Camera depth of each point (> 0 in front), as ref_screen computes it."""
    p, m = points.double(), c2w.double()
    return -((p - m[:3, 3]) @ m[:3, :3])[:, 2]


@pytest.mark.parametrize("backend", ["compiled", "grid", "torch"])
@pytest.mark.parametrize("between", [False, True])
@pytest.mark.parametrize("persp", [2.0, 4.0])
def test_reach_perspective_matches_brute_force(backend, between, persp):
    """reach_perspective: a reaching point (reach > 1) nearer than the median candidate reaches, gates and (with
    between) counts as within the plain cap farther by median depth / its depth, at most persp (brute force
    here; the backends without per-point reach search the largest reach for every point); points of reach 1 and
    points beyond the median keep their cap."""
    pts, c2w, q, reach = _reach_case(backend, 9, 19, 2.0)
    gate = 1.5
    cap = nb.ScreenIndex(pts, c2w, H, W, FOCAL, True).radius_px(8)
    px = _projected(pts, c2w)
    z = _depths(pts, c2w)
    inside = torch.isfinite(px).all(1)  # the candidates (_projected leaves the others NaN)
    ratio = (z[inside].median() / z).clamp(1.0, persp)
    ratio = torch.where(reach.double() > 1.0, ratio, torch.ones_like(ratio))
    per_point = cap * reach.double() * ratio
    if backend != "compiled":
        per_point = torch.full_like(per_point, float(per_point[inside].max()))  # the largest of the candidates
    open_ = ref_screen(pts, c2w, q, 8, True, per_point[None])
    off = px[None] - q.double()[:, None]
    d = off.norm(dim=-1)
    within = d <= (cap * gate * ratio)[None]
    near = (d <= (cap * ratio)[None]).any(1) if between else within.any(1)
    if between:
        for r in range(q.shape[0]):
            u = off[r][within[r]] / d[r][within[r]][:, None]
            near[r] |= bool(((u @ u.T) < -0.5).any())
    ref = torch.where(near[:, None], open_[0], -1), torch.where(near[:, None], open_[1], math.inf)
    index = nb.ScreenIndex(pts, c2w, H, W, FOCAL, True, backend=backend, reach=reach, reach_gate=gate,
                           reach_between=between, reach_perspective=persp)
    assert_same(index.query(q, 8), ref)
    assert index.perspective is not None and 1.0 < float(index.perspective.max()) <= persp
    plain = nb.ScreenIndex(pts, c2w, H, W, FOCAL, True, backend=backend, reach=reach, reach_gate=gate,
                           reach_between=between)
    assert plain.perspective is None
    assert bool(((index.query(q, 8).idx >= 0).any(1) & ~(plain.query(q, 8).idx >= 0).any(1)).any())  # it reaches


@pytest.mark.parametrize("backend", ["compiled", "grid", "torch"])
def test_reach_perspective_fills_a_near_stretched_part(backend):
    """A floor receding from the camera, its points 0.5 apart in the world (so farther apart on the screen where
    it is nearer: 8.8 px at its near edge, 2.2 at its far one), every point reaching 1.2 caps: without the
    perspective factor its near rows have rays without neighbours between the points; with it (at most 4) none;
    factors <= 1, no reach or hostile positions change nothing or stay finite."""
    if backend == "compiled" and not compiled.available():
        pytest.skip("numba missing")
    x, zz = torch.meshgrid(torch.arange(-3.0, 3.0001, 0.5), torch.arange(-6.0, -1.4999, 0.5), indexing="xy")
    pts = torch.stack([x.reshape(-1), torch.full((x.numel(),), -0.6), zz.reshape(-1)], 1)
    c2w = torch.eye(4)
    reach = torch.full((pts.shape[0],), 1.2)
    qr, qc = torch.meshgrid(torch.arange(H, dtype=torch.float32), torch.arange(W, dtype=torch.float32),
                            indexing="ij")
    q = torch.stack([qc.reshape(-1) + 0.5, qr.reshape(-1) + 0.5], 1)
    rows = _projected(pts, c2w)[:, 1]
    rows = rows[torch.isfinite(rows)]
    on_floor = (q[:, 1] >= float(rows.min()) + 1) & (q[:, 1] <= float(rows.max()) - 1) & (q[:, 0] >= 1) \
        & (q[:, 0] <= W - 1)
    empty = {}
    for persp in (0.0, 1.0, 4.0):
        idx = nb.ScreenIndex(pts, c2w, H, W, FOCAL, True, backend=backend, max_radius_px=1.5, reach=reach,
                             reach_gate=1.5, reach_perspective=persp).query(q, 8).idx
        empty[persp] = int(((idx < 0).all(1) & on_floor).sum())
    assert empty[0.0] > 0 and empty[1.0] == empty[0.0] and empty[4.0] == 0
    ones = nb.ScreenIndex(pts, c2w, H, W, FOCAL, True, backend=backend, max_radius_px=1.5, reach=torch.ones(
        pts.shape[0]), reach_gate=1.5, reach_perspective=4.0)
    assert ones.perspective is None  # nothing reaches: nothing widens
    wild = pts.clone()
    wild[::5] = float("nan")
    wild[1::7] = 1e30
    got = nb.ScreenIndex(wild, c2w, H, W, FOCAL, True, backend=backend, max_radius_px=1.5, reach=reach,
                         reach_gate=1.5, reach_perspective=1e6).query(q, 8)
    assert torch.isfinite(got.dist[got.valid]).all()
