"""Live preview, render engine, Image Editor panel and paint transfer of the packaged add-on, in real Blender
subprocesses (own BLENDER_USER_RESOURCES) with a tiny trained card model. One process (render_script.py) runs
every step; a second, fresh process (reload_script.py) renders the saved .blend."""
from __future__ import annotations

import os
from pathlib import Path

import numpy as np
import pytest
import torch
from PIL import Image

from core.bundle import load_bundle
from tests.helpers.blender import addon_setup, image_strip, run_script, step_result

pytestmark = pytest.mark.blender
HERE = Path(__file__).parent
PATCH_CENTRE = np.array([0.45, 0.15, 0.0])  # keep in step with render_script.py
PATCH_RADIUS = 0.15


def patch_mask(model: Path) -> np.ndarray:
    """Atlas texels [A, B] of a disc on the card: texels whose surface point lies in it, and the bilinear
    footprints of surface samples in it (every chart the atlas blends there)."""
    atlas = load_bundle(model, device="cpu").atlas
    tex = atlas.texel_points().numpy()
    mask = np.zeros(tex.shape[:2], bool)
    ok = np.isfinite(tex).all(-1)
    mask[ok] = (np.linalg.norm(tex[ok][:, :2] - PATCH_CENTRE[:2], axis=1) < PATCH_RADIUS) & (np.abs(tex[ok][:, 2]) < 0.1)
    g = np.linspace(-PATCH_RADIUS, PATCH_RADIUS, 25)
    xy = np.stack(np.meshgrid(g, g), -1).reshape(-1, 2)
    xy = xy[np.linalg.norm(xy, axis=1) < PATCH_RADIUS] + PATCH_CENTRE[:2]
    pts = torch.from_numpy(np.c_[xy, np.zeros(len(xy))].astype(np.float32))
    probs, uv = atlas.chart_uv(pts)
    R = atlas.layout.R
    origins = atlas.layout.origins(torch.device("cpu")).numpy().astype(int)
    for c in range(atlas.layout.n):
        inside = ((uv[:, c] > 0) & (uv[:, c] < 1)).all(-1)  # clamped uvs read the chart's edge texels
        use = ((probs[:, c] > 0.05) & inside).numpy()
        t = np.floor(uv[use, c].numpy() * R - 0.5)
        for dc in (0, 1):
            for dr in (0, 1):
                mask[(t[:, 1] + dr).clip(0, R - 1).astype(int) + origins[c, 0],
                     (t[:, 0] + dc).clip(0, R - 1).astype(int) + origins[c, 1]] = True
    return mask


@pytest.fixture(scope="module")
def record(tmp_path_factory):
    tmp = tmp_path_factory.mktemp("render")
    s = addon_setup(tmp)
    model, work = s.model, s.work
    np.save(tmp / "patch.npy", patch_mask(model))
    first = run_script(HERE / "render_script.py", [str(s.zip_path), str(model), str(tmp / "patch.npy"), str(work)],
                        s.env, tmp)
    second = run_script(HERE / "reload_script.py", [str(work / "posed.blend")], s.env, tmp) \
        if (work / "posed.blend").exists() else {"error": "posed.blend was not saved"}
    if os.environ.get("POINTGT_DOC_IMAGES"):  # docs/addon.md shows this test's frames
        _doc_images(work, Path(os.environ["POINTGT_DOC_IMAGES"]))
    return {"r": first, "reload": second, "work": work, "model": model}


def _doc_images(work: Path, out: Path) -> None:
    """Small strips for the docs: the posed animation frames, and the other-camera view of preview paint."""
    image_strip([work / "anim" / f"f_000{f}.png" for f in (1, 2, 3)], out / "addon_patch_follows_pose.png")
    image_strip([work / "anim" / "f_0001.png", work / "other_view.png"], out / "addon_preview_paint_other_view.png")


def _get(record, step):
    return step_result(record["r"], step)


def _png(path: Path) -> np.ndarray:
    return np.asarray(Image.open(path).convert("RGB"), dtype=np.float32) / 255.0


def _centroid(rgb: np.ndarray, colour) -> tuple[np.ndarray, int]:
    """(col, row) pixel-centre centroid and count of the pixels close to `colour` (display space)."""
    near = np.linalg.norm(rgb - np.asarray(colour, np.float32), axis=-1) < 0.45
    rows, cols = np.nonzero(near)
    if not len(rows):
        return np.array([np.nan, np.nan]), 0
    return np.array([cols.mean() + 0.5, rows.mean() + 0.5]), int(near.sum())


