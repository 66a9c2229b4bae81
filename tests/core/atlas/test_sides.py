"""Charts split by side (core/atlas/sides.py): the orientation of a chart's map against one-sided normals, finite on
degenerate maps and normals; a flattened sphere (one chart laying its front and back over each other) gets one
island set per side, keeps its texels' points and round-trips them; a split atlas saves and loads bit for bit; a
quick fit with `island_sides` runs end to end."""
import math

import numpy as np
import pytest
import torch

from core.atlas.atlas import Atlas
from core.atlas.config import AtlasConfig
from core.atlas.sides import ChartSides, orientation, tangent_basis
from core.atlas.surface import SurfaceProjection
from core.atlas.synthetic import synthetic_samples
from core.util.errors import InputError
from tests.helpers.atlas_files import check_saves_and_loads_bit_for_bit


class _PlanarMap(torch.nn.Module):
    """t(x) = (x, y) / 2 + 1/2 for one chart: [M, 3] -> [M, 1, 2]; on a sphere the front (z > 0) and the back are
    laid over each other with opposite orientations."""

    def forward(self, xn):
        return (0.5 * xn[:, None, :2] + 0.5).contiguous()


def _sphere(n=8000, noise=0.003):
    xyz = synthetic_samples("sphere", n, seed=2)[0].double()
    return (xyz + noise * torch.randn(xyz.shape, generator=torch.Generator().manual_seed(0),
                                      dtype=torch.float64)).float()


def _round_trip(atlas) -> tuple[float, int]:
    tp = atlas.texel_points()
    ok = torch.isfinite(tp).all(-1)
    _, pix = atlas.atlas_pixel_coords(tp[ok])
    rows, cols = torch.nonzero(ok, as_tuple=True)
    miss = (pix - torch.stack([cols + 0.5, rows + 0.5], -1)).norm(dim=-1)
    return float((miss <= 1.0).float().mean()), int(ok.sum())


def _planar_island_atlas(xyz, split: bool, crease: float = 0.0, min_share: float = 0.05):
    """A one-chart atlas with the planar map, its islands, kernel texture and texel map built as fit_atlas does."""
    from core.atlas.fit import chart_sides, island_layout, sample_spacing
    from core.atlas.texture import filled_kernel_texture

    rgb = torch.rand(len(xyz), 3, generator=torch.Generator().manual_seed(0))
    atlas = Atlas(1, 16, 2, torch.zeros(3), 1.0)
    atlas.tex = _PlanarMap()
    cfg = AtlasConfig(layout="islands", island_sides=split, island_sides_crease=crease, image_size=96,
                      island_sides_neighbours=256, island_sides_min_share=min_share)
    spacing, area, *elements = sample_spacing(xyz.numpy().astype(np.float64), per_sample=True)
    xn, hist = atlas.normalise(xyz), {}
    if split:
        chart_sides(atlas, xyz, xn, cfg, spacing, hist)
    with torch.no_grad():
        probs, uv = atlas.outputs(xn)
        layout, info = island_layout(probs, uv, elements, area, math.sqrt(0.5 / area), 16, cfg, None)
        atlas.set_layout(layout)
        tex, _, _ = filled_kernel_texture(*atlas.place(probs, uv), rgb, layout.size, 1.0, labels=atlas.blur_labels)
        atlas.set_textures(tex)
        atlas.canonicalise_textures()
        atlas.compute_texel_points(xyz, 3 * spacing, 1.0, "splat", 1.0)
    return atlas, hist


def test_tangent_basis_is_right_handed_and_zero_without_a_normal():
    n = torch.nn.functional.normalize(torch.randn(200, 3, generator=torch.Generator().manual_seed(0)), dim=-1)
    n = torch.cat([n, torch.eye(3), torch.zeros(1, 3), torch.full((1, 3), float("nan"))])
    t1, t2 = tangent_basis(n)
    good = slice(0, 203)
    assert torch.allclose(torch.linalg.cross(t1[good], t2[good]), n[good], atol=1e-5)
    assert torch.allclose((t1[good] * n[good]).sum(-1), torch.zeros(203), atol=1e-6)
    assert (t1[203:] == 0).all() and (t2[203:] == 0).all()


