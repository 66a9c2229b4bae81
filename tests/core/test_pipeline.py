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
                            eval_samples=256, layout="islands", log_every=10_000, footprint_lambdas="0.5,4")
    fit_atlas_stage(b, split, atlas_cfg, show_progress=False)
    assert torch.isfinite(b.atlas.packed_image()).all()
    fp = b.meta["atlas_fit"]["footprint"]
    assert fp["pixels"] > 0
    # the refit's λ chosen from the held-out fourth view, each candidate's score kept with the model
    assert fp["lambda"] in (0.5, 4.0) and set(fp["holdout_psnr"]) == {"0.5", "4"}
    # a bad candidate list fails before any fitting
    with pytest.raises(InputError, match="footprint-lambdas"):
        fit_atlas_stage(b, split, AtlasConfig(device="cpu", footprint_lambdas="1,-2"), show_progress=False)


def test_a_capture_with_its_own_cameras_per_frame_and_a_lens_fits_like_its_pinhole_twin(tmp_path):
    """End to end through visual hull, neighbour search, training and stage 2's footprints: a capture whose frames
    have their own intrinsics and image sizes, half of them seen through a distorting lens, loads onto one
    pinhole camera and fits like the same views taken through that camera."""
    from core.images.cameras import Intrinsics
    from core.images.dataset import load_dataset
    from core.images.metrics import psnr
    from core.points.render import render_frame
    from tests.helpers.synthetic import fibonacci_cameras, render_split, write_capture
    from tests.helpers.tiny import fit_tiny

    k = Intrinsics(40.0, 38.0, 17.0, 15.5)  # 32 x 32
    cams, test_cams = fibonacci_cameras(8, seed=0), fibonacci_cameras(2, seed=5)
    lens = (-0.2, 0.04, 0.0, 0.002, -0.001)
    own = Intrinsics(60.0, 57.0, 27.5, 25.25)  # 1.5 x the focal lengths, 52 x 52 pixels
    views = [render_split("card", cams[i:i + 1], 52 if i % 2 else 32, intrinsics=own if i % 2 else k,
                          lens=None if i % 4 < 2 else lens, split=f"v{i}") for i in range(8)]
    keys = {f"v{i}": {"fl_x": v.intrinsics.fx, "fl_y": v.intrinsics.fy, "cx": v.intrinsics.cx,
                      "cy": v.intrinsics.cy, "w": v.width, "h": v.height,
                      **(dict(zip(("k1", "k2", "k3", "p1", "p2"), lens)) if i % 4 >= 2 else {})}
            for i, v in enumerate(views)}
    test = render_split("card", test_cams, 32, intrinsics=k, split="test")
    write_capture(tmp_path / "mixed", [test, *views], frame_keys=lambda split, i: keys.get(split, {}),
                  top_keys={"train_filenames": [f"images/v{i}_0.png" for i in range(8)]})
    twin = render_split("card", cams, 32, intrinsics=k)
    write_capture(tmp_path / "pinhole", [twin, test])
    scores, metas = [], []
    for name in ("mixed", "pinhole"):
        data = load_dataset(tmp_path / name, required=("train", "test"))
        assert data["train"].focal == k and data["test"].focal == k
        metas.append(data["train"].meta.get("resampled"))
        bundle = fit_tiny("fast", data["train"], data["test"], steps=40, atlas_steps=10)
        scores.append(sum(psnr(render_frame(bundle.model, data["test"].c2w[i], 32, 32, k)["rgb"].detach(),
                               data["test"].images[i]) for i in range(2)) / 2)
    assert metas == [{"frames": 6, "min_coverage": 1.0, "undistorted": 4}, None]
    assert abs(scores[0] - scores[1]) < 1.0 and min(scores) > 15.0, scores
