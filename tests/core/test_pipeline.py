"""Stage glue: refreshing the texel map of a fitted model keeps its charts and texture."""
import copy

import pytest
import torch

from core.atlas.config import AtlasConfig
from core.bundle import Bundle
from core.pipeline import refresh_texel_map
from core.util.errors import InputError
from tests.helpers.tiny import tiny_bundle


def test_refresh_texel_map_recomputes_only_the_map():
    bundle, train, _ = tiny_bundle("card")
    b = copy.deepcopy(bundle)  # the cached tiny model is shared: work on a copy
    tex, image = b.atlas.textures.detach().clone(), b.atlas.packed_image().clone()
    b.atlas.texel_xyz.fill_(float("nan"))
    info = refresh_texel_map(b, train, AtlasConfig(device="cpu"))
    tp = b.atlas.texel_points()
    assert info["valid_texels"] == int(torch.isfinite(tp).all(-1).sum()) > 50
    assert torch.equal(b.atlas.textures, tex) and torch.equal(b.atlas.packed_image(), image)
    assert torch.equal(torch.isfinite(tp), torch.isfinite(bundle.atlas.texel_points()))
    assert torch.allclose(tp.nan_to_num(0), bundle.atlas.texel_points().nan_to_num(0), atol=1e-5)
    assert b.meta["atlas_fit"]["texel_map"] == "splat"
    with pytest.raises(InputError, match="no atlas"):
        refresh_texel_map(Bundle(model=bundle.model, meta={}), train, AtlasConfig(device="cpu"))


def test_stage2_refits_the_texture_for_pixel_filtered_lookups():
    bundle, _, _ = tiny_bundle("card")
    fp = bundle.meta["atlas_fit"]["footprint"]
    assert fp["pixels"] > 100 and fp["rmse_after"] < fp["rmse_before"]


def test_stage2_runs_on_a_capture_camera_with_intrinsics():
    """A capture's camera (fx != fy, off-centre principal point, non-square image) reaches stage 2 as Intrinsics:
    the island atlas's resolution and the footprint refit use one focal scale, sqrt(fx * fy)."""
    from core.images.cameras import Intrinsics
    from core.pipeline import fit_atlas_stage
    from tests.helpers.synthetic import fibonacci_cameras, render_split

    bundle, _, _ = tiny_bundle("fast")
    b = copy.deepcopy(bundle)
    k = Intrinsics(40.0, 34.0, 17.0, 14.5)
    split = render_split("card", fibonacci_cameras(4, seed=0), 36, height=28, intrinsics=k)
    atlas_cfg = AtlasConfig(device="cpu", charts="4", steps=10, texture_steps=5, texture_res=16, batch=256,
                            uv_batch=32, distortion_batch=32, width_chart=16, depth_chart=2, width_map=16, depth_map=2,
                            eval_samples=256, layout="islands", log_every=10_000)
    fit_atlas_stage(b, split, atlas_cfg, show_progress=False)
    assert torch.isfinite(b.atlas.packed_image()).all()
    assert b.meta["atlas_fit"]["footprint"]["pixels"] > 0
