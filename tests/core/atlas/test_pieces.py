"""Charts cut into pieces where their map overlaps itself (core/atlas/pieces.py): a ramp winding one and a half turns
under a map that projects it straight down (its last half turn laid over its first with the same orientation, which
the side split cannot separate) is cut so that no texel holds both layers, lookups and baking agree, and the atlas
saves and loads bit for bit; a map that only compresses is not cut; bad piece tables are refused."""
import math

import numpy as np
import pytest
import torch

from core.atlas.atlas import Atlas
from core.atlas.config import AtlasConfig
from core.atlas.pieces import ChartPieces, chart_pieces, solve_columns
from core.util.errors import InputError
from tests.helpers.atlas_files import check_saves_and_loads_bit_for_bit


class _DownMap(torch.nn.Module):
    """t(x) = (x, y) / 2 + 1/2 for one chart: [M, 3] -> [M, 1, 2] (a projection along z)."""

    def forward(self, xn):
        return (0.5 * xn[:, None, :2] + 0.5).contiguous()


def _ramp(n=12000, turns=1.5, seed=0):
    """Samples [n, 3] of a ramp r in [0.55, 0.95], angle a in [0, 2 pi turns), rising 0.3 per turn, and a [n]."""
    g = torch.Generator().manual_seed(seed)
    a = torch.rand(n, generator=g, dtype=torch.float64) * 2 * math.pi * turns
    r = 0.55 + 0.4 * torch.rand(n, generator=g, dtype=torch.float64)
    xyz = torch.stack([r * torch.cos(a), r * torch.sin(a), 0.3 * a / (2 * math.pi) - 0.2], -1)
    return xyz.float(), a


def _ramp_atlas(xyz, pieces: bool):
    """A one-chart island atlas with the projection map, built as fit_atlas builds it (pieces optional)."""
    from core.atlas.fit import chart_pieces_step, island_layout, sample_spacing
    from core.atlas.texture import filled_kernel_texture

    atlas = Atlas(1, 16, 2, torch.zeros(3), 1.0)
    atlas.tex = _DownMap()
    cfg = AtlasConfig(layout="islands", island_sides=False, image_size=128, island_pieces=pieces)
    spacing, area, *elements = sample_spacing(xyz.numpy().astype(np.float64), per_sample=True)
    xn, hist, k_area = atlas.normalise(xyz), {}, math.sqrt(0.5 / area)
    with torch.no_grad():
        probs, uv = atlas.outputs(xn)
        if pieces:
            chart_pieces_step(atlas, xn, probs, uv, elements, area, k_area, 16, cfg, None, spacing, hist)
            probs, uv = atlas.outputs(xn)
        layout, _ = island_layout(probs, uv, elements, area, k_area, 16, cfg, None)
        atlas.set_layout(layout)
        rgb = torch.rand(len(xyz), 3, generator=torch.Generator().manual_seed(0))
        tex, _, _ = filled_kernel_texture(*atlas.place(probs, uv), rgb, layout.size, 1.0, labels=atlas.blur_labels)
        atlas.set_textures(tex)
        atlas.canonicalise_textures()
        atlas.compute_texel_points(xyz, 3 * spacing, 1.0, "splat", 1.0)
    return atlas, hist


def _layers_share_texels(atlas, xyz, a) -> float:
    """Share of the first half turn's samples whose texel also holds a sample one turn above."""
    _, pix = atlas.atlas_pixel_coords(xyz)
    cell = pix.floor().long()
    key = cell[:, 1] * 100000 + cell[:, 0]
    low, high = a < math.pi, a >= 2 * math.pi
    return float(torch.isin(key[low], key[high]).float().mean())


