"""Atlas object: shapes, serialisation round trip, texel-map layout, and (with a quick fit) the checkerboard bake."""
import numpy as np
import pytest
import torch

from core.atlas.atlas import Atlas
from core.atlas.config import AtlasConfig
from core.atlas.fit import choose_chart_count, fit_atlas
from core.atlas.synthetic import synthetic_samples
from core.util.errors import InputError, ModelFileError

# quick fits of the mechanisms: without the default normal-flatness term and side split, which fold more texels on
# a 400-step map (the defaults are measured on the scene library, docs/atlas.md)
QUICK = dict(steps=400, texture_steps=60, batch=256, uv_batch=64, distortion_batch=64, width_map=48, depth_map=2,
             width_chart=32, depth_chart=2, texture_res=32, log_every=100, eval_samples=1024, charts="4", device="cpu",
             w_normal=0.0, island_sides=False)


@pytest.fixture(scope="module")
def strip_fit():
    xyz, rgb = synthetic_samples("strip", 6000, seed=1)
    threads = torch.get_num_threads()
    torch.set_num_threads(1)  # small matrices: one thread is several times faster on a busy machine
    try:
        atlas, hist = fit_atlas(xyz, rgb, AtlasConfig(**{**QUICK, "layout": "islands"}), quiet=True)
    finally:
        torch.set_num_threads(threads)
    return atlas, hist, xyz, rgb


@pytest.fixture(scope="module")
def strip_fit_grid():
    xyz, rgb = synthetic_samples("strip", 6000, seed=1)
    threads = torch.get_num_threads()
    torch.set_num_threads(1)
    try:
        atlas, hist = fit_atlas(xyz, rgb, AtlasConfig(**QUICK, layout="grid"), quiet=True)
    finally:
        torch.set_num_threads(threads)
    return atlas, hist, xyz, rgb


def _random_atlas(n=4, R=16, pad=2):
    torch.manual_seed(0)
    a = Atlas(n, R, pad, torch.tensor([0.1, 0.2, 0.3]), 0.9, width_chart=16, depth_chart=1, width_map=16, depth_map=1)
    with torch.no_grad():
        a.textures.uniform_(0, 1)
    return a


def test_lookup_and_query_shapes():
    a = _random_atlas()
    x = torch.randn(37, 3)
    probs, uv = a.chart_uv(x)
    assert probs.shape == (37, 4) and uv.shape == (37, 4, 2)
    assert torch.allclose(probs.sum(-1), torch.ones(37))
    assert a.lookup(x).shape == (37, 3)
    assert a.lookup(np.zeros((0, 3), np.float32)).shape == (0, 3)
    chart, pix = a.atlas_pixel_coords(x)
    assert chart.shape == (37,) and pix.shape == (37, 2)
    H, W = a.layout.shape
    assert a.packed_image().shape == (H, W, 3) and a.texel_points().shape == (H, W, 3)


def test_lookup_with_the_packed_image_equals_fitted_lookup_and_sees_edits():
    a = _random_atlas()
    x = torch.randn(50, 3)
    img = a.packed_image()
    assert torch.equal(a.lookup(x, img), a.lookup(x))
    edited = torch.zeros_like(img)  # paint everything black
    assert torch.equal(a.lookup(x, edited.numpy()), torch.zeros(50, 3))


def test_bad_inputs_raise_clear_errors():
    a = _random_atlas()
    with pytest.raises(InputError, match=r"\[M, 3\]"):
        a.lookup(torch.zeros(5, 2))
    with pytest.raises(InputError, match="NaN"):
        a.lookup(torch.full((2, 3), float("nan")))
    with pytest.raises(InputError, match="expected an image"):
        a.lookup(torch.zeros(3, 3), image=torch.zeros(10, 10, 3))


