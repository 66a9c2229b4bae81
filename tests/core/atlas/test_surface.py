"""Mid-surface projection (core/atlas/surface.py): points of a noisy slab go to its middle, a point's offset across
the slab does not change where it lands, extreme and degenerate inputs stay finite, and an atlas with it reads
the same texel across the slab, saves and loads it, and bakes through it."""
import json

import numpy as np
import pytest
import torch

from core.atlas.atlas import Atlas
from core.atlas.surface import SurfaceProjection
from core.atlas.synthetic import synthetic_samples
from core.util.errors import InputError, ModelFileError

RADIUS = 0.8  # synthetic sphere


def _noisy_sphere(noise=0.01, n=20000, seed=2):
    xyz = synthetic_samples("sphere", n, seed=seed)[0].double()
    return xyz + noise * torch.randn(xyz.shape, generator=torch.Generator().manual_seed(0), dtype=torch.float64)


def test_projection_moves_a_noisy_slab_to_its_middle():
    """Samples scattered 1 cm (about 3 sample spacings) off a sphere: projected, they lie within a fraction of
    that of the sphere."""
    xyz = _noisy_sphere()
    proj = SurfaceProjection.from_samples(xyz.numpy())
    before = (xyz.norm(dim=-1) - RADIUS).abs()
    after = (proj.project(xyz).norm(dim=-1) - RADIUS).abs()
    assert float(before.median()) > 0.005
    assert float(after.median()) < 0.25 * float(before.median()), (float(before.median()), float(after.median()))
    # the move is along the normal: the direction from the centre is kept
    cos = torch.nn.functional.cosine_similarity(proj.project(xyz), xyz, dim=-1)
    assert float(cos.min()) > 0.999


def test_where_a_point_sits_across_the_slab_does_not_change_its_projection():
    """The same surface place offset by -2..+2 cm along its normal lands on (nearly) one point; without the
    projection those points are 4 cm apart."""
    proj = SurfaceProjection.from_samples(_noisy_sphere().numpy())
    dirs = torch.nn.functional.normalize(torch.randn(300, 3, generator=torch.Generator().manual_seed(3),
                                                     dtype=torch.float64), dim=-1)
    outs = torch.stack([proj.project(dirs * (RADIUS + d)) for d in (-0.02, -0.01, 0.0, 0.01, 0.02)])
    spread = (outs - outs.mean(0)).norm(dim=-1).max(0).values
    assert float(spread.median()) < 0.002, float(spread.median())   # against 0.02 unprojected
    assert torch.isfinite(outs).all()


def test_far_extreme_and_degenerate_inputs_give_finite_points():
    proj = SurfaceProjection.from_samples(_noisy_sphere(n=3000).numpy(), neighbours=64)
    x = torch.tensor([[1e6, 0.0, 0.0], [0.0, -1e30, 3.0], [1e-30, 1e-30, 1e-30], [0.0, 0.0, 0.0], [5.0, 5.0, 5.0]])
    out = proj.project(x)
    assert out.dtype == torch.float32 and torch.isfinite(out).all()
    # a far point moves along its nearest planes' normals only: its distance from the surface is what changes
    assert float((out[0] - x[0]).norm()) <= 1e6 + 1
    assert proj.project(torch.zeros(0, 3)).shape == (0, 3)
    # empty neighbourhoods (too few samples), a line and one repeated point span no plane: points stay put
    for samples in (np.zeros((2, 3)), np.stack([np.linspace(0, 1, 50), np.zeros(50), np.zeros(50)], -1),
                    np.ones((40, 3))):
        p = SurfaceProjection.from_samples(samples)
        y = torch.tensor([[0.3, 2.0, -1.0], [1e20, 0.0, 0.0]], dtype=torch.float64)
        assert torch.equal(p.project(y), y)
    # a slab as thick as it is wide (a ball of samples) defines no plane either: left as it is
    ball = np.random.default_rng(4).normal(size=(3000, 3))
    p = SurfaceProjection.from_samples(ball, neighbours=256)
    assert float((p.normals != 0).any(1).mean()) < 0.05
    y = torch.from_numpy(ball[:200])
    assert float((p.project(y) - y).norm(dim=-1).median()) < 1e-3
    with pytest.raises(InputError):
        SurfaceProjection.from_samples(np.array([[0.0, 0.0, np.nan]] * 10))
    with pytest.raises(InputError):
        proj.project(torch.zeros(4, 2))


