"""`pointgt eval`: the shared evaluation loop on a model file and a dataset folder, with the blank-frame floor."""
import json

import pytest
import torch

from core.bundle import load_bundle, save_bundle
from core.images.dataset import load_split
from core.images.metrics import psnr
from core.points.model import TRAIN_BACKGROUND
from core.points.train import evaluate
from tests.helpers.synthetic import write_split
from tests.helpers.tiny import tiny_bundle
from tools.cli import main


def test_eval_reports_the_training_figures_and_the_blank_floor(tmp_path, capsys):
    bundle, _, test = tiny_bundle("fast")
    save_bundle(tmp_path / "m.pgt", bundle)
    root = write_split(tmp_path / "data", test)
    out = tmp_path / "eval.json"
    assert main(["eval", str(tmp_path / "m.pgt"), str(root), "--device", "cpu", "--json", str(out)]) == 0
    res = json.loads(out.read_text())
    split = load_split(root, "test")
    assert res["views"] == len(split) == len(res["per_view"]) and res["split"] == "test"
    # the same loop as training's evaluation of the same model on the same images
    want = evaluate(load_bundle(tmp_path / "m.pgt", device="cpu").model, split, range(len(split)), TRAIN_BACKGROUND)
    for k in ("psnr", "psnr_object", "ssim"):
        assert res[k] == pytest.approx(want[k], abs=1e-9), k
        assert res[k] == pytest.approx(sum(r[k] for r in res["per_view"]) / len(split), abs=1e-9)
    blank = torch.ones_like(split.images[0])
    floor = [psnr(blank, split.images[i]) for i in range(len(split))]
    assert res["blank_frame_psnr"] == pytest.approx(sum(floor) / len(floor), abs=1e-9)
    assert res["psnr"] > res["blank_frame_psnr"] and all(r["seconds"] > 0 for r in res["per_view"])
    assert f"PSNR {res['psnr']:.2f} dB" in capsys.readouterr().out