def test_round_trip_through_arrays_is_exact(strip_fit):
    a = strip_fit[0]
    arrays, meta = a.to_arrays(), a.meta()
    ints = ("atlas/islands/grid", "atlas/islands/cell_boxes", "atlas/islands/cell_crops", "atlas/islands/offset",
            "atlas/islands/orient", "atlas/pieces/sub", "atlas/pieces/piece", "atlas/pieces/first")
    assert all(k.startswith("atlas/") and v.dtype == (np.int32 if k in ints else np.float32) for k, v in arrays.items())
    assert meta["layout"] == "islands" and a.islands
    assert arrays["atlas/image"].shape == (*a.layout.shape, 3)
    import json
    b = Atlas.from_arrays({k: v.copy() for k, v in arrays.items()}, json.loads(json.dumps(meta)), "cpu")
    assert torch.equal(b.textures, a.textures)
    assert torch.equal(b.packed_image(), a.packed_image())
    assert np.array_equal(b.texel_points().numpy(), a.texel_points().numpy(), equal_nan=True)
    x = strip_fit[2][:500]
    assert torch.equal(b.lookup(x), a.lookup(x))
    assert a.bake_samples is not None and torch.equal(b.bake_samples, a.bake_samples)
    assert b.bake_sigma == a.bake_sigma == AtlasConfig().texture_sigma
    # files written before the samples were stored load without them (bake falls back to the texel map)
    old = Atlas.from_arrays({k: v for k, v in arrays.items() if k != "atlas/bake_samples"},
                            {k: v for k, v in meta.items() if k != "bake_sigma"}, "cpu")
    assert old.bake_samples is None and torch.equal(old.packed_image(), a.packed_image())


def test_from_arrays_rejects_missing_or_misshaped_arrays():
    a = _random_atlas()
    arrays, meta = a.to_arrays(), a.meta()
    broken = dict(arrays)
    del broken["atlas/net/tex.mlp.0.weight"]
    with pytest.raises(ModelFileError, match="tex.mlp.0.weight"):
        Atlas.from_arrays(broken, meta)
    broken = dict(arrays, **{"atlas/image": arrays["atlas/image"][:-1]})
    with pytest.raises(ModelFileError, match="atlas/image"):
        Atlas.from_arrays(broken, meta)
    with pytest.raises(ModelFileError, match="version"):
        Atlas.from_arrays(arrays, dict(meta, version=99))
    for bad in (np.zeros((5, 2), np.float32), np.full((5, 3), np.nan, np.float32)):
        with pytest.raises(ModelFileError, match="bake_samples"):
            Atlas.from_arrays(dict(arrays, **{"atlas/bake_samples": bad}), meta)
    with pytest.raises(ModelFileError, match="bake_sigma"):
        Atlas.from_arrays(dict(arrays, **{"atlas/bake_samples": np.zeros((5, 3), np.float32)}),
                          dict(meta, bake_sigma="x"))


def test_texel_map_layout(strip_fit):
    a = strip_fit[0]
    tp = a.texel_points()
    L = a.layout
    assert tp.shape == (*L.shape, 3)
    finite = torch.isfinite(tp)
    assert torch.equal(finite.all(-1), finite.any(-1))  # a texel is all-NaN or all-finite
    inside = torch.zeros(L.shape, dtype=torch.bool)
    for c in range(L.n):
        r0, c0 = L.origin(c)
        inside[r0:r0 + L.R, c0:c0 + L.R] = True
    assert not finite.all(-1)[~inside].any()  # padding never has a surface point
    # where the samples land, the texel map mostly has a surface point
    _, pix = a.atlas_pixel_coords(strip_fit[2])
    at_samples = finite.all(-1)[pix[:, 1].long(), pix[:, 0].long()].float().mean()
    assert at_samples > 0.5, f"only {at_samples:.2f} of the sample texels have a surface point"
    # valid texel points lie near the strip (the NaN rule drops far ones)
    pts = tp[finite.all(-1)]
    d = torch.cdist(pts, strip_fit[2]).min(dim=1).values
    assert d.max() < 3.0 * strip_fit[1]["spacing"] + 1e-6


def test_checkerboard_baked_through_texel_map_is_reproduced(strip_fit):
    a, hist, xyz, _ = strip_fit
    cell = 0.5

    def checker(p):
        k = torch.floor(p / cell).long().sum(-1) % 2
        return torch.stack([k.float(), 1 - k.float(), torch.full_like(k.float(), 0.5)], -1)

    tp = a.texel_points()
    ok = torch.isfinite(tp).all(-1)
    img = a.packed_image().clone()
    img[ok] = checker(tp[ok])
    # samples away from cell borders, and handled by their chart with confidence
    frac = (xyz / cell) - torch.floor(xyz / cell)
    away = ((frac > 0.2) & (frac < 0.8)).all(-1)
    probs, _ = a.chart_uv(xyz)
    # only samples whose bilinear footprint lies on baked (valid) texels: the bake defines nothing elsewhere
    _, pix = a.atlas_pixel_coords(xyz)
    r, c = pix[:, 1].long(), pix[:, 0].long()
    H, W = ok.shape
    baked = torch.ones(len(xyz), dtype=torch.bool)
    for dr in (-1, 0, 1):
        for dc in (-1, 0, 1):
            baked &= ok[(r + dr).clamp(0, H - 1), (c + dc).clamp(0, W - 1)]
    x = xyz[away & baked & (probs.max(-1).values > 0.98)]
    assert len(x) > 100
    got = a.lookup(x, img)
    agree = ((got[:, 0] > 0.5) == (checker(x)[:, 0] > 0.5)).float().mean()
    assert agree > 0.95, f"only {agree:.3f} of samples show the baked checkerboard"


