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