def _strip_atlas():
    """A random 4-chart atlas over the strip with a mid-surface from 1 cm-noisy strip samples."""
    torch.manual_seed(0)
    xyz = synthetic_samples("strip", 6000, seed=1)[0]
    noisy = xyz + 0.01 * torch.randn(xyz.shape, generator=torch.Generator().manual_seed(1))
    atlas = Atlas(4, 16, 2, xyz.mean(0), float((xyz.max(0).values - xyz.min(0).values).max()) / 2 + 0.05)
    atlas.surface = SurfaceProjection.from_samples(noisy.numpy())
    return atlas, xyz, noisy


def test_atlas_reads_one_texel_across_the_slab_and_round_trips_its_mid_surface():
    atlas, xyz, noisy = _strip_atlas()
    x = xyz[:400]
    n = torch.from_numpy(atlas.surface.normals[atlas.surface._tree.query(x.double().numpy())[1]]).float()
    shifted = [atlas.chart_uv(x + d * n, placed=False)[1] for d in (-0.015, 0.015)]
    plain = Atlas(4, 16, 2, atlas.centre, atlas.half)
    plain.load_state_dict(atlas.state_dict())
    free = [plain.chart_uv(x + d * n, placed=False)[1] for d in (-0.015, 0.015)]
    moved, moved_free = (shifted[0] - shifted[1]).norm(dim=-1), (free[0] - free[1]).norm(dim=-1)
    assert float(moved.median()) < 0.1 * float(moved_free.median()), (float(moved.median()),
                                                                     float(moved_free.median()))
    # saved and loaded: the same projection, bit for bit
    arrays, meta = atlas.to_arrays(), atlas.meta()
    assert meta["version"] == 4 and "atlas/surface/normals" in arrays
    b = Atlas.from_arrays({k: v.copy() for k, v in arrays.items()}, json.loads(json.dumps(meta)), "cpu")
    assert torch.equal(b.chart_uv(noisy[:500])[1], atlas.chart_uv(noisy[:500])[1])
    # an atlas without it is written as before (version 1 for the grid) and has no surface on loading
    assert plain.meta()["version"] == 1 and Atlas.from_arrays(plain.to_arrays(), plain.meta()).surface is None
    broken = dict(meta, surface={"bandwidth": -1.0})
    with pytest.raises(ModelFileError):
        Atlas.from_arrays(arrays, broken)
    with pytest.raises(ModelFileError):
        Atlas.from_arrays({k: v for k, v in arrays.items() if k != "atlas/surface/centres"}, meta)