def test_chart_pieces_separate_two_layers_a_map_lays_over_each_other():
    xyz, a = _ramp()
    y = xyz.numpy().astype(np.float64)
    t = (y[:, :2] * 0.5 + 0.5) * 120  # texel coordinates of the projection
    spacing = float(np.median(np.sort(np.linalg.norm(y[:400, None] - y[None], axis=-1), 1)[:, 1]))
    cen, lab = chart_pieces(y, t, spacing)
    assert 2 <= lab.max() + 1 <= 4
    # every patch in the overlapped angles (first and last half turn) lies in a piece apart from the patches one
    # turn above or below it
    ang = np.mod(np.arctan2(cen[:, 1], cen[:, 0]), 2 * math.pi)
    level = np.floor((cen[:, 2] + 0.2) / 0.3 - ang / (2 * math.pi) + 0.5).astype(int)  # which turn
    over = ang < math.pi * 0.9
    first, second = over & (level == 0), over & (level == 1)
    assert first.sum() > 50 and second.sum() > 50
    # (a few patches where the ramp's turns meet, at angle 0, may go either way)
    mixed = sum(min(int((lab[first] == k).sum()), int((lab[second] == k).sum())) for k in range(lab.max() + 1))
    assert mixed <= 0.01 * (first.sum() + second.sum()), mixed


def test_a_map_that_only_compresses_is_not_cut():
    g = np.random.default_rng(1)
    y = np.c_[g.uniform(0, 1, 8000), g.uniform(0, 0.25, 8000), np.zeros(8000)]
    t = np.c_[y[:, 0] * 20, y[:, 1] * 400]  # 20x fewer texels along x than along y: cells many samples long
    cen, lab = chart_pieces(y, t, 0.006)
    assert lab.max() == 0 and len(cen) > 10


def test_chart_pieces_are_finite_on_degenerate_input():
    y = np.zeros((500, 3))
    y[:10] = np.nan
    cen, lab = chart_pieces(y, np.zeros((500, 2)), 0.01)
    assert np.isfinite(cen).all() and (lab == 0).all()
    cen, lab = chart_pieces(np.zeros((0, 3)), np.zeros((0, 2)), 0.01)
    assert len(cen) == 0 and len(lab) == 0
    # a map that spreads its samples over 1e12 texels: the growth's grid stays bounded (no memory blow-up)
    xyz, _ = _ramp(6000)
    y = xyz.numpy().astype(np.float64)
    cen, lab = chart_pieces(y, (y[:, :2] * 0.5 + 0.5) * 1.2e12, 0.01)
    assert len(lab) == len(cen) > 0 and lab.min() == 0 and np.isfinite(cen).all()
    with pytest.raises(InputError):
        chart_pieces(np.zeros((5, 3)), np.zeros((4, 2)), 0.01)
    with pytest.raises(InputError):
        chart_pieces(np.zeros((5, 3)), np.zeros((5, 2)), float("nan"))


def test_a_ramp_cut_into_pieces_keeps_its_layers_apart_and_maps_back():
    xyz, a = _ramp()
    whole, _ = _ramp_atlas(xyz, pieces=False)
    cut, hist = _ramp_atlas(xyz, pieces=True)
    assert whole.pieces is None and cut.pieces is not None and cut.n > cut.n_sub == 1
    assert hist["pieces"]["cut"] == 1 and hist["pieces"]["charts"] == cut.n
    share_whole, share_cut = _layers_share_texels(whole, xyz, a), _layers_share_texels(cut, xyz, a)
    assert share_whole > 0.4 and share_cut < 0.02, (share_whole, share_cut)
    # the texel map: every kept texel's point maps back to its own texel; far more texels keep a point
    tp = cut.texel_points()
    ok = torch.isfinite(tp).all(-1)
    _, pix = cut.atlas_pixel_coords(tp[ok])
    rows, cols = torch.nonzero(ok, as_tuple=True)
    assert float(((pix - torch.stack([cols + 0.5, rows + 0.5], -1)).norm(dim=-1) <= 1.0).float().mean()) == 1.0
    kept = lambda at: float(torch.isfinite(at.texel_points()).all(-1).sum() / at.layout.island_pixels.sum())
    assert kept(cut) > 0.8 > kept(whole), (kept(cut), kept(whole))
    # a baked function of height reads back at the samples (no texel shared by layers 0.3 apart)
    from core.edits.bake import bake
    img = bake(cut, lambda p: (((p[:, 2:3] + 0.2) / 0.6).clamp(0, 1).expand(-1, 3), None))
    got = cut.lookup(xyz, img)[:, 0]
    want = ((xyz[:, 2] + 0.2) / 0.6).clamp(0, 1)
    assert float((got - want).abs().median()) < 0.02
    assert torch.isfinite(cut.lookup(torch.tensor([[1e6, -1e6, 3.0], [0.0, 0.0, 0.0], [1e30, 0.0, -1e30]]))).all()


