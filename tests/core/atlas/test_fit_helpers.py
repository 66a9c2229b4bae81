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
