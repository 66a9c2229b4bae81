"""Stage-2 fitting helpers: the surface-area estimate that sets the UV scale."""
import math

import numpy as np
import pytest

from core.atlas.fit import sample_spacing
from core.atlas.synthetic import synthetic_samples

AREAS = {"strip": 0.8 * 0.75 * math.pi * 1.0, "sphere": 4 * math.pi * 0.8**2}


@pytest.mark.parametrize("name", ["strip", "sphere"])
@pytest.mark.parametrize("noise", [0.0, 0.01])
def test_area_estimate_is_robust_to_a_noisy_slab(name, noise):
    """Samples 1 cm off the surface (about 3 sample spacings, like PAPR's surface points) must not inflate the
    area: a 3-D k-NN radius read 3.6 on this strip (true 1.885)."""
    xyz = synthetic_samples(name, 20000, seed=2)[0].numpy().astype(np.float64)
    xyz = xyz + noise * np.random.default_rng(0).normal(size=xyz.shape)
    spacing, area = sample_spacing(xyz)
    assert abs(area / AREAS[name] - 1) < 0.1, area
    assert 0 < spacing < 0.05


def test_area_estimate_scales_with_the_square_of_length():
    xyz = synthetic_samples("strip", 5000, seed=3)[0].numpy().astype(np.float64)
    a1 = sample_spacing(xyz)[1]
    for s in (1e-3, 1e3):
        assert abs(sample_spacing(xyz * s)[1] / (a1 * s * s) - 1) < 1e-6


def test_kernel_texture_beats_descent_on_noisy_colours():
    """Same seed, same maps (400 steps: at 150 both textures are dominated by unconverged maps); only the final
    texture differs. Colours carry noise (as real pixels do): the kernel texture must be closer to the clean
    colour than the per-sample descent fit, which reproduces the noise."""
    import torch

    from core.atlas.config import AtlasConfig
    from core.atlas.fit import fit_atlas
    from core.atlas.synthetic import surface_colour

    xyz, clean = synthetic_samples("strip", 4000, seed=4)
    noisy = (clean + 0.15 * torch.randn(clean.shape, generator=torch.Generator().manual_seed(0))).clamp(0, 1)
    quick = dict(steps=400, texture_steps=150, batch=256, uv_batch=32, distortion_batch=32, width_map=32, depth_map=2,
                 width_chart=16, depth_chart=1, texture_res=48, log_every=1000, eval_samples=256, charts="4")
    threads = torch.get_num_threads()
    torch.set_num_threads(1)
    try:
        err = {}
        for mode in ("kernel", "descent"):
            atlas, hist = fit_atlas(xyz, noisy, AtlasConfig(texture_mode=mode, **quick), quiet=True)
            held_out = synthetic_samples("strip", 2000, seed=5)[0]
            err[mode] = float((atlas.lookup(held_out) - surface_colour(held_out)).pow(2).mean())
            assert torch.isfinite(atlas.textures).all()
    finally:
        torch.set_num_threads(threads)
    assert err["kernel"] < 0.7 * err["descent"], err


def test_unknown_texture_mode_is_a_clear_error():
    from core.atlas.config import AtlasConfig
    from core.atlas.fit import fit_atlas
    from core.util.errors import InputError

    xyz, rgb = synthetic_samples("strip", 200, seed=0)
    with pytest.raises(InputError, match="texture_mode"):
        fit_atlas(xyz, rgb, AtlasConfig(texture_mode="paint", steps=1), quiet=True)


def test_fit_uses_the_configured_threads_and_restores_them():
    import torch

    from core.atlas.config import AtlasConfig
    from core.atlas.fit import fit_atlas

    xyz, rgb = synthetic_samples("strip", 300, seed=0)
    original = torch.get_num_threads()
    torch.set_num_threads(2)
    try:
        seen = []
        fit_atlas(xyz, rgb, AtlasConfig(steps=2, texture_steps=0, texture_res=8, charts="4", threads=1, width_map=8,
                                        depth_map=1, width_chart=8, depth_chart=1, eval_samples=64),
                  progress=lambda f, info: seen.append(torch.get_num_threads()), quiet=True)
        assert seen and set(seen) == {1}
        assert torch.get_num_threads() == 2
    finally:
        torch.set_num_threads(original)