def test_a_fit_with_the_mid_surface_bakes_and_reads_on_it():
    """A quick island fit to samples 1 cm off the strip with `mid_surface=True`: the stored bake samples and
    the texel map lie on the mid-surface, every texel's point maps back within 1 texel, and a point's texel no
    longer depends on its offset across the slab (without the projection the same fit's maps move it by texels)."""
    from core.atlas.config import AtlasConfig
    from core.atlas.fit import fit_atlas

    xyz, rgb = synthetic_samples("strip", 4000, seed=4)
    noisy = xyz + 0.01 * torch.randn(xyz.shape, generator=torch.Generator().manual_seed(1))
    quick = dict(steps=300, batch=256, uv_batch=32, distortion_batch=64, width_map=32, depth_map=2, width_chart=16,
                 depth_chart=1, log_every=1000, eval_samples=256, charts="4", layout="islands", image_size=96,
                 mid_surface_neighbours=128)
    threads = torch.get_num_threads()
    torch.set_num_threads(1)
    try:
        atlas, hist = fit_atlas(noisy, rgb, AtlasConfig(mid_surface=True, **quick), quiet=True)
    finally:
        torch.set_num_threads(threads)
    assert hist["mid_surface"]["anchors"] == 4000 and hist["mid_surface"]["move_median"] > 0
    assert torch.allclose(atlas.bake_samples, atlas.surface.project(noisy).float(), atol=1e-6)
    tp = atlas.texel_points()
    ok = torch.isfinite(tp).all(-1)
    assert float(ok.float().mean()) > 0.3
    off = (atlas.surface.project(tp[ok]) - tp[ok]).norm(dim=-1)
    assert float(off.median()) < 1e-3, float(off.median())   # the noise: 1e-2
    _, pix = atlas.atlas_pixel_coords(tp[ok])
    rows, cols = torch.nonzero(ok, as_tuple=True)
    assert float(((pix - torch.stack([cols + 0.5, rows + 0.5], -1)).norm(dim=-1) <= 1).float().mean()) == 1.0
    # the same place at the slab's two faces: one texel with the projection, texels apart without
    x = xyz[:500]
    n = torch.from_numpy(atlas.surface.normals[atlas.surface._tree.query(x.double().numpy())[1]]).float()
    px = [atlas.atlas_pixel_coords(x + d * n)[1] for d in (-0.01, 0.01)]
    surface, atlas.surface = atlas.surface, None
    free = [atlas.atlas_pixel_coords(x + d * n)[1] for d in (-0.01, 0.01)]
    atlas.surface = surface
    moved, moved_free = (px[0] - px[1]).norm(dim=-1).median(), (free[0] - free[1]).norm(dim=-1).median()
    assert float(moved) < 0.2 and float(moved_free) > 5 * float(moved), (float(moved), float(moved_free))
    assert torch.isfinite(atlas.lookup(torch.tensor([[1e6, -1e6, 3.0], [0.0, 0.0, 0.0]]))).all()


def test_texel_map_projects_the_samples_it_is_given():
    """compute_texel_points projects the samples it is given: the stored bake samples are the projected ones."""
    atlas, _, noisy = _strip_atlas()
    atlas.compute_texel_points(noisy, max_dist=0.05)
    assert torch.allclose(atlas.bake_samples, atlas.surface.project(noisy).float())


def test_rendered_lookups_use_the_same_projection_as_chart_uv():
    """The frame renderer's sub-pixel lookups (core/atlas/subpixel.py, also the footprint refit's) go through the
    atlas's projection: on a frame of points they equal an atlas without one given the projected points."""
    from core.atlas.subpixel import subpixel_chart_uv

    atlas, xyz, noisy = _strip_atlas()
    plain = Atlas(4, 16, 2, atlas.centre, atlas.half)
    plain.load_state_dict(atlas.state_dict())
    pts = noisy[:64].reshape(8, 8, 3)
    valid = torch.ones(8, 8, dtype=torch.bool)
    valid[0, 0] = False
    depth = torch.ones(8, 8)
    got = subpixel_chart_uv(atlas, pts, valid, depth, 2, 1e9)
    want = subpixel_chart_uv(plain, atlas.surface.project(pts.reshape(-1, 3)).reshape(8, 8, 3), valid, depth, 2, 1e9)
    assert torch.equal(got[2], want[2])
    assert torch.allclose(got[1], want[1], atol=1e-6) and torch.allclose(got[0], want[0], atol=1e-6)
    assert not torch.allclose(got[1], subpixel_chart_uv(plain, pts, valid, depth, 2, 1e9)[1], atol=1e-4)