def test_fixed_seed_gives_the_same_atlas():
    xyz, rgb = synthetic_samples("sphere", 1500, seed=2)
    cfg = AtlasConfig(**dict(QUICK, steps=15, texture_steps=5))
    a, ha = fit_atlas(xyz, rgb, cfg, quiet=True)
    b, hb = fit_atlas(xyz, rgb, cfg, quiet=True)
    assert ha["psnr"] == hb["psnr"]
    for (na, pa), (nb, pb) in zip(a.state_dict().items(), b.state_dict().items()):
        assert na == nb and torch.equal(pa.nan_to_num(7.0), pb.nan_to_num(7.0)), na


def test_fit_rejects_bad_samples():
    xyz, rgb = synthetic_samples("strip", 200)
    with pytest.raises(InputError, match="rgb"):
        fit_atlas(xyz, rgb[:10], AtlasConfig(**QUICK), quiet=True)
    with pytest.raises(InputError, match="at least"):
        fit_atlas(xyz[:10], rgb[:10], AtlasConfig(**QUICK), quiet=True)
    bad = xyz.clone()
    bad[3, 1] = float("inf")
    with pytest.raises(InputError, match="NaN or infinite"):
        fit_atlas(bad, rgb, AtlasConfig(**QUICK), quiet=True)


def test_auto_chart_count_rule():
    cfg = AtlasConfig()
    assert choose_chart_count(synthetic_samples("strip", 4000)[0], cfg)[0] == 4
    assert choose_chart_count(synthetic_samples("torus", 4000)[0], cfg)[0] == 8
    assert choose_chart_count(synthetic_samples("torus", 4000)[0], AtlasConfig(charts="4"))[0] == 4


def _cycle_error_texels(a, tp) -> torch.Tensor:
    """For every texel with a point: distance (texels) from its centre to where t_c sends the point back."""
    ok = torch.isfinite(tp).all(-1)
    _, pix = a.atlas_pixel_coords(tp[ok])
    rows, cols = torch.nonzero(ok, as_tuple=True)
    return (pix - torch.stack([cols + 0.5, rows + 0.5], -1)).norm(dim=-1)


def test_texel_map_from_forward_splat_is_consistent_with_lookups(strip_fit_grid):
    """The grid layout's texel map (kernel mean of the sample positions around each texel) sends each texel's point
    back to that texel; the surface-coordinate net alone (inverse) is the looser map it replaced."""
    a, hist, xyz, _ = strip_fit_grid
    max_dist = 3.0 * hist["spacing"]
    splat = a.compute_texel_points(xyz, max_dist, max_cycle=1e9, mode="splat").clone()
    inverse = a.compute_texel_points(xyz, max_dist, max_cycle=1e9, mode="inverse").clone()
    e_splat, e_inv = _cycle_error_texels(a, splat), _cycle_error_texels(a, inverse)
    _, pix = a.atlas_pixel_coords(xyz)  # the texels the samples land in all get a point
    landed = torch.isfinite(splat).all(-1)[pix[:, 1].long(), pix[:, 0].long()].float().mean()
    assert landed > 0.9, f"only {landed:.2f} of the sample texels have a point"
    assert e_splat.median() < 0.5, f"splat texel map misses its texels by {e_splat.median():.2f} (median)"
    assert e_splat.median() < e_inv.median()
    # the cycle rule drops what misses by more than max_cycle texels
    strict = a.compute_texel_points(xyz, max_dist, max_cycle=0.5, mode="splat")
    assert _cycle_error_texels(a, strict).max() <= 0.5 + 1e-4
    with pytest.raises(InputError, match="splat"):
        a.compute_texel_points(xyz, max_dist, mode="nearest")
    a.compute_texel_points(xyz, max_dist)  # leave the fixture's atlas as fit_atlas made it