def test_orientation_separates_the_two_sides_of_a_flattened_sphere():
    """Against outward normals the planar map's orientation has the sign of n_z (front and back opposite) and the
    size of the restricted map's det over its gradients along the surface, n_z / sqrt((1 - n_x²)(1 - n_y²))."""
    xyz = _sphere()
    n = torch.nn.functional.normalize(xyz, dim=-1)
    rho = orientation(_PlanarMap(), xyz, n, 1e-3)[:, 0]
    far = n[:, 2].abs() > 0.1
    assert bool((torch.sign(rho[far]) == torch.sign(n[far, 2])).all())
    den = (1 - n[:, 0] ** 2) * (1 - n[:, 1] ** 2)
    well = den > 0.1                       # away from the poles of x and y, where both gradients vanish
    assert torch.allclose(rho[well], n[well, 2] / den[well].sqrt(), atol=5e-3)
    assert rho.abs().max() <= 1


def test_orientation_is_finite_and_zero_on_degenerate_maps_and_normals():
    x = torch.randn(64, 3, generator=torch.Generator().manual_seed(1))
    n = torch.nn.functional.normalize(torch.randn(64, 3, generator=torch.Generator().manual_seed(2)), dim=-1)
    maps = {"constant": lambda p: torch.zeros(len(p), 2, 2),
            "rank one": lambda p: torch.stack([p[:, :1].expand(-1, 2), p[:, :1].expand(-1, 2)], -1),
            "huge": lambda p: 1e30 * p[:, None, :2].expand(-1, 2, -1),
            "tiny": lambda p: 1e-30 * p[:, None, :2].expand(-1, 2, -1),
            "nan": lambda p: torch.full((len(p), 2, 2), float("nan")),
            "inf": lambda p: torch.full((len(p), 2, 2), float("inf"))}
    for name, fn in maps.items():
        rho = orientation(fn, x, n, 1e-2)
        assert rho.shape == (64, 2) and torch.isfinite(rho).all(), name
        assert (rho.abs() <= 1).all(), name
        if name in ("constant", "rank one", "nan", "inf"):
            assert (rho == 0).all(), name
    for normals in (torch.zeros(64, 3), torch.full((64, 3), float("nan"))):
        assert (orientation(_PlanarMap(), x, normals, 1e-2) == 0).all()


def test_side_rule_keeps_creases_on_the_majority_side():
    """On the flattened sphere one hemisphere is reversed (which one: the orientation's arbitrary side); a crease
    threshold moves only points near the equator (where the map turns over) back to the majority side."""
    xyz = _sphere(4000)
    surf = SurfaceProjection.from_samples(xyz.numpy(), neighbours=256).orient()
    tex, z = _PlanarMap(), xyz[:, 2]
    sharp = ChartSides(surf, [1.0], 0.01, 0.0).reversed(tex, xyz, xyz)[:, 0]
    assert 0.45 < float(sharp.float().mean()) < 0.55
    back = z * float(torch.sign(z[sharp].mean())) > 0
    assert float((sharp == back)[z.abs() > 0.2].float().mean()) > 0.99
    soft = ChartSides(surf, [1.0], 0.01, 0.3).reversed(tex, xyz, xyz)[:, 0]
    moved = sharp & ~soft
    assert not bool((soft & ~sharp).any()) and 0.01 < float(moved.float().mean()) < 0.2
    assert float(z[moved].abs().max()) < 0.35
    with pytest.raises(InputError):
        ChartSides(surf, [0.5], 0.01)
    with pytest.raises(InputError):
        ChartSides(surf, [1.0], float("nan"))