def _noisy_plate(thickness, n=40000, width=0.5, noise=0.003, seed=0):
    """The two faces of a width x width plate at z = +-thickness/2, scattered `noise` across (spacing ~3.5 mm)."""
    rng = np.random.default_rng(seed)
    xy = rng.uniform(-width / 2, width / 2, (n, 2))
    z = np.where(rng.random(n) < 0.5, thickness / 2, -thickness / 2)
    return np.c_[xy, z] + noise * rng.normal(size=(n, 3))


def test_adaptive_neighbourhoods_keep_the_two_faces_of_a_thin_part_apart():
    """A plate 3 cm thick (about 8 sample spacings): a 1024-sample neighbourhood spans both faces, so its plane
    runs through the plate's middle and presses both faces onto one sheet; adaptive neighbourhoods stop growing
    before they reach the other face and keep each face on its own middle. A thick plate is left alike."""
    for thickness, fixed_gap in ((0.03, (0.0, 0.012)), (0.1, (0.095, 0.105))):
        x = _noisy_plate(thickness)
        inner = (np.abs(x[:, :2]) < 0.15).all(1)
        top = inner & (x[:, 2] > 0)
        bottom = inner & (x[:, 2] < 0)
        gaps = {}
        for adaptive in (False, True):
            p = SurfaceProjection.from_samples(x, adaptive=adaptive).project(x).numpy()
            assert np.isfinite(p).all()
            gaps[adaptive] = float(np.median(p[top, 2]) - np.median(p[bottom, 2]))
            assert float(np.std(p[top, 2])) < 0.003       # each face still lands on one sheet
        assert fixed_gap[0] < gaps[False] < fixed_gap[1], gaps
        assert abs(gaps[True] - thickness) < 0.1 * thickness, gaps


def test_adaptive_neighbourhoods_stay_finite_on_degenerate_samples():
    """Too few samples for the smaller sizes, a line, one repeated point and far outliers: finite planes and
    finite projections, and points stay put where no neighbourhood spans a plane."""
    for samples in (np.zeros((2, 3)), np.stack([np.linspace(0, 1, 50), np.zeros(50), np.zeros(50)], -1),
                    np.ones((40, 3)), np.r_[_noisy_plate(0.03, n=3000), [[1e6, 0, 0], [0, 0, -1e6]]]):
        p = SurfaceProjection.from_samples(samples, neighbours=256, adaptive=True)
        assert np.isfinite(p.centres).all() and np.isfinite(p.normals).all()
        q = torch.tensor([[1e6, 0.0, 0.0], [0.0, 0.0, 0.0], [1e-30, 2.0, -3.0]])
        assert torch.isfinite(p.project(q)).all()
        if len(samples) < 100:
            assert torch.equal(p.project(q), q)


def test_the_adaptive_flag_reaches_the_fits_projection():
    """AtlasConfig.mid_surface_adaptive (`--atlas-mid-surface-adaptive`) builds the atlas's projection with adaptive
    neighbourhoods, the same planes as SurfaceProjection.from_samples(adaptive=True)."""
    from core.atlas.config import AtlasConfig
    from core.atlas.fit import mid_surface

    x = torch.from_numpy(_noisy_plate(0.03, n=6000)).float()
    got = {}
    for adaptive in (False, True):
        a = Atlas(2, 16, 2, torch.zeros(3), 1.0, width_chart=8, depth_chart=1, width_map=8, depth_map=1)
        hist = {}
        moved = mid_surface(a, x, AtlasConfig(mid_surface=True, mid_surface_neighbours=512,
                                              mid_surface_adaptive=adaptive), 0.005, hist)
        assert moved.shape == x.shape and torch.isfinite(moved).all() and hist["mid_surface"]["anchors"] == 6000
        got[adaptive] = a.surface
    ref = SurfaceProjection.from_samples(x.numpy(), neighbours=512, adaptive=True)
    assert np.array_equal(got[True].centres, ref.centres) and np.array_equal(got[True].normals, ref.normals)
    assert not np.array_equal(got[False].centres, got[True].centres)