@pytest.mark.parametrize("noise", [0.0, 0.01])
def test_sample_normals_are_the_thin_direction_of_a_noisy_slab(noise):
    """The sphere's normal is radial; with samples 1 cm off the surface (a slab ~3 spacings thick, like PAPR's
    surface points) the PCA normal of 48 neighbours must still be within ~15 degrees of it for most samples."""
    from core.atlas.fit import sample_normals

    xyz = synthetic_samples("sphere", 20000, seed=2)[0].numpy().astype(np.float64)
    radial = xyz / np.linalg.norm(xyz, axis=1, keepdims=True)
    xyz = xyz + noise * np.random.default_rng(0).normal(size=xyz.shape)
    n = sample_normals(xyz)
    assert n.shape == xyz.shape and n.dtype == np.float32
    assert np.allclose(np.linalg.norm(n, axis=1), 1.0, atol=1e-5)
    cos = np.abs((n * radial).sum(1))
    assert np.median(cos) > 0.97 and np.quantile(cos, 0.1) > 0.9, (np.median(cos), np.quantile(cos, 0.1))


def test_sample_normals_of_degenerate_samples_are_finite():
    from core.atlas.fit import sample_normals

    same = np.ones((100, 3))
    assert np.array_equal(sample_normals(same), np.zeros((100, 3), np.float32))   # no plane: zero normals
    line = np.stack([np.linspace(0, 1, 100), np.zeros(100), np.zeros(100)], 1)
    assert np.isfinite(sample_normals(line)).all()
    assert sample_normals(np.zeros((2, 3))).shape == (2, 3)


def test_normal_flatness_measures_the_derivative_along_the_normal_only():
    import torch

    from core.atlas.losses import normal_flatness

    g = torch.Generator().manual_seed(0)
    normals = torch.nn.functional.normalize(torch.randn(50, 3, generator=g), dim=-1)
    # a Jacobian whose rows are perpendicular to the normal: the map is flat across the surface
    rows = torch.randn(50, 2, 2, 3, generator=g)
    flat = rows - (rows * normals[:, None, None]).sum(-1, keepdim=True) * normals[:, None, None]
    assert float(normal_flatness(flat, normals)) < 1e-10
    # one row along the normal with length 2: |J n|^2 = 4 for that chart
    J = flat.clone()
    J[:, 0, 0] = 2 * normals
    w = torch.tensor([[1.0, 0.0]]).expand(50, 2)
    ref = np.mean([float((J[i, 0] @ normals[i]).pow(2).sum()) for i in range(50)])
    assert abs(float(normal_flatness(J, normals, w)) - ref) < 1e-4 and abs(ref - 4) < 1e-3
    assert float(normal_flatness(J, normals, torch.tensor([[0.0, 1.0]]).expand(50, 2))) < 1e-10
    # non-finite normals count as 0, gradients stay finite
    bad = normals.clone()
    bad[0] = float("nan")
    Jg = J.clone().requires_grad_(True)
    loss = normal_flatness(Jg, bad, w)
    loss.backward()
    assert torch.isfinite(loss) and torch.isfinite(Jg.grad).all()
    for scale in (1e20, 1e-20, 0.0):   # absurd, tiny and zero Jacobians: finite loss and gradient
        Jx = (J * scale).requires_grad_(True)
        loss = normal_flatness(Jx, normals, w)
        loss.backward()
        assert torch.isfinite(loss) and torch.isfinite(Jx.grad).all(), scale


