"""`pointgt fit` end to end on a tiny analytic scene written to disk: the summary is measured on every test view."""
import json
import re

import pytest
import torch

from core.bundle import load_bundle
from core.images.dataset import load_split
from core.points.train import evaluate
from tests.helpers.synthetic import fibonacci_cameras, render_split, write_split
from tools.cli import main


def test_fit_reports_psnr_on_all_test_views(tmp_path, capsys):
    root = tmp_path / "card"
    write_split(root, render_split("card", fibonacci_cameras(6, seed=0), 24))
    write_split(root, render_split("card", fibonacci_cameras(3, seed=5), 24, split="test"))
    out = tmp_path / "m.pgt"
    rc = main(["fit", str(root), "--out", str(out), "--stage", "papr", "--steps", "15", "--points", "300",
               "--eval-views", "1", "--no-profile", "--no-progress", "--device", "cpu", "--threads", "1"])
    assert rc == 0
    printed = capsys.readouterr().out
    assert "on all 3 test views" in printed and "on the curve's 1)" in printed
    summary = json.loads(out.with_suffix(".history.json").read_text())["test_all_views"]
    assert summary["views"] == 3
    # the stored figures are the saved model's, over the whole test split
    bundle = load_bundle(out, "cpu")
    with torch.no_grad():
        again = evaluate(bundle.model, load_split(root, "test"), range(3), (1.0, 1.0, 1.0))
    for k in ("psnr", "psnr_object", "ssim"):
        assert abs(again[k] - summary[k]) < 1e-3, k
    assert bundle.meta["train"]["test_all_views"]["views"] == 3


def test_texel_map_refresh_keeps_samples_for_baking_and_a_backup(tmp_path, capsys):
    """`pointgt fit --stage all` then `pointgt atlas M DATA --texel-map-only` on a model whose stored samples
    were dropped (an older file): the refresh stores them again, says so, and keeps the previous file as .bak."""
    from core.bundle import save_bundle

    root = tmp_path / "card"
    write_split(root, render_split("card", fibonacci_cameras(6, seed=0), 24))
    write_split(root, render_split("card", fibonacci_cameras(2, seed=5), 24, split="test"))
    out = tmp_path / "m.pgt"
    assert main(["fit", str(root), "--out", str(out), "--steps", "15", "--points", "300", "--eval-views", "1",
                 "--no-profile", "--no-progress", "--device", "cpu", "--threads", "1", "--atlas-charts", "4",
                 "--atlas-steps", "30", "--atlas-texture-steps", "5", "--atlas-texture-res", "16",
                 "--no-atlas-footprint"]) == 0
    said = re.search(r"stage 2: .* in (\d+) s \(surface samples (\d+) s, atlas (\d+) s\)", capsys.readouterr().out)
    assert said and int(said[1]) >= int(said[3])  # the whole stage, then its parts
    bundle = load_bundle(out, "cpu")
    assert bundle.meta["atlas_fit"]["stage_seconds"] >= bundle.meta["atlas_fit"]["total_seconds"]
    n_samples = len(bundle.atlas.bake_samples)
    assert n_samples > 100
    bundle.atlas.bake_samples = None  # as written before the samples were stored
    save_bundle(out, bundle, backup=False)
    capsys.readouterr()
    assert main(["atlas", str(out), str(root), "--texel-map-only"]) == 0
    assert f"{n_samples} samples kept for baking" in capsys.readouterr().out
    assert len(load_bundle(out, "cpu").atlas.bake_samples) == n_samples
    assert load_bundle(out.with_name("m.pgt.bak"), "cpu").atlas.bake_samples is None