def test_mid_surface_normals_follow_the_surface_and_stay_finite():
    """normals_at: on a noisy sphere the mid-surface's normals are radial (either sign); far, extreme and
    degenerate inputs give finite unit-or-zero normals, zero where no anchor defines a plane."""
    xyz = _noisy_sphere(n=8000)
    proj = SurfaceProjection.from_samples(xyz.numpy(), neighbours=256)
    x = proj.project(xyz[:500])
    n = proj.normals_at(x)
    assert n.shape == (500, 3) and n.dtype == torch.float32
    cos = torch.nn.functional.cosine_similarity(n.double(), x, dim=-1).abs()
    assert float(cos.median()) > 0.99 and float(cos.min()) > 0.9, (float(cos.median()), float(cos.min()))
    far = proj.normals_at(torch.tensor([[1e6, 0.0, 0.0], [0.0, -1e30, 3.0], [1e-30, 1e-30, 1e-30], [0.0, 0.0, 0.0]]))
    length = far.norm(dim=-1)
    assert torch.isfinite(far).all() and bool(((length - 1).abs() < 1e-4).logical_or(length == 0).all())
    assert proj.normals_at(torch.zeros(0, 3)).shape == (0, 3)
    ball = SurfaceProjection.from_samples(np.random.default_rng(4).normal(size=(3000, 3)), neighbours=256)
    assert float((ball.normals_at(torch.zeros(50, 3)).norm(dim=-1) == 0).float().mean()) > 0.9
    for samples in (np.zeros((2, 3)), np.ones((40, 3))):
        assert torch.equal(SurfaceProjection.from_samples(samples).normals_at(torch.ones(3, 3)), torch.zeros(3, 3))


def test_the_tangent_jacobian_sees_the_fold_the_full_jacobian_hides():
    """A map of the plane z = 0 that reads (x, z): in 3-D its Jacobian has two unit singular values (no distortion
    at all for the normal-free loss), but on the plane it is constant along y — folded flat. Its part along the
    surface has sigma2 = 0, and the distortion's log-area term, taken on it, is at its ceiling. A map whose rows
    are tangent is left alone; zero and NaN normals leave J as it is; extreme Jacobians stay finite."""
    from core.atlas.distortion import distortion_terms
    from core.atlas.fit import tangent_jacobian

    z = torch.tensor([[0.0, 0.0, 1.0]])
    flat = torch.tensor([[[[1.0, 0.0, 0.0], [0.0, 0.0, 1.0]]]])           # [1, 1, 2, 3]: u = x, v = z
    good = torch.tensor([[[[1.0, 0.0, 0.3], [0.0, 1.0, -0.2]]]])           # tangent rows plus a normal part
    assert float(distortion_terms(flat)[1]) < 1e-10
    assert float(distortion_terms(tangent_jacobian(flat, z))[1]) > 150     # (log 1e-6)^2 = 191: the floor
    assert torch.allclose(tangent_jacobian(good, z), torch.tensor([[[[1.0, 0.0, 0.0], [0.0, 1.0, 0.0]]]]))
    assert float(distortion_terms(tangent_jacobian(good, z))[1]) < 1e-10
    for nrm in (torch.zeros(1, 3), torch.tensor([[float("nan"), 0.0, 1.0]])):
        assert torch.equal(tangent_jacobian(flat, nrm), flat)
    J = torch.tensor([[[[1e30, -1e30, 3.0], [1e-30, 0.0, 0.0]]]], requires_grad=True)
    s, a = distortion_terms(tangent_jacobian(J, z))
    (s + a).backward()
    assert torch.isfinite(s) and torch.isfinite(a) and torch.isfinite(J.grad).all()


def test_mid_surface_maps_need_the_mid_surface():
    from core.atlas.config import AtlasConfig
    from core.atlas.fit import fit_atlas

    xyz, rgb = synthetic_samples("strip", 500, seed=4)
    with pytest.raises(InputError, match="mid_surface"):
        fit_atlas(xyz, rgb, AtlasConfig(mid_surface_maps=True, steps=1), quiet=True)
    with pytest.raises(InputError, match="mid_surface_maps"):
        fit_atlas(xyz, rgb, AtlasConfig(mid_surface=True, w_fold=1.0, steps=1), quiet=True)