def test_a_flattened_sphere_gets_one_island_set_per_side_and_keeps_its_texels():
    """One chart laying the sphere's front and back over each other: unsplit, most island texels are claimed by
    both sides and keep no point; split by side, both sides get their own islands, most island texels keep a
    point, and every kept texel's point maps back within 1 texel (baking and lookup pick the same side)."""
    xyz = _sphere()
    whole, _ = _planar_island_atlas(xyz, split=False)
    split, hist = _planar_island_atlas(xyz, split=True)
    assert split.n == 2 and split.n_net == 1 and 0.4 < hist["sides"]["reversed"] < 0.6
    assert bool(split.layout.has_islands.all())
    kept_whole = float(torch.isfinite(whole.texel_points()).all(-1).sum() / whole.layout.island_pixels.sum())
    kept_split = float(torch.isfinite(split.texel_points()).all(-1).sum() / split.layout.island_pixels.sum())
    assert kept_whole < 0.4 and kept_split > 0.8, (kept_whole, kept_split)
    share, count = _round_trip(split)
    assert share == 1.0 and count > 2 * int(torch.isfinite(whole.texel_points()).all(-1).sum())
    # front and back read different texels (unsplit: the same)
    front, back = torch.tensor([[0.1, 0.2, 0.75]]), torch.tensor([[0.1, 0.2, -0.75]])
    px = [split.atlas_pixel_coords(p)[1] for p in (front, back)]
    assert float((px[0] - px[1]).norm()) > 5
    assert torch.isfinite(split.lookup(torch.tensor([[1e6, -1e6, 3.0], [0.0, 0.0, 0.0], [0.0, 0.0, 1e-30]]))).all()


def test_a_chart_with_few_reversed_samples_stays_whole():
    """island_sides_min_share above the chart's reversed share: the chart is not split, and the atlas is the one of
    one side per chart (no side rule, the same layout charts as networks)."""
    atlas, hist = _planar_island_atlas(_sphere(4000), split=True, min_share=0.9)
    assert atlas.sides is None and atlas.n == atlas.n_net == 1 and hist["sides"]["split"] == 0
    assert hist["sides"]["reversed"] == 0.0 and atlas.meta()["version"] == 7


def test_a_split_atlas_saves_and_loads_bit_for_bit():
    xyz = _sphere(4000)
    atlas, _ = _planar_island_atlas(xyz, split=True)
    meta = check_saves_and_loads_bit_for_bit(atlas, xyz, _PlanarMap(), "atlas/sides/majority",
                                             np.array([1.0, -1.0], np.float32))
    assert meta["version"] == 7 and meta["n"] == 1 and "sides" in meta


def test_a_quick_fit_split_by_side_runs_end_to_end():
    """A quick island fit to the torus with `island_sides`: twice the layout charts of the networks, finite
    history, and every kept texel maps back within 1 texel."""
    from core.atlas.fit import fit_atlas

    xyz, rgb = synthetic_samples("torus", 4000, seed=4)
    quick = dict(steps=150, batch=256, uv_batch=32, distortion_batch=64, width_map=32, depth_map=2, width_chart=16,
                 depth_chart=1, log_every=1000, eval_samples=256, charts="4", layout="islands", image_size=128,
                 island_sides_neighbours=128, island_sides=True, island_sides_min_share=0.0, island_pieces=False)
    threads = torch.get_num_threads()
    torch.set_num_threads(1)
    try:
        atlas, hist = fit_atlas(xyz, rgb, AtlasConfig(**quick), quiet=True)
    finally:
        torch.set_num_threads(threads)
    assert atlas.n_net == 4 and atlas.n == 8 and all(np.isfinite(hist["psnr"]))
    assert 0.0 <= hist["sides"]["reversed"] <= 0.5
    share, count = _round_trip(atlas)
    assert share == 1.0 and count > 1000