def test_without_torch_the_preview_and_render_say_so(record):
    r = _get(record, "torch_missing")
    assert "PyTorch is missing" in r["status"] and r["done"]["card"].startswith("error: ")
    assert "PyTorch is missing" in r["render_error"] and r["torch_loaded"] is False


def test_import_takes_k_from_the_model(record):
    r = _get(record, "scene")
    assert r["import"] == ["FINISHED"] and r["k"] == 8 and r["engine"] == "POINTGT"


def test_painted_atlas_patch_moves_with_the_posed_surface(record):
    r = _get(record, "animation")
    assert r["files"] == ["f_0001.png", "f_0002.png", "f_0003.png"] and r["n_ids"] >= 5
    centres = []
    for f in (1, 2, 3):
        rgb = _png(record["work"] / "anim" / f"f_000{f}.png")
        assert rgb.shape == (48, 64, 3)  # 128 x 96 at 50 %
        c, n = _centroid(rgb, (1.0, 0.0, 0.0))
        assert n >= 8, f"frame {f}: the red patch is not visible ({n} px)"
        want = np.asarray(r["expect"][str(f)])
        assert np.linalg.norm(c - want) < 3.0, (f, c, want)  # where the painted surface went
        centres.append(c)
    assert np.linalg.norm(centres[2] - centres[0]) > 4.0  # it did move


def test_live_preview_updates_only_when_something_changed(record):
    r = _get(record, "live_preview")
    c = r["counts"]
    assert r["size"] == [64, 48] and r["image_name"] == "card preview"
    assert c["after_frame"] >= 1
    assert c["same_frame"] == c["after_frame"]  # the image write and the same frame again: nothing redone
    assert c["next_frame"] == c["same_frame"] + 1 and r["moved"] > 0.05
    assert c["after_paint"] == c["next_frame"] + 1 and r["rebuilt"]  # painting the atlas re-renders
    assert r["status"].startswith("Preview 64x48")


def test_paint_on_preview_lands_in_atlas_and_shows_from_another_camera(record):
    r = _get(record, "paint_preview")
    assert r["result"] == ["FINISHED"] and r["changed_texels"] >= 10 and r["green_pct"] > 0.9
    rgb = _png(record["work"] / "other_view.png")
    c, n = _centroid(rgb, (0.1, 0.9, 0.1))
    assert n >= 4, f"the green square is not visible from the other camera ({n} px)"
    assert np.linalg.norm(c - np.asarray(r["expect"])) < 3.0, (c, r["expect"], r["point"])
    assert r["auto_changed"] >= 4  # painting the preview again transferred by itself on the next update


def test_saved_scene_renders_the_same_frames_in_a_fresh_process(record):
    prep = _get(record, "save_reload_prepare")
    assert prep["model_path"].startswith("//") and prep["before"] == ["f_0002.png", "f_0003.png"]
    r = record["reload"]
    assert "error" not in r, r
    assert r["enabled"] and r["engine"] == "POINTGT" and r["frames"] == ["f_0002.png", "f_0003.png"]
    for name in r["frames"]:
        a = _png(record["work"] / "before" / name)
        b = _png(record["work"] / "frames" / name)
        assert np.array_equal(a, b), name


def test_errors_become_reports_and_keep_earlier_frames(record):
    r = _get(record, "errors")
    assert "NaN" in r["nan_status"] and "NaN" in r["nan_render"] and r["kept"] and r["kept_end"]
    assert "changed the point count" in r["count_status"] and "changed the point count" in r["count_render"]
    assert "gone.pgt" in r["missing_render"] and "not found" in r["missing_render"]
    assert "newer PointGT" in r["newer_status"] and "newer PointGT" in r["newer_render"]
    assert r["recovered"] in ("rendered", "unchanged")


def test_image_editor_panel_and_atlas_ready_for_painting(record):
    calls = _get(record, "draw_ui")["calls"]
    for name in ("pointgt.open_preview", "pointgt.open_atlas", "preview_resolution", "correspondence",
                 "pointgt.refresh_preview", "pointgt.transfer_paint", "render.render", "live_preview"):
        assert name in calls, name
    r = _get(record, "open_atlas")
    assert r["result"] == ["FINISHED"] and r["image"] == "card atlas" and r["ui_mode"] == "PAINT"
    assert r["canvas"] == "card atlas" and r["mode"] == "IMAGE"