def test_orient_gives_a_closed_surface_one_side():
    """PCA normals have random signs; after orient() the anchors of a noisy sphere all face out or all face in, the
    projection is unchanged, and degenerate anchors (no plane) stay zero."""
    xyz = _noisy_sphere(n=8000)
    proj = SurfaceProjection.from_samples(xyz.numpy(), neighbours=256)
    before = proj.project(xyz[:300])
    side = np.sign(np.einsum("ij,ij->i", proj.normals, proj.centres))
    assert 0.1 < float((side > 0).mean()) < 0.9        # random signs to begin with
    proj.orient()
    side = np.sign(np.einsum("ij,ij->i", proj.normals, proj.centres))
    assert max(float((side > 0).mean()), float((side < 0).mean())) > 0.999
    assert torch.allclose(proj.project(xyz[:300]), before, atol=1e-9)
    cos = torch.nn.functional.cosine_similarity(proj.normals_at(proj.project(xyz[:300])).double(), xyz[:300], dim=-1)
    assert max(float((cos > 0).float().mean()), float((cos < 0).float().mean())) == 1.0
    for samples in (np.zeros((2, 3)), np.ones((40, 3))):
        p = SurfaceProjection.from_samples(samples).orient()
        assert np.isfinite(p.normals).all() and not p.normals.any()


def test_the_fold_barrier_sees_two_sheets_laid_over_each_other():
    """A chart that maps a flattened tube: its front (u = x, v = y against normal +z) and its back (the normal -z,
    read the same way) land on the same texels, each locally without distortion — the distortion loss sees nothing,
    the fold barrier sees the back reversed. One orientation everywhere costs nothing; creases (rank-1 along the
    surface) cost margin^2; zero, huge and NaN inputs stay finite."""
    from core.atlas.distortion import distortion_terms
    from core.atlas.losses import fold_barrier

    J = torch.tensor([[1.0, 0.0, 0.0], [0.0, 1.0, 0.0]]).expand(8, 1, 2, 3).clone()
    up, down = torch.tensor([0.0, 0.0, 1.0]), torch.tensor([0.0, 0.0, -1.0])
    probs = torch.ones(8, 1)
    one_side = torch.stack([up] * 8)
    two_sheets = torch.stack([up] * 5 + [down] * 3)
    assert float(distortion_terms(J)[0] + distortion_terms(J)[1]) < 1e-10
    assert float(fold_barrier(J, one_side, probs)) == 0.0
    got = float(fold_barrier(J, two_sheets, probs))
    assert abs(got - 3 / 8 * 1.25 ** 2) < 1e-5, got          # the 3 reversed samples: (0.25 + 1)^2 each
    # a second chart holding the back costs nothing (the barrier pushes the back out of the first chart)
    probs2 = torch.tensor([[1.0, 0.0]] * 5 + [[0.0, 1.0]] * 3)
    J2 = J.expand(8, 2, 2, 3).clone()
    assert float(fold_barrier(J2, two_sheets, probs2)) == 0.0
    crease = torch.tensor([[1.0, 0.0, 0.0], [1.0, 0.0, 0.0]]).expand(8, 1, 2, 3)
    assert abs(float(fold_barrier(crease, one_side, probs)) - 0.25 ** 2) < 1e-6
    nan_normals = torch.full((8, 3), float("nan"))
    assert float(fold_barrier(J, nan_normals, probs)) == 0.0
    wild = torch.tensor([[1e30, -1e30, 3.0], [1e-30, 0.0, 0.0]]).expand(8, 1, 2, 3).clone().requires_grad_(True)
    zero = torch.zeros(8, 1, 2, 3, requires_grad=True)
    for j in (wild, zero):
        loss = fold_barrier(j, two_sheets, probs)
        loss.backward()
        assert torch.isfinite(loss) and torch.isfinite(j.grad).all()