def test_normal_loss_flattens_the_map_across_a_noisy_slab():
    """Samples scattered 1 cm off the strip (a slab like PAPR's surface points): without the term the texture
    coordinates change along the normal (the 3-D cycle loss asks the maps to tell the slab's layers apart); with
    it they change far less there, so a point off the middle of the slab reads its own place's texels."""
    import torch

    from core.atlas.config import AtlasConfig
    from core.atlas.fit import fit_atlas, sample_normals

    xyz, rgb = synthetic_samples("strip", 4000, seed=4)
    xyz = xyz + 0.01 * torch.randn(xyz.shape, generator=torch.Generator().manual_seed(1))
    quick = dict(steps=300, batch=256, uv_batch=32, distortion_batch=64, width_map=32, depth_map=2, width_chart=16,
                 depth_chart=1, texture_res=48, log_every=1000, eval_samples=256, charts="4", footprint=False)
    normals = torch.from_numpy(sample_normals(xyz.numpy().astype(np.float64)))
    x, n = xyz[:500], normals[:500]
    t = torch.nn.functional.normalize(torch.linalg.cross(n, torch.tensor([[0.6, 0.0, 0.8]]).expand_as(n)), dim=-1)
    ratio = {}
    threads = torch.get_num_threads()
    torch.set_num_threads(1)
    try:
        for w in (0.0, 1.0):
            atlas, _ = fit_atlas(xyz, rgb, AtlasConfig(w_normal=w, **quick), quiet=True)
            with torch.no_grad():
                p, _ = atlas.chart_uv(x, placed=False)
                c, ar = p.argmax(-1), torch.arange(len(x))

                def grad(d, eps=1e-3):
                    return ((atlas.chart_uv(x + eps * d, placed=False)[1]
                             - atlas.chart_uv(x - eps * d, placed=False)[1])[ar, c]).norm(dim=-1) / (2 * eps)
                ratio[w] = float((grad(n) / grad(t).clamp_min(1e-9)).median())
            assert torch.isfinite(atlas.textures).all()
    finally:
        torch.set_num_threads(threads)
    assert ratio[1.0] < 0.6 * ratio[0.0], ratio   # measured 1.32 -> 0.61


def test_chamfer_equals_the_min_over_the_full_distance_matrix_value_and_gradient():
    """losses.chamfer differentiates only the nearest pairs: the same loss and gradients as taking the min over
    the full squared-distance matrix with autograd."""
    import torch

    from core.atlas import losses

    g = torch.Generator().manual_seed(0)
    x0, y0 = torch.randn(300, 3, generator=g), torch.randn(500, 3, generator=g)
    x, y = x0.clone().requires_grad_(True), y0.clone().requires_grad_(True)
    losses.chamfer(x, y).backward()
    xr, yr = x0.clone().requires_grad_(True), y0.clone().requires_grad_(True)
    d = ((xr[:, None] - yr[None]) ** 2).sum(-1)
    ref = d.min(dim=1).values.mean() + d.min(dim=0).values.mean()
    ref.backward()
    assert torch.allclose(losses.chamfer(x0, y0), ref.detach(), rtol=1e-6, atol=0)
    assert torch.allclose(x.grad, xr.grad, rtol=1e-5, atol=1e-8) and torch.allclose(y.grad, yr.grad, rtol=1e-5, atol=1e-8)


def test_nearest_pairs_equal_cdists_argmins_on_the_cpu_path_and_the_fallback():
    """losses.nearest_pairs (squared distances by matrix products, numpy's row argmin) picks the same nearest
    points as torch.cdist's argmins in both directions, at the training's batch shapes and on clustered points
    (many near ties); float64 inputs take the cdist path."""
    import torch

    from core.atlas import losses

    g = torch.Generator().manual_seed(3)
    for B, K, spread in ((512, 1024, 1.0), (300, 500, 1.0), (64, 2000, 1e-3), (1, 7, 1.0)):
        x = torch.randn(B, 3, generator=g) * spread + 0.5
        y = torch.randn(K, 3, generator=g) * spread + 0.5
        to_y, to_x = losses.nearest_pairs(x, y)
        d2 = torch.cdist(x.double(), y.double()).pow(2)
        # the picked point is as near as the nearest, up to float32 rounding of the sets' squared size
        tol = 1e-6 * spread ** 2
        assert (d2[torch.arange(B), to_y] - d2.min(1).values).max() <= tol
        assert (d2[to_x, torch.arange(K)] - d2.min(0).values).max() <= tol
        d = d2
        if spread == 1.0:  # no near ties: the very same indices
            assert torch.equal(to_y, d.argmin(1)) and torch.equal(to_x, d.argmin(0))
    x64, y64 = torch.randn(20, 3, dtype=torch.float64), torch.randn(30, 3, dtype=torch.float64)
    a, b = losses.nearest_pairs(x64, y64)
    d = torch.cdist(x64, y64)
    assert torch.equal(a, d.argmin(1)) and torch.equal(b, d.argmin(0))
