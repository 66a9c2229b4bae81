"""Metrics against known values and a brute-force SSIM, and the evaluation loop every command shares."""
import math

import pytest
import torch

from core.images.metrics import (blank_floor, mean_scores, object_mask, psnr, score_frame, score_views, ssim)


def test_psnr_known_values():
    gt = torch.full((4, 5, 3), 0.5)
    assert psnr(gt + 0.1, gt) == pytest.approx(20.0, abs=1e-4)          # mse 0.01
    assert psnr(gt + 0.01, gt) == pytest.approx(40.0, abs=1e-3)         # mse 1e-4
    assert psnr(torch.zeros(2, 2, 3), torch.ones(2, 2, 3)) == pytest.approx(0.0)
    assert psnr(gt, gt) == 99.0                                          # the cap of a perfect frame
    # the mask selects pixels: half the frame wrong by 0.1, the other half by 0.3
    pred = gt.clone()
    pred[:2] += 0.1
    pred[2:] += 0.3
    rows = torch.arange(4)[:, None].expand(4, 5)
    assert psnr(pred, gt, rows < 2) == pytest.approx(20.0, abs=1e-4)
    assert psnr(pred, gt, rows >= 2) == pytest.approx(-10 * math.log10(0.09), abs=1e-4)
    assert psnr(pred, gt) == pytest.approx(-10 * math.log10(0.05), abs=1e-4)  # mean of 0.01 and 0.09
    assert math.isnan(psnr(pred, gt, torch.zeros(4, 5, dtype=torch.bool)))


def test_object_mask_is_the_union_of_both_foregrounds():
    gt = torch.tensor([[1.0, 0.0], [0.0, 0.6]])
    pred = torch.tensor([[0.0, 0.9], [0.0, 0.2]])
    assert object_mask(gt, pred).tolist() == [[True, True], [False, True]]
    assert object_mask(gt, None).tolist() == [[True, False], [False, True]]


def _ssim_reference(x, y, window=11, sigma=1.5):
    """SSIM written out per window position and channel (Wang et al. 2004, Gaussian window, valid positions)."""
    c1, c2 = 0.01 ** 2, 0.03 ** 2
    r = torch.arange(window, dtype=torch.float64) - (window - 1) / 2
    g = torch.exp(-r ** 2 / (2 * sigma ** 2))
    w = torch.outer(g, g) / torch.outer(g, g).sum()
    h, wd, ch = x.shape
    vals = []
    for i in range(h - window + 1):
        for j in range(wd - window + 1):
            for c in range(ch):
                a, b = x[i:i + window, j:j + window, c].double(), y[i:i + window, j:j + window, c].double()
                ma, mb = (w * a).sum(), (w * b).sum()
                va, vb = (w * a * a).sum() - ma ** 2, (w * b * b).sum() - mb ** 2
                cov = (w * a * b).sum() - ma * mb
                vals.append(((2 * ma * mb + c1) * (2 * cov + c2)) / ((ma ** 2 + mb ** 2 + c1) * (va + vb + c2)))
    return float(torch.stack(vals).mean())


def test_ssim_known_values_and_brute_force():
    g = torch.Generator().manual_seed(0)
    x = torch.rand(14, 13, 3, generator=g)
    assert float(ssim(x, x)) == pytest.approx(1.0, abs=1e-6)
    # constant images: variances vanish, SSIM = (2ab + c1) / (a² + b² + c1)
    a, b = 0.5, 0.25
    want = (2 * a * b + 1e-4) / (a * a + b * b + 1e-4)
    assert float(ssim(torch.full((12, 12, 3), a), torch.full((12, 12, 3), b))) == pytest.approx(want, rel=1e-5)
    y = (x + 0.2 * torch.rand(14, 13, 3, generator=g)).clamp(0, 1)
    assert float(ssim(x, y)) == pytest.approx(_ssim_reference(x, y), abs=1e-5)
    assert float(ssim(x, 1 - x)) < 0  # anti-correlated structure
    # batched and unreduced
    m = ssim(torch.stack([x, x]), torch.stack([x, y]), reduce=False)
    assert m.shape == (2, 4, 3) and float(m[0].mean()) == pytest.approx(1.0, abs=1e-6)


def test_score_views_scores_each_view_and_passes_extras():
    gt = torch.full((3, 4, 4, 3), 0.5)
    alphas = torch.zeros(3, 4, 4)
    alphas[:, :2] = 1.0
    seen = []

    def render(i):
        seen.append(i)
        rgb = gt[i].clone()
        rgb[:2] += 0.1 * (i + 1)  # object pixels wrong by 0.1·(i+1), background exact
        return {"rgb": rgb, "alpha": alphas[i], "extra": {"seconds": float(i)},
                "also": {"atlas_{}": gt[i] + 0.1}}
    rows = score_views(render, gt, alphas, views=[0, 2])
    assert seen == [0, 2] and len(rows) == 2
    assert rows[0]["psnr_object"] == pytest.approx(20.0, abs=1e-4)
    assert rows[1]["psnr_object"] == pytest.approx(-10 * math.log10(0.09), abs=1e-4)
    assert rows[0]["psnr"] == pytest.approx(-10 * math.log10(0.005), abs=1e-4)
    assert rows[1]["seconds"] == 2.0 and rows[0]["atlas_psnr"] == pytest.approx(20.0, abs=1e-4)
    assert rows[0]["atlas_psnr_object"] == pytest.approx(20.0, abs=1e-4)
    mean = mean_scores(rows, ("psnr_object", "seconds"))
    assert mean == pytest.approx({"psnr_object": (20.0 - 10 * math.log10(0.09)) / 2, "seconds": 1.0}, abs=1e-4)
    # a view without object pixels has no object PSNR and is left out of the mean
    row = score_frame(gt[0], gt[0], torch.zeros(4, 4))
    assert math.isnan(row["psnr_object"])
    assert mean_scores([row, {"psnr_object": 30.0}], ("psnr_object",))["psnr_object"] == 30.0


def test_blank_floor_scores_a_white_frame():
    gt = torch.ones(2, 4, 4, 3)
    gt[:, :2] = 0.0  # object: black, half the frame
    alphas = torch.zeros(2, 4, 4)
    alphas[:, :2] = 1.0
    floor = blank_floor(gt, alphas)
    assert floor["psnr"] == pytest.approx(-10 * math.log10(0.5), abs=1e-4)
    assert floor["psnr_object"] == pytest.approx(0.0, abs=1e-6)