def test_an_atlas_cut_into_pieces_saves_and_loads_bit_for_bit():
    xyz, _ = _ramp(6000)
    atlas, _ = _ramp_atlas(xyz, pieces=True)
    meta = check_saves_and_loads_bit_for_bit(atlas, xyz, _DownMap(), "atlas/pieces/first",
                                             np.array([0, 1], np.int32))  # two sub-charts for one
    assert meta["version"] == 7 and "pieces" in meta


def test_chart_pieces_expand_moves_only_the_own_sub_charts_probability():
    # sub-chart 0 cut into layout charts 0 and 2 (patches at x = 0 and x = 1), sub-chart 1 whole (layout chart 1)
    cp = ChartPieces(np.array([[0.0, 0, 0], [1.0, 0, 0]]), np.array([0, 0]), np.array([0, 2]), np.array([0, 1]))
    assert cp.n == 3 and cp.sub_of.tolist() == [0, 1, 0] and cp.split == [0]
    probs = torch.tensor([[0.7, 0.3], [0.7, 0.3], [0.2, 0.8], [0.7, 0.3]])
    uv = torch.rand(4, 2, 2)
    world = torch.tensor([[0.1, 0, 0], [0.9, 0, 0], [0.9, 0, 0], [float("nan"), 0, 0]])
    p, u = cp.expand(probs, uv, world)
    assert torch.allclose(p, torch.tensor([[0.7, 0.3, 0.0], [0.0, 0.3, 0.7], [0.2, 0.8, 0.0], [0.7, 0.3, 0.0]]))
    assert torch.equal(u, uv[:, [0, 1, 0]])
    # the point's piece without islands: its sub-chart's largest piece instead
    p, _ = cp.expand(probs, uv, world, has=torch.tensor([True, True, False]))
    assert float(p[1, 0]) == pytest.approx(0.7) and float(p[1, 2]) == 0.0
    for args in ((np.zeros((2, 3)), [0, 0], [0, 2], [0]),            # layout chart 1 belongs to no sub-chart
                 (np.zeros((2, 3)), [0, 1], [0, 0], [0, 1]),          # piece 0 in two sub-charts
                 (np.full((1, 3), np.nan), [0], [0], [0]),
                 (np.zeros((1, 3)), [3], [0], [0])):
        with pytest.raises(InputError):
            ChartPieces(*args)


def test_solve_columns_equals_numpys_solve_with_every_column_at_once():
    """The pieces' per-patch linear maps are solved one right-hand side at a time (numpy's multi-column solve goes
    through OpenBLAS's threaded path per system); the result is numpy's solve up to rounding, for one and several
    columns and for ill-conditioned systems."""
    rng = np.random.default_rng(0)
    A = rng.normal(size=(500, 3, 3))
    A = A @ A.transpose(0, 2, 1) + 1e-6 * np.eye(3)
    for k in (1, 2, 3):
        B = rng.normal(size=(500, 3, k))
        X = solve_columns(A, B)
        assert X.shape == (500, 3, k)
        ref = np.linalg.solve(A, B)
        assert np.allclose(X, ref, rtol=1e-6, atol=1e-9 * np.abs(ref).max())
    with pytest.raises(np.linalg.LinAlgError):
        solve_columns(np.zeros((2, 3, 3)), np.ones((2, 3, 2)))
