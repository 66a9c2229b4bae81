"""Charts cut into layers (core/atlas/layers.py): places a chart map lays over each other with the same orientation
get islands of their own; baking and lookups agree on the layer; files keep the rule."""
import numpy as np
import pytest
import torch

from core.atlas.atlas import Atlas
from core.atlas.layers import ChartLayers, layer_samples
from core.util.errors import InputError, ModelFileError
from tests.core.atlas.test_sides import _planar_island_atlas, _round_trip, _sphere


def _two_sheets(n=6000, gap=0.5, noise=0.003):
    """Two parallel square sheets z = 0 and z = gap, facing the same way: the planar map (x, y) lays them over each
    other with the same orientation, which the side split cannot separate."""
    g = torch.Generator().manual_seed(3)
    xy = torch.rand(n, 2, generator=g) * 1.6 - 0.8
    z = torch.where(torch.arange(n) % 2 == 0, 0.0, gap)
    xyz = torch.cat([xy, z[:, None]], 1) - torch.tensor([0.0, 0.0, gap / 2])
    return (xyz + noise * torch.randn(xyz.shape, generator=g)).float()


def _kept(atlas) -> float:
    return float(torch.isfinite(atlas.texel_points()).all(-1).sum() / atlas.layout.island_pixels.sum())


def test_two_sheets_laid_over_each_other_get_one_layer_each():
    """Without layers most island texels belong to both sheets and keep no point; with them each sheet has its own
    islands, nearly every island texel keeps its point and maps back within 1 texel, and the two sheets' points
    above each other read different texels."""
    xyz = _two_sheets()
    whole, _ = _planar_island_atlas(xyz, split=False)
    cut, _ = _planar_island_atlas(xyz, split=False, layers=True)
    assert whole.n == 1 and cut.n == 2 and cut.layers is not None and cut.layers.src.tolist() == [0, 0]
    assert _kept(whole) < 0.3 and _kept(cut) > 0.85, (_kept(whole), _kept(cut))
    share, count = _round_trip(cut)
    assert share == 1.0 and count > 3 * _round_trip(whole)[1]
    low, high = torch.tensor([[0.1, 0.2, -0.25]]), torch.tensor([[0.1, 0.2, 0.25]])
    (c0, p0), (c1, p1) = cut.atlas_pixel_coords(low), cut.atlas_pixel_coords(high)
    assert int(c0) != int(c1) and float((p0 - p1).norm()) > 5
    # a texel's colour comes from its own sheet: paint one sheet red in the samples, the other blue
    assert int(cut.net_chart(torch.tensor([0, 1])).max()) == 0


def test_layers_and_sides_together_on_the_planar_sphere():
    """The planar map of a sphere (front and back of opposite orientation): layers alone separate them as well as
    the side split does, and both together keep every texel's round trip."""
    xyz = _sphere()
    alone, _ = _planar_island_atlas(xyz, split=False, layers=True)
    both, _ = _planar_island_atlas(xyz, split=True, layers=True)
    assert _kept(alone) > 0.85 and _kept(both) > 0.85
    assert _round_trip(alone)[0] == 1.0 and _round_trip(both)[0] == 1.0
    assert torch.isfinite(both.lookup(torch.tensor([[1e6, -1e6, 3.0], [0.0, 0.0, 0.0], [0.0, 0.0, 1e-30]]))).all()


def test_one_sheet_is_not_cut():
    g = torch.Generator().manual_seed(0)
    xy = torch.rand(4000, 2, generator=g).numpy().astype(np.float64)
    xyz = np.concatenate([xy, np.zeros((4000, 1))], 1)
    final, src = layer_samples(xyz, np.zeros(4000, np.int64), xy * 100.0, 1, spacing=0.01, radius=0.06)
    assert src.tolist() == [0] and (final == 0).all()


