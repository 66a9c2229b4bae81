"""tools.bench.view_gap: the object error of a stage-1 model split by region, views grouped by elevation."""
import math

import torch

from tools.bench.view_gap import elevation_deg, markdown, split_rows, summarise, view_row


def _frame():
    gt = torch.ones(8, 8, 3)
    ga = torch.zeros(8, 8)
    ga[2:6, 2:6] = 1.0
    gt[2:6, 2:6] = torch.tensor([0.8, 0.1, 0.1])
    return gt, ga


def test_a_perfect_render_has_no_error_anywhere():
    gt, ga = _frame()
    row = view_row(gt.clone(), ga.clone(), gt, ga)
    assert row["psnr_object"] == 99.0 and row["iou"] == 1.0 and row["pixels"] == 16
    assert all(row["share_" + r] == 0.0 for r in ("both", "missed", "spurious"))
    assert math.isnan(row["base_psnr_object"])


def test_the_error_lands_in_its_region():
    gt, ga = _frame()
    rgb, alpha = gt.clone(), ga.clone()
    alpha[2:4, 2:6] = 0.0                     # half the object not covered, rendered as the background
    rgb[2:4, 2:6] = 1.0
    rgb[0, 0] = torch.tensor([0.0, 0.0, 0.0])  # a spurious dark pixel, covered
    alpha[0, 0] = 1.0
    row = view_row(rgb, alpha, gt, ga, base=gt.clone())
    miss = 8 * (0.2 ** 2 + 0.9 ** 2 + 0.9 ** 2)
    assert math.isclose(row["share_missed"], miss / (miss + 3.0), rel_tol=1e-5)
    assert math.isclose(row["share_spurious"], 3.0 / (miss + 3.0), rel_tol=1e-5)
    assert row["share_both"] == 0.0
    assert math.isclose(row["iou"], 8 / 17) and row["pixels"] == 17
    assert row["base_psnr_object"] == 99.0 and row["psnr_object"] < 10.0


def test_elevation_of_cameras_above_below_and_at_the_origin():
    m = torch.eye(4)
    m[:3, 3] = torch.tensor([1.0, 0.0, 1.0])
    assert math.isclose(elevation_deg(m), 45.0, abs_tol=1e-9)
    m[:3, 3] = torch.tensor([0.0, 0.0, -2.0])
    assert math.isclose(elevation_deg(m), -90.0)
    assert elevation_deg(torch.eye(4)) == 0.0


def test_rows_of_a_trained_residual_unet_are_finite_and_grouped():
    from core.points.train import TrainConfig, fit_points
    from tests.helpers.synthetic import fibonacci_cameras, render_split
    from tests.helpers.tiny import model_config

    split = render_split("card", fibonacci_cameras(4, seed=0), 32)
    cfg = TrainConfig(steps=10, patches=1, patch_size=16, eval_every=1e9, eval_views=1, device="cpu", threads=1,
                      prune_every=0, clone_every=0)
    model, _ = fit_points(split, split, model_config("fast", decoder="unet"), cfg, show_progress=False)
    rows = split_rows(model, split, grazing_deg=90.0)  # every view grazing
    assert len(rows) == 4 and all(r["group"] == "grazing" for r in rows)
    for r in rows:
        assert math.isfinite(r["psnr_object"]) and math.isfinite(r["base_psnr_object"])
        assert math.isclose(sum(r["share_" + k] for k in ("both", "missed", "spurious")), 1.0, rel_tol=1e-5)
    s = summarise(rows)
    assert set(s) == {"grazing", "all"} and s["all"]["views"] == 4
    assert math.isclose(s["all"]["psnr_object"], sum(r["psnr_object"] for r in rows) / 4)
    text = markdown({"splits": {"train": {"summary": s}}})
    assert text.count("| train, ") == 2