class _PlanarMap(torch.nn.Module):
    """t(x) = (x, y) / 2 + 1/2 for one chart: [M, 3] -> [M, 1, 2]; on a sphere the front (z > 0) and the back are
    laid over each other with opposite orientations."""

    def forward(self, xn):
        return (0.5 * xn[:, None, :2] + 0.5).contiguous()


def test_fold_report_finds_the_back_of_a_flattened_sphere():
    """fold_report on a one-chart atlas that flattens the sphere along z: about half of the samples (the minority
    side) are reversed when the chart covers the whole sphere, none when it covers the cap z > 0.3 only; finite
    with a projection or without one, and the atlas's own planes are not reoriented."""
    from core.atlas.fit import fold_report

    xyz = _noisy_sphere(n=8000, noise=0.003).float()
    atlas = Atlas(1, 16, 2, torch.zeros(3), 1.0)
    atlas.tex = _PlanarMap()
    whole = fold_report(atlas, xyz, max_points=4000)
    assert 0.4 < whole["reversed"] <= 0.5 and whole["charts"][0][1] > 3900, whole
    cap = xyz[xyz[:, 2] > 0.3]
    assert fold_report(atlas, cap, max_points=4000)["reversed"] < 0.01
    atlas.surface = SurfaceProjection.from_samples(xyz.numpy(), neighbours=256)
    stored = atlas.surface.normals.copy()
    projected = fold_report(atlas, xyz, max_points=4000)
    assert 0.4 < projected["reversed"] <= 0.5
    assert 0.15 < projected["crease"] < 0.25, projected   # |rho| = |n_z|: the band |z| < 0.2, a fifth of the sphere
    assert np.array_equal(atlas.surface.normals, stored)


def test_a_fit_with_maps_on_the_mid_surface_and_the_fold_barrier_runs_end_to_end():
    """A quick island fit to samples 1 cm off the strip with mid_surface_maps and w_fold: the projection is built
    before the maps (its normals given one side), the fit stays finite, and the kept texels map back within 1
    texel."""
    from core.atlas.config import AtlasConfig
    from core.atlas.fit import fit_atlas

    xyz, rgb = synthetic_samples("strip", 3000, seed=4)
    noisy = xyz + 0.01 * torch.randn(xyz.shape, generator=torch.Generator().manual_seed(1))
    quick = dict(steps=150, batch=256, uv_batch=32, distortion_batch=64, width_map=32, depth_map=2, width_chart=16,
                 depth_chart=1, log_every=1000, eval_samples=256, charts="4", layout="islands", image_size=96,
                 mid_surface_neighbours=128)
    threads = torch.get_num_threads()
    torch.set_num_threads(1)
    try:
        atlas, hist = fit_atlas(noisy, rgb, AtlasConfig(mid_surface=True, mid_surface_maps=True, w_fold=1.0, **quick),
                                quiet=True)
    finally:
        torch.set_num_threads(threads)
    assert hist["mid_surface"]["anchors"] == 3000 and all(np.isfinite(hist["psnr"]))
    nrm = atlas.surface.normals[np.linalg.norm(atlas.surface.normals, axis=1) > 0.5]
    assert float(np.mean(nrm @ nrm.mean(0) > 0)) > 0.99      # the strip's anchors face one side
    tp = atlas.texel_points()
    ok = torch.isfinite(tp).all(-1)
    assert int(ok.sum()) > 500                                # of 96² (a short fit: utilisation is not the point)
    _, pix = atlas.atlas_pixel_coords(tp[ok])
    rows, cols = torch.nonzero(ok, as_tuple=True)
    assert float(((pix - torch.stack([cols + 0.5, rows + 0.5], -1)).norm(dim=-1) <= 1).float().mean()) == 1.0