def _altered_card_fit(tmp_path, monkeypatch, alter):
    """A card scene on disk, and (out, `pointgt fit` arguments) of a 10-step decoder-free fit of it whose
    `fit_points` result passes through alter(model, history) first (what the guard could have left behind)."""
    import core.points.train as train_mod

    real_fit = train_mod.fit_points

    def altered_fit(*a, **kw):
        model, hist = real_fit(*a, **kw)
        alter(model, hist)
        return model, hist

    monkeypatch.setattr(train_mod, "fit_points", altered_fit)
    root = tmp_path / "card"
    write_split(root, render_split("card", fibonacci_cameras(6, seed=0), 24))
    write_split(root, render_split("card", fibonacci_cameras(2, seed=5), 24, split="test"))
    out = tmp_path / "m.pgt"
    return out, ["fit", str(root), "--out", str(out), "--steps", "10", "--points", "300", "--eval-views", "1",
                 "--no-profile", "--no-progress", "--device", "cpu", "--threads", "1", "--decoder", "none"]


def test_fit_refuses_to_hand_over_a_blank_model(tmp_path, capsys, monkeypatch):
    """A fit whose model still renders the blank frame (the guard could not recover it) is saved for inspection,
    said loudly, stage 2 skipped, exit 3; --allow-blank carries on."""
    def blank(model, hist):
        with torch.no_grad():
            model.bg_logit.fill_(80.0)  # every ray takes the background

    out, args = _altered_card_fit(tmp_path, monkeypatch, blank)
    assert main(args) == 3
    err = capsys.readouterr().err
    assert "renders the blank frame" in err and "--allow-blank" in err
    meta = load_bundle(out, "cpu").meta
    assert meta["train"]["guard"]["collapsed"] and meta["train"]["guard"]["blank_floor_all_views"]["psnr"] > 0
    assert load_bundle(out, "cpu").atlas is None  # stage 2 did not run on it
    assert main(args + ["--stage", "papr", "--allow-blank"]) == 0


def test_fit_multi_scale_trains_from_the_loaded_size_at_the_coarsest(tmp_path, capsys):
    """`pointgt fit --train-scales 1,2` on 24² images: the model's training size is 12² (its meta, test figures),
    the finest level sets the training footprint; factors that do not divide the images are refused first."""
    from core.points.resolution import training_footprint

    root = tmp_path / "card"
    write_split(root, render_split("card", fibonacci_cameras(6, seed=0), 24))
    write_split(root, render_split("card", fibonacci_cameras(2, seed=5), 24, split="test"))
    out = tmp_path / "m.pgt"
    flags = ["--out", str(out), "--stage", "papr", "--steps", "12", "--points", "300", "--eval-views", "1",
             "--no-profile", "--no-progress", "--device", "cpu", "--threads", "1", "--allow-blank"]
    assert main(["fit", str(root), *flags, "--train-scales", "1,5"]) != 0
    assert "--train-scales" in capsys.readouterr().err and not out.exists()
    assert main(["fit", str(root), *flags, "--train-scales", "1,2", "--train-scale-weights", "1,1"]) == 0
    assert "multi-scale training on levels 24x24, 12x12; training size 12x12" in capsys.readouterr().out
    bundle = load_bundle(out, "cpu")
    scene = bundle.meta["scene"]
    assert (scene["width"], scene["train_images"]["width"]) == (12, 24)
    levels = bundle.meta["train"]["final"]["train_levels"]
    assert sum(levels.values()) == 12 and min(levels.values()) > 0, levels
    native = load_split(root, "train")
    fp = training_footprint(native.c2w, native.focal, bundle.model.xyz.detach())
    assert float(bundle.model.train_footprint) == pytest.approx(fp, rel=1e-5)
    # the decoder's pixel is the training size's (the coarsest level, 12²): twice the finest level's
    assert float(bundle.model.decoder_footprint) == pytest.approx(2 * fp, rel=1e-5)
    gain = bundle.meta["train"]["final"]["interior_gain"]  # measured on the 24² level (the card: no decoder)
    assert (gain is None) == (bundle.model.decoder is None)


