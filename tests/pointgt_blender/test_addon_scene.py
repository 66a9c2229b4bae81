"""The add-on in a Blender scene with other objects: duplicates, the non-blocking preview, a self-contained
.blend, warnings and the surface proxy. One Blender subprocess (scene_script.py) runs every step with the tiny
card model."""
from __future__ import annotations

import os
from pathlib import Path

import numpy as np
import pytest
from PIL import Image

from core.modelfile import load_pgt, save_pgt

from tests.helpers.blender import addon_setup, image_strip, run_script, step_result

pytestmark = pytest.mark.blender
HERE = Path(__file__).parent


@pytest.fixture(scope="module")
def record(tmp_path_factory):
    tmp = tmp_path_factory.mktemp("scene")
    s = addon_setup(tmp)
    model, work = s.model, s.work
    arrays, meta = load_pgt(model)
    # attention goes to the background only
    arrays["net/bg_logit"] = np.array(np.asarray(arrays["net/bg_logit"], dtype=np.float32) + np.float32(60.0),
                                      dtype=np.float32, ndmin=1).reshape(np.shape(arrays["net/bg_logit"]))
    blank = save_pgt(tmp / "blank.pgt", arrays, meta, backup=False,
                     allow_nonfinite=[n for n in arrays if n.startswith("atlas/texel")])
    r = run_script(HERE / "scene_script.py", [str(s.zip_path), str(model), str(blank), str(work)], s.env, tmp)
    if os.environ.get("POINTGT_DOC_IMAGES"):  # docs/addon.md shows these frames
        out = Path(os.environ["POINTGT_DOC_IMAGES"])
        image_strip([work / "proxy_rest.png", work / "proxy_posed.png"], out / "addon_proxy_paint_and_rig.png")
        image_strip([work / "scene_only.png", work / "composite.png"], out / "addon_composite_with_scene.png")
    return {"r": r, "work": work, "model": model, "tmp": tmp, "env": s.env}


def _get(record, step):
    return step_result(record["r"], step)


def test_duplicates_and_moves_leave_the_atlas_bit_identical(record):
    _get(record, "scene")
    r = _get(record, "duplicates")
    assert r["identical"], f"the atlas changed by up to {r['max_diff']}"
    assert r["transfers"] == 0
    assert r["renders"] >= 3  # each object's preview was rendered, into its own image
    assert len(set(r["previews"])) == 3 and None not in r["previews"], r["previews"]
    assert r["owners"] == r["names"]
    assert sorted(r["shared"]) == sorted(r["names"][1:])  # the panel shows who shares the atlas
    assert r["undo_steps"] >= 4 and r["undo_identical"] and r["undo_transfers"] == 0, r  # undo changes no texel


def test_make_atlas_single_user_copies_it_bit_identical(record):
    r = _get(record, "duplicates")
    assert r["single_user"] == ["FINISHED"] and r["own_differs"] and r["own_identical"] and r["own_packed"]
    assert r["shared_after"] == [r["names"][2]]  # only the linked duplicate still shares the original's atlas


def test_handlers_only_mark_dirty_and_the_preview_renders_coarse_to_fine_when_idle(record):
    r = _get(record, "nonblocking")
    b = r["batch"]
    assert b["requests"] >= 10 and b["rendered"] == 0 and b["levels"] == 0  # a batch of calls renders nothing
    assert r["handler_calls"] >= 10 and r["handler_max_ms"] <= 100.0, r["handler_max_ms"]
    assert r["levels"] == [[64, 48], [128, 96]]
    assert r["idle"] == {"rendered": 1, "levels": 2, "jobs": 1}  # one job for the whole batch, two levels
    assert r["refining_seen"] and r["level_seen"] and r["final_status"].startswith("Preview 128x96")
    assert r["slices"] >= 4  # the work came in several slices


def test_blocking_preview_updates_and_the_composite_layer_report_progress(record):
    p = _get(record, "scene")["sync_progress"]
    assert len(p) >= 3 and p == sorted(p) and 0.0 < p[0] < 1.0 and p[-1] == 1.0, p
    lp = _get(record, "composite")["layer_progress"]
    assert lp["progress"] == [1.0] and lp["frame"] == 1, lp  # one model: one step, printed to the console


def test_a_new_change_cancels_the_running_preview(record):
    r = _get(record, "nonblocking")
    assert r["cancelled"] == 1
    assert r["mean_x_after_move"] > 0.03  # the preview that finished shows the points after the last move


def test_loud_warnings_for_blank_models_and_bad_poses(record):
    r = _get(record, "warnings")
    assert "renders blank" in r["blank_status"] and "blank.pgt" in r["blank_status"]
    assert "Warning" not in r["good_status"]
    assert "collapsed" in r["collapsed"] and "blew up" in r["exploded"]
    assert "off-camera" in r["off_camera"] and "off-camera" in r["off_camera_render"]
    assert r["back"].startswith("Preview ")


