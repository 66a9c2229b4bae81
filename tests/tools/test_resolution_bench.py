"""The resolution benchmark (tools/bench/resolution.py): its evaluation on a tiny analytic scene, and end to end
on a tiny library scene (Blender)."""
import json
import math

import pytest
import torch

from tests.helpers.synthetic import fibonacci_cameras, render_split
from tests.helpers.tiny import tiny_bundle
from tools.bench import resolution


def test_specks_count_stray_pixels_away_from_the_object_only():
    gt_alpha = torch.zeros(20, 20)
    gt_alpha[5:10, 5:10] = 1.0
    rgb = torch.ones(20, 20, 3)
    rgb[5:10, 5:10] = 0.2                 # the object itself
    rgb[10:12, 7, 0] = 0.5               # its rim, within one training pixel (2 px)
    rgb[17, 17] = torch.tensor([1.0, 0.85, 1.0])  # a stray speck
    rgb[1, 18] = 0.95                     # too faint to count
    assert resolution.specks(rgb, gt_alpha, 2) == 1
    assert resolution.specks(torch.ones(20, 20, 3), gt_alpha, 2) == 0
    assert resolution.specks(rgb, gt_alpha, 1) == 2  # a narrower rim: the rim's second row counts too


def test_regions_split_the_true_coverage_into_interior_and_silhouette_band():
    gt_alpha = torch.zeros(20, 20)
    gt_alpha[4:14, 4:14] = 1.0
    inner, edge = resolution.region_masks(gt_alpha, 2)
    assert torch.equal(inner.nonzero().amin(0), torch.tensor([6, 6])) and int(inner.sum()) == 36  # 10 - 2·2 = 6²
    assert not bool((inner & edge).any()) and int(edge.sum()) == 14 * 14 - 36  # 2 px either side of the edge
    gt = torch.full((20, 20, 3), 0.5)
    rgb = gt.clone()
    rgb[0, 0] = 0.6  # an error outside both regions is not counted
    assert resolution.region_psnr(rgb, gt, inner) == pytest.approx(100.0)
    rgb[8, 8] = 0.6
    assert resolution.region_psnr(rgb, gt, inner) == pytest.approx(10 * math.log10(36 / 0.01), rel=1e-4)
    assert math.isnan(resolution.region_psnr(rgb, gt, torch.zeros(20, 20, dtype=torch.bool)))


def test_evaluate_scores_native_and_both_upsamplings_on_the_same_views():
    bundle, _, _ = tiny_bundle("fast")
    model = bundle.model
    cams = fibonacci_cameras(2, seed=5)
    low = render_split("card", cams, 32, split="test")  # the preset's training size
    high = render_split("card", cams, 64, split="test")
    cache = {}
    one = resolution.evaluate(model, low, low, 1, "pixels", cache)
    # at 1x the native render is the 1x render and the ground truth upsampled is the ground truth itself
    assert one["psnr_object"] == pytest.approx(one["up_render_psnr_object"])
    assert one["up_gt_psnr"] == 99.0 and len(one["per_view"]) == 2 and one["scale"] == 1.0
    two = resolution.evaluate(model, low, high, 2, "filtered", cache)
    for k in ("psnr", "psnr_object", "up_render_psnr_object", "up_gt_psnr_object", "seconds", "seconds_up"):
        assert math.isfinite(two[k]), k
    assert two["scale"] == pytest.approx(2.0, rel=0.06)
    assert 0 < two["up_gt_psnr_object"] < 99
    assert two["specks"] >= 0 and two["specks_up"] >= 0
    for k in ("native", "up_render", "up_gt"):
        assert math.isfinite(two[f"{k}_interior"]) and math.isfinite(two[f"{k}_edge"]), k
    row = {"scene": "card", "factor": 2, "size": 64, "mode": "filtered", **two}
    table = resolution.markdown([row], "head")
    assert "| card | default | 64² (2x) | filtered |" in table
    assert "2x default fit, filtered: native − upsampled mean" in resolution.summary([row], 2)


@pytest.mark.blender
def test_bench_end_to_end_on_a_tiny_library_scene(tmp_path):
    out = tmp_path / "res.json"
    md = tmp_path / "res.md"
    assert resolution.main(["--work", str(tmp_path / "w"), "--scenes", "tube", "--size", "16", "--factors", "2",
                            "--views-train", "4", "--views-test", "2", "--steps", "3", "--render-mode",
                            "pixels,filtered", "--fit-args", "--zoom-frac 0.5", "--tag", "zoom", "--json", str(out),
                            "--markdown", str(md)]) == 0
    rows = json.loads(out.read_text())["rows"]
    assert [(r["factor"], r["mode"]) for r in rows] == [(1, "pixels"), (1, "filtered"), (2, "pixels"),
                                                        (2, "filtered")]
    assert rows[0]["psnr_object"] == pytest.approx(rows[1]["psnr_object"])  # 1x: every mode the same
    assert (tmp_path / "w" / "tube" / "x2" / "scene.json").exists() and "| tube | zoom | 32² (2x) |" in md.read_text()
    assert (tmp_path / "w" / "tube" / "model_3_zoom.pgt").exists() and all(r["fit"] == "zoom" for r in rows)
    # --train-hires 2 on the same folder: the 2x scene gets its training views, the fit trains from them on
    # levels 32² and 16² (its training size is still 16²), the rows say so
    assert resolution.main(["--work", str(tmp_path / "w"), "--scenes", "tube", "--size", "16", "--factors", "2",
                            "--views-train", "4", "--views-test", "2", "--steps", "3", "--render-mode", "filtered",
                            "--train-hires", "2", "--json", str(out)]) == 0
    rows = json.loads(out.read_text())["rows"]
    assert [(r["factor"], r["fit"]) for r in rows] == [(1, "hires2"), (2, "hires2")]
    assert resolution.train_views(tmp_path / "w" / "tube" / "x2") == 4
    from core.bundle import load_bundle

    meta = load_bundle(tmp_path / "w" / "tube" / "model_3_hires2.pgt", "cpu").meta
    assert meta["scene"]["width"] == 16 and meta["scene"]["train_images"]["width"] == 32
    assert meta["train"]["config"]["train_scales"] == "1,2"
    assert rows[1]["scale"] == pytest.approx(1.0)  # the 2x frame is the finest level's size: rendered as trained


def test_hires_scales_are_the_powers_of_two_that_divide_the_factor_and_the_factor():
    assert [resolution.hires_scales(f) for f in (2, 3, 4, 6, 8, 12)] == ["1,2", "1,3", "1,2,4", "1,2,6", "1,2,4,8",
                                                                         "1,2,4,12"]


def test_step_seconds_times_both_fits_alternating():
    from tests.helpers.tiny import model_config

    cams = fibonacci_cameras(3, seed=1)
    low, high = render_split("sphere", cams, 16), render_split("sphere", cams, 32)
    times = resolution.step_seconds(model_config("fast"), ["--train-scales", "1,2", "--patches", "1",
                                                           "--patch-size", "8", "--threads", "1"],
                                    low, high, low, steps=3, pairs=2)
    assert sorted(times) == ["1x", "hires"] and all(len(v) == 2 and all(t > 0 for t in v) for v in times.values())