def test_small_layers_join_their_neighbours():
    """A chart laid over itself in a small patch only: the patch (fewer samples than min_samples) stays on the
    chart's first layer instead of becoming a sliver island."""
    g = np.random.default_rng(1)
    a = np.concatenate([g.random((4000, 2)), np.zeros((4000, 1))], 1)
    b = np.concatenate([g.random((60, 2)) * 0.05 + 0.5, np.full((60, 1), 0.3)], 1)  # far above, same texels
    link = np.linspace([0.5, 0.5, 0.0], [0.5, 0.5, 0.3], 40)  # connects the patch to the sheet
    xyz = np.concatenate([a, b, link])
    t = xyz[:, :2] * 100.0
    final, src = layer_samples(xyz, np.zeros(len(xyz), np.int64), t, 1, spacing=0.01, radius=0.06, min_samples=200)
    assert src.tolist() == [0]
    final, src = layer_samples(xyz, np.zeros(len(xyz), np.int64), t, 1, spacing=0.01, radius=0.06, min_samples=20)
    assert len(src) == 2 and (final[4000:4060] == 1).mean() > 0.9


def test_layers_save_and_load_bit_for_bit_and_damaged_files_are_refused():
    xyz = _two_sheets(4000)
    atlas, _ = _planar_island_atlas(xyz, split=True, layers=True)
    arrays, meta = atlas.to_arrays(), atlas.meta()
    arrays.update({k: v for k, v in Atlas(1, 16, 2, torch.zeros(3), 1.0).to_arrays().items() if "/net/tex." in k})
    assert meta["version"] == 6 and meta["layers"]
    loaded = Atlas.from_arrays(arrays, meta)
    from tests.core.atlas.test_sides import _PlanarMap
    loaded.tex = _PlanarMap()
    p0, uv0 = atlas.chart_uv(xyz)
    p1, uv1 = loaded.chart_uv(xyz)
    assert torch.equal(p0, p1) and torch.equal(uv0, uv1)
    assert torch.equal(atlas.lookup(xyz), loaded.lookup(xyz))
    for key, value in (("atlas/layers/src", np.array([0, 5], np.int32)),
                       ("atlas/layers/chart", np.full(len(arrays["atlas/layers/chart"]), 9, np.int32)),
                       ("atlas/layers/points", np.full_like(arrays["atlas/layers/points"], np.nan))):
        bad = dict(arrays)
        bad[key] = value
        with pytest.raises(ModelFileError):
            Atlas.from_arrays(bad, meta)
    bad = dict(arrays)
    del bad["atlas/layers/points"]
    with pytest.raises(ModelFileError):
        Atlas.from_arrays(bad, meta)


def test_chart_layers_checks_its_input_and_assigns_finite_points():
    with pytest.raises(InputError):
        ChartLayers([1, 0], np.zeros((0, 3)), np.zeros(0))
    with pytest.raises(InputError):
        layer_samples(np.zeros((5, 3)), np.zeros(4, np.int64), np.zeros((5, 2)), 1, 0.01, 0.06)
    with pytest.raises(InputError):
        layer_samples(np.zeros((5, 3)), np.zeros(5, np.int64), np.zeros((5, 2)), 1, 0.0, 0.06)
    lay = ChartLayers([0, 0], np.array([[0.0, 0, 0], [0, 0, 1]]), np.array([0, 1]))
    pts = torch.tensor([[0.0, 0, 0.1], [0, 0, 0.9], [float("nan"), 0, 0], [1e30, 0, 0]])
    out = lay.assign(pts, torch.zeros(4, dtype=torch.long))
    assert out[:2].tolist() == [0, 1] and bool(((out == 0) | (out == 1)).all())
    p, uv = lay.expand(torch.tensor([[1.0]] * 4), torch.zeros(4, 1, 2), out)
    assert p.shape == (4, 2) and torch.equal(p.sum(-1), torch.ones(4)) and uv.shape == (4, 2, 2)