def test_the_blend_renders_without_its_model_file(record):
    r = _get(record, "packed")
    assert r["packed"] and r["packed_size"] == (record["model"]).stat().st_size
    assert r["error_after"] == ""
    a = np.asarray(Image.open(record["work"] / "before.png"))
    b = np.asarray(Image.open(record["work"] / "after.png"))
    assert a.shape == b.shape and np.array_equal(a, b) and a[..., :3].std() > 0.01
    assert r["unpack"] == ["FINISHED"] and r["unpacked_same"]
    assert not r["after_unpack"]["packed"] and r["after_unpack"]["path"].endswith("unpacked.pgt")
    assert r["after_unpack"]["texts"] == []  # nobody uses the packed copy any more
    assert r["repack"] == ["FINISHED"]


def test_chart_outlines_are_drawn_over_the_atlas_only_and_lie_on_the_chart_borders(record):
    r = _get(record, "outlines")
    assert r["draw_handlers"] == 1 and r["off"] and r["other_image"] and r["cached"], r
    assert r["on_grid"] and r["segments"] >= 4 * r["charts"], r  # at least a square per chart
    assert r["bad"] == 0 and r["unit_edges"] == r["expected_edges"] > 0, r  # every border edge, nothing else
    assert r["outlined_charts"] == r["charts"] >= 2, r


def test_surface_proxy_shows_the_atlas_and_paint_through_its_uvs_lands_where_the_render_looks(record):
    r = _get(record, "proxy")
    assert 100 <= r["faces"] <= 4000 and r["triangles"] and r["uv"] == "PointGT atlas"
    assert r["material_image"] == r["atlas"] and r["bound"]
    # the card's charts meshed one by one leave cracks between them; the proxy is one piece (welded seams, filled
    # notches), its open edges down to the card's outline, still manifold for Surface Deform
    c, c0 = r["cracks"], r["cracks_per_chart"]
    assert c0["pieces"] >= 2 and c["pieces"] == 1 and c["most"] == 2, r
    assert c["open_edges"] < 0.7 * c0["open_edges"], r
    assert r["painted_faces"] >= 4 and r["painted_texels"] >= 10
    c, n = r["rest"]
    assert n >= 6 and np.hypot(c[0] - r["rest_expect"][0], c[1] - r["rest_expect"][1]) < 3.0, str(r)


def test_automatic_weights_on_the_proxy_pose_the_neural_render(record):
    r = _get(record, "proxy")
    assert r["parent"] == ["FINISHED"] and r["error"] == ""
    # a 90 degree turn of the right bone: away from the joint the right end turns with it and the left end stays
    # (moves by less than 5 % of what the right end moves: the heat weights of the proxy welded from the islands
    # leak a little); near the joint the heat weights blend (not the stiff segments of Automatic Weights on bare
    # points)
    assert r["right_moved"] > 0.5 and r["right_error"] < 0.05 and r["left_moved"] < 0.05 * r["right_moved"], r
    assert r["blended"] >= 0.05 * r["points"], r
    # at 90 and 45 degrees the paint sits where its surface went in the neural render
    c, n = r["posed90"]
    assert n >= 6, r
    assert np.hypot(c[0] - r["posed90_expect"][0], c[1] - r["posed90_expect"][1]) < 3.0, r
    c, n = r["posed"]
    assert n >= 6, r
    assert np.hypot(c[0] - r["posed_expect"][0], c[1] - r["posed_expect"][1]) < 3.0, r
    assert np.hypot(c[0] - r["rest"][0][0], c[1] - r["rest"][0][1]) > 5.0  # it did move


def test_composite_with_scene_occludes_both_ways_and_casts_the_models_shadow(record):
    r = _get(record, "composite")
    assert r["setup"] == ["FINISHED"] and r["engine"] == "CYCLES"
    _check_composite(r)


def test_composite_with_scene_works_with_eevee_too(record):
    r = _get(record, "composite_eevee")
    assert r["engine"] == "BLENDER_EEVEE"
    _check_composite(r)


def _check_composite(r):
    g = r["box_px"]
    assert g[1] > g[0] + 0.15 and g[1] > g[2] + 0.15, r  # the green box hides the card behind it
    assert r["layer_alpha_at_box"] > 0.5 and np.abs(np.subtract(r["neural_at_box"], g)).max() > 0.1  # card behind
    c, n = r["red"]  # the disc painted through the proxy follows the 45 degree pose
    assert n >= 6 and np.hypot(c[0] - r["red_expect"][0], c[1] - r["red_expect"][1]) < 3.0, r
    # elsewhere the PointGT layer lies over the floor: the frame is the layer composited over the scene alone
    assert r["card_px"] >= 50 and r["card_alpha"] > 0.5 and r["card_diff"] < 0.03, r
    assert r["card_vs_scene_alone"] > 0.1, r
    assert r["shadow_px"] >= 20 and r["lit_px"] >= 100
    assert r["shadow_lum"] < 0.7 * r["lit_lum"], r  # the card's shadow (its proxy) falls on the floor