@pytest.mark.parametrize("layout", ["islands", "grid"])
def test_bake_from_samples_matches_texel_points_on_smooth_colour_and_keeps_decal_masks(layout, strip_fit,
                                                                                       strip_fit_grid):
    """Baking splats fn at the stored surface samples; for a smooth fn that is fn at the texel's point (the
    fallback), and a decal's mask stays a mask: 1 deep inside, 0 far outside, fractional only at its edge."""
    import copy

    from core.edits.bake import bake

    a, _, xyz, _ = strip_fit if layout == "islands" else strip_fit_grid
    lo, hi = xyz.min(0).values, xyz.max(0).values
    smooth = lambda p: (((p - lo) / (hi - lo)).clamp(0, 1), None)
    with_samples = bake(a, smooth, source="samples")
    at_points = bake(a, smooth, source="points")
    fallback = copy.deepcopy(a)
    fallback.bake_samples = None  # an older file: "auto" bakes at the texel points
    assert torch.equal(bake(fallback, smooth), at_points)
    with pytest.raises(InputError, match="no surface samples"):
        bake(fallback, smooth, source="samples")
    with pytest.raises(InputError, match="source"):
        bake(a, smooth, source="texels")
    ok = torch.isfinite(a.texel_points()).all(-1)
    assert ok.sum() > 100
    err = (with_samples[ok] - at_points[ok]).abs()
    if a.islands:  # where the quick fit folds its map, a texel's point is one place that maps there, the samples
        assert err.median() < 0.01 and err.quantile(0.75) < 0.03  # around it a mix of both (island texel map)
    else:
        assert err.median() < 0.01 and err.max() < 0.1
    assert not torch.equal(with_samples, at_points)  # the sample path really ran

    centre = xyz.mean(0)
    radius = 0.3 * float((hi - lo).norm())
    red = torch.tensor([1.0, 0.0, 0.0])
    decal = lambda p: (red.expand(p.shape[0], 3), ((p - centre).norm(dim=-1) < radius).float())
    base = torch.zeros(*a.layout.shape, 3)
    img = bake(a, decal, base_image=base, source="samples")
    d = (a.texel_points() - centre).norm(dim=-1)
    inside, outside = ok & (d < 0.5 * radius), ok & (d > 1.5 * radius)  # the kernel softens the edge
    assert inside.sum() > 20 and outside.sum() > 20
    assert img[inside][:, 1:].abs().max() < 1e-6  # the decal's own colour, nothing else mixed in
    # Gaussian tails reach a few texels of this coarse 32-texel test atlas: judge the bulk, not every texel (on
    # some of the quick fit's seeds a few per cent of the inner texels read just under 0.95, none under 0.9)
    assert img[inside][:, 0].median() > 0.99 and (img[inside][:, 0] > 0.9).float().mean() > 0.95
    assert img[outside].max() < 0.05
    assert torch.isfinite(img).all() and img.min() >= 0 and img.max() <= 1


@pytest.mark.parametrize("layout", ["islands", "grid"])
def test_fitted_bake_reads_back_at_the_samples(layout, strip_fit, strip_fit_grid):
    """The least-squares bake's linear map is what the samples read (the sparse matrix against SampleLookup.read
    on a random image), and its image returns a hard-edged texture at the samples closer than the splat does."""
    from core.atlas.packing import unpack
    from core.atlas.sample_lookup import packed_read_matrix, sample_lookup
    from core.edits.bake import bake

    a, _, xyz, _ = strip_fit if layout == "islands" else strip_fit_grid
    lk = sample_lookup(a)
    H, W = a.layout.shape
    img = torch.rand(H, W, 3, generator=torch.Generator().manual_seed(3))
    A = packed_read_matrix(a, lk, H, W)
    via_matrix = torch.from_numpy(A @ img.double().numpy().reshape(-1, 3)).float()
    assert torch.allclose(via_matrix, lk.read(unpack(img, a.layout)), atol=1e-5)
    lo, hi = xyz.min(0).values, xyz.max(0).values
    bands = lambda p: ((((p[:, :1] - lo[0]) / (hi[0] - lo[0]) * 5).floor() % 2).expand(-1, 3), None)  # noqa: E731
    want = bands(lk.samples)[0]
    err = {s: float(((lk.read(unpack(bake(a, bands, source=s), a.layout)) - want) ** 2).mean())
           for s in ("fit", "samples")}
    # this quick fit's 32-texel charts hold several samples per texel: the fit cannot return each its own colour
    assert err["fit"] < 0.85 * err["samples"], err
