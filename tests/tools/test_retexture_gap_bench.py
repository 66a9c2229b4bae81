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
