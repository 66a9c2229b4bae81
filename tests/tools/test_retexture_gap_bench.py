"""tools.bench.retexture_gap: the chart map's derivative across the samples' slab against along it."""
import pytest
import torch

from tools.bench.retexture_gap import normal_ratio


class _PlaneMap:
    """Samples on a noisy slab around z = 0 and the map u = x + a z, v = y + b z (one chart): along the surface
    the coordinates change at rate 1, across it at rate |(a, b)|."""

    def __init__(self, a: float, b: float):
        g = torch.Generator().manual_seed(0)
        xy = torch.rand(6000, 2, generator=g)
        z = 0.005 * torch.randn(6000, 1, generator=g)
        self.bake_samples = torch.cat([xy, z], 1)
        self.a, self.b = a, b

    def chart_uv(self, x, placed=True):
        uv = torch.stack([x[:, 0] + self.a * x[:, 2], x[:, 1] + self.b * x[:, 2]], -1)
        return torch.ones(x.shape[0], 1), uv[:, None]


@pytest.mark.parametrize("a,b", [(0.0, 0.0), (1.0, 0.0), (0.6, 0.8), (3.0, 4.0)])
def test_normal_ratio_reads_the_slope_across_the_slab(a, b):
    ratio = normal_ratio(_PlaneMap(a, b), max_samples=500)
    # the PCA normal of a 0.5 cm slab over a 1 m square is z to within a degree or so
    assert abs(ratio - (a * a + b * b) ** 0.5) < 0.05 * max(1.0, (a * a + b * b) ** 0.5), ratio


def test_lookup_stats_place_the_lookups_without_a_surface_point():
    """On a tiny card model: shares lie in [0, 1]; a lookup in the padding between islands is one without a point; with the texel map
    emptied every lookup is one without a point, and the stored sample nearest each lies near it and lands within a
    few texels of it through the same chart."""
    import math

    from tests.helpers.tiny import tiny_bundle
    from tools.bench.retexture_gap import lookup_stats

    bundle, _, test = tiny_bundle("fast")
    atlas = bundle.atlas
    spacing = float(bundle.meta["atlas_fit"]["spacing"])
    st = lookup_stats(bundle, test, spacing)
    for k in ("no_point", "far", "off_island", "no_point_other_chart", "bad_other_chart_near"):
        assert 0.0 <= st[k] <= 1.0, (k, st)
    # padding texels hold no point: a lookup off every island is one without a point (a grid atlas has none)
    assert st["off_island"] <= st["no_point"] and (atlas.islands or st["off_island"] == 0.0)
    saved = atlas.texel_xyz.clone()
    try:
        atlas.texel_xyz.fill_(float("nan"))
        empty = lookup_stats(bundle, test, spacing)
    finally:
        atlas.texel_xyz.copy_(saved)
    assert empty["no_point"] == 1.0 and empty["far"] == 0.0
    assert empty["bad_other_chart_near"] == 0.0  # no texel holds a point: no other chart can help
    assert math.isfinite(empty["no_point_sample_dist"]) and empty["no_point_sample_dist"] < 5.0, empty
    assert empty["no_point_sample_texels"] < 5.0 and empty["no_point_other_chart"] < 0.5, empty