def test_fit_train_scales_auto_trains_from_the_finer_images_down_to_the_downscale(tmp_path, capsys):
    """`pointgt fit --downscale 2 --train-scales auto` on 24² images: the training size is 12² as --downscale says,
    stage 1 trains on the pyramid 24² / 12² (two thirds of the steps on 12², or the user's --train-scale-weights);
    auto is the default; with --train-scales off --downscale 2 trains on the 12² images alone, and auto with
    --downscale 1 finds nothing finer (said only when the user asked for auto)."""
    root = tmp_path / "card"
    write_split(root, render_split("card", fibonacci_cameras(6, seed=0), 24))
    write_split(root, render_split("card", fibonacci_cameras(2, seed=5), 24, split="test"))
    flags = ["--stage", "papr", "--steps", "12", "--points", "300", "--eval-views", "1", "--no-profile",
             "--no-progress", "--device", "cpu", "--threads", "1", "--allow-blank"]

    def fit(name, *extra):
        out = tmp_path / f"{name}.pgt"
        assert main(["fit", str(root), "--out", str(out), *flags, *extra]) == 0
        bundle = load_bundle(out, "cpu")
        return bundle, capsys.readouterr().out, bundle.meta["train"]["final"].get("train_levels")

    auto, printed, levels = fit("auto", "--downscale", "2", "--train-scales", "auto")
    assert "multi-scale training on levels 24x24, 12x12; training size 12x12 (--train-scales auto" in printed
    scene, cfg = auto.meta["scene"], auto.meta["train"]["config"]
    assert (scene["width"], scene["train_images"]["width"]) == (12, 24)
    assert (cfg["train_scales"], cfg["train_scale_weights"]) == ("1,2", "1,2")
    assert sorted(levels) == ["1", "2"] and sum(levels.values()) == 12 and min(levels.values()) > 0
    _, printed, levels = fit("weights", "--downscale", "2", "--train-scales", "auto", "--train-scale-weights", "0,1")
    assert levels == {"1": 0, "2": 12}  # auto's levels with the user's shares (all on the coarsest)

    default, printed, levels = fit("default", "--downscale", "2")
    assert "multi-scale training on levels 24x24, 12x12; training size 12x12 (--train-scales auto" in printed
    assert default.meta["train"]["config"]["train_scales"] == "1,2" and sorted(levels) == ["1", "2"]
    plain, printed, levels = fit("plain", "--downscale", "2", "--train-scales", "off")
    assert "multi-scale" not in printed and "train_images" not in plain.meta["scene"] and levels is None
    assert plain.meta["scene"]["width"] == 12 and plain.meta["train"]["config"]["train_scales"] == ""
    native, printed, levels = fit("native", "--train-scales", "auto")
    assert "--downscale 1 leaves no finer images" in printed and levels is None
    assert native.meta["scene"]["width"] == 24 and "train_images" not in native.meta["scene"]
    quiet, printed, levels = fit("quiet")  # the default at the loaded size: nothing finer, nothing said
    assert "multi-scale" not in printed and "finer images" not in printed and levels is None
    assert quiet.meta["train"]["config"]["train_scales"] == ""


def test_fit_warns_of_a_late_decline_and_keeps_it_in_the_model(tmp_path, capsys, monkeypatch):
    """A fit the guard saw lose its object too late to restart (history's guard.declined) is saved and carried on
    (exit 0), with a warning that names the fall and the way out; the model file keeps the reason."""
    def declined(model, hist):
        hist[-1]["guard"]["declined"] = "the object PSNR fell from 24.00 dB at step 400 to 19.50 dB (coverage 0.88)"

    out, args = _altered_card_fit(tmp_path, monkeypatch, declined)
    assert main(args + ["--stage", "papr"]) == 0
    err = capsys.readouterr().err
    assert "fell from 24.00 dB at step 400" in err and "--seed" in err
    assert "fell from 24.00" in load_bundle(out, "cpu").meta["train"]["guard"]["declined"]
