"""`pointgt render` edit flags (deformed points, ids, painted atlas, JSON stats, bad .npy files) and
`pointgt eval-edits` (diagnostics on a tiny model; a Blender smoke run on a tiny scene in a subprocess)."""
from __future__ import annotations

import json
import math
import subprocess
import sys
import textwrap
from pathlib import Path

import numpy as np
import pytest
import torch

from core.bundle import save_bundle
from core.edits.bake import bake
from core.frames.edited import EditConfig, EditState, render_edited
from core.points.render import render_frame
from core.images.png import read_png, write_png
from tests.helpers.tiny import tiny_bundle
from tools.cli import main
from tools.eval_edits import diagnostics, markdown, methods

ROOT = Path(__file__).resolve().parents[2]


@pytest.fixture(scope="module")
def tiny():
    return tiny_bundle("card")


@pytest.fixture(scope="module")
def model_files(tiny, tmp_path_factory):
    """The tiny model as a .pgt, a transforms JSON of its test cameras and a painted atlas PNG."""
    bundle, _, test = tiny
    d = tmp_path_factory.mktemp("render_cli")
    save_bundle(d / "m.pgt", bundle)
    frames = [{"file_path": f"./test/v{i}", "transform_matrix": test.c2w[i].tolist()} for i in range(2)]
    (d / "cams.json").write_text(json.dumps({"camera_angle_x": test.camera_angle_x, "frames": frames}))
    red_right = lambda x: (torch.where((x[:, 0] > 0)[:, None], torch.tensor([1.0, 0.0, 0.0]),
                                       torch.tensor([0.0, 0.0, 1.0])), None)
    write_png(d / "atlas.png", bake(bundle.atlas, red_right).numpy())
    return d


def _render(d, *extra):
    return main(["render", str(d / "m.pgt"), "--cameras", str(d / "cams.json"), "--size", "40", "--device", "cpu",
                 *extra])


def test_render_with_points_ids_and_atlas_writes_frames_and_stats(tiny, model_files, tmp_path):
    bundle, _, _ = tiny
    n = bundle.model.num_points
    keep = np.setdiff1d(np.arange(n), np.arange(0, n, 10))  # remove every 10th point, move the rest, one NaN
    pts = bundle.model.xyz.detach().numpy()[keep] + np.float32([0.05, 0.0, 0.0])
    pts[3] = np.nan
    np.save(tmp_path / "p.npy", pts.astype(np.float32))
    np.save(tmp_path / "i.npy", keep.astype(np.int32))
    out = tmp_path / "frames"
    rc = _render(model_files, "--out", str(out), "--points", str(tmp_path / "p.npy"), "--ids", str(tmp_path / "i.npy"),
                 "--atlas", str(model_files / "atlas.png"), "--correspondence", "naive", "--blend", "threshold",
                 "--json", str(tmp_path / "r.json"))
    assert rc == 0
    stats = json.loads((tmp_path / "r.json").read_text())
    assert stats["frames"] == 2 and stats["edited"] and stats["textured"]
    assert stats["correspondence"] == "naive" and stats["blend"] == "threshold"
    assert stats["points"] == len(keep) and stats["non_finite_points"] == 1
    assert stats["rays"] == 2 * 40 * 40 and 0 < stats["texture_rays"] <= stats["rays_shaded"] <= stats["rays"]
    assert stats["seconds_per_frame"] > 0 and stats["non_finite_lookups_repaired"] >= 0
    img = read_png(out / "v0.png")
    assert img.shape == (40, 40, 4) and np.isfinite(img).all()
    # the painted colours reach the frame: red and blue object pixels, no green from the original texture left
    obj = img[..., 3] > 0.5
    assert obj.sum() > 20
    colour = img[obj, :3]  # straight alpha: the object's own colour, no background mixed in
    # the original texture's green channel spans 0.1..0.9 (0.80 of the pixels pass with the fold rule off, 0.797
    # with it: the tiny card's edge pixels)
    assert (colour[:, 1] < 0.35).mean() > 0.75


def test_render_without_edit_flags_keeps_the_plain_path(tiny, model_files, tmp_path):
    assert _render(model_files, "--out", str(tmp_path / "f"), "--json", str(tmp_path / "r.json")) == 0
    stats = json.loads((tmp_path / "r.json").read_text())
    assert stats["frames"] == 2 and "edited" not in stats
    # The PNG holds straight alpha: composited over white it is the render over white (up to 8-bit rounding).
    bundle, _, test = tiny
    img = read_png(tmp_path / "f" / "v1.png")
    over_white = img[..., :3] * img[..., 3:] + (1 - img[..., 3:])
    ref = render_frame(bundle.model, test.c2w[1], 40, 40, test.focal)["rgb"].numpy()
    assert (img[..., 3] > 0.5).sum() > 20 and (img[..., 3] < 0.5).sum() > 20
    np.testing.assert_allclose(over_white, ref, atol=3 / 255)


@pytest.mark.parametrize("make, message", [
    (lambda p: np.save(p, np.zeros((5, 2), np.float32)), r"must have shape \[M, 3\], got \[5, 2\]"),
    (lambda p: np.save(p, np.zeros((5, 3), np.int32)), "must be floating point, got dtype int32"),
    (lambda p: np.save(p, np.array([{"x": 1}], dtype=object), allow_pickle=True), "pickled data"),
    (lambda p: p.write_bytes(b"not an array"), "not a .npy file"),
    (lambda p: (np.save(p, np.zeros((100, 3), np.float32)), p.write_bytes(p.read_bytes()[:200])), "truncated"),
])
def test_bad_points_files_are_named_errors(model_files, tmp_path, capsys, make, message):
    bad = tmp_path / "bad.npy"
    make(bad)
    assert _render(model_files, "--out", str(tmp_path / "f"), "--points", str(bad)) == 2
    err = capsys.readouterr().err
    assert str(bad) in err and message.split("\\")[0].split("(")[0] in err.replace("\\", "")
    assert not (tmp_path / "f" / "v0.png").exists()


def test_bad_ids_files_are_named_errors(tiny, model_files, tmp_path, capsys):
    n = tiny[0].model.num_points
    np.save(tmp_path / "p.npy", np.zeros((4, 3), np.float32))
    cases = {"float ids": (np.zeros(4, np.float32), "must be integers"),
             "2-D ids": (np.zeros((4, 1), np.int64), "must have shape [M]"),
             "wrong count": (np.zeros(3, np.int64), "expected shape [4]"),
             "out of range": (np.array([0, 1, 2, n]), f"[0, {n - 1}]")}
    for name, (arr, message) in cases.items():
        np.save(tmp_path / "i.npy", arr)
        rc = _render(model_files, "--out", str(tmp_path / "f"), "--points", str(tmp_path / "p.npy"),
                     "--ids", str(tmp_path / "i.npy"))
        err = capsys.readouterr().err
        assert rc == 2, name
        assert message in err and "i.npy" in err, (name, err)
    rc = _render(model_files, "--out", str(tmp_path / "f"), "--points", str(tmp_path / "missing.npy"))
    assert rc == 2 and "missing.npy: --points file does not exist" in capsys.readouterr().err


def test_correspondence_gap_equals_distance_of_surface_point_to_its_ray(tiny):
    """naive − aware = x̂ − Π_ray(x̂) ray by ray, so the measured gap must equal the measured ray distance."""
    bundle, _, test = tiny
    xyz = bundle.model.xyz.detach()
    bent = xyz.clone()
    bent[:, 2] += 0.4 * xyz[:, 0] ** 2  # a non-rigid bend
    atlas = bake(bundle.atlas, lambda x: (x.clamp(0, 1), None))
    for t in (1.0, 0.3):
        # the tangent compression rule pinned: the tiny card's points form a thick cloud (auto would undo all
        # compression, which leaves fewer object rays on this bend); the diagnostics are what is tested here.
        # Rendered at twice the test size: at 40² the sharp temperature leaves only 43-54 rays of foreground
        # weight > 0.5 in this view (the tiny card trained with and without ray jitter), at 80² 162-222
        # (render_mode pixels: every ray traced; an upsampled frame's rays blend the training scale's)
        state = EditState(bundle, points=bent, atlas=atlas, cfg=EditConfig(temperature=t, f_compression="tangent",
                                                                          render_mode="pixels"))
        out = render_edited(state, test.c2w[0], 2 * test.height, 2 * test.width, 2 * test.focal)
        d = diagnostics(out, state)
        assert d["rays_object"] > 50
        assert 0 < d["max_weight"] <= 1
        assert math.isclose(d["corr_gap"], d["ray_dist"], rel_tol=1e-3, abs_tol=1e-6)
        assert math.isclose(d["ray_dist_spacings"] * float(bundle.model.spacing), d["ray_dist"], rel_tol=1e-5)


def test_retexture_against_the_perfect_atlas_measures_the_atlas_alone(tiny):
    """psnr_object_vs_oracle compares the frame with the perfect-atlas frame (same geometry and coverage), so it
    does not move with the ground truth, whose geometry and coverage error sets the floor of the dB gap
    psnr_object_oracle - psnr_object, and it drops when the atlas holds the wrong texture."""
    from types import SimpleNamespace

    from core.edits.procedural import evaluate
    from tools.eval_edits import score_frames

    bundle, _, test = tiny
    spec = {"bbox": {"center": [0.0, 0.0, 0.0], "half_size": [1.0, 1.0, 1.0]}, "texture": {"params": {}}}
    baked = {t: bake(bundle.atlas, lambda x, t=t: (evaluate(t, x, [0.0] * 3, [1.0] * 3, None)[0], None))
             for t in ("stripes", "checker")}
    views = SimpleNamespace(c2w=test.c2w[:2], height=test.height, width=test.width, focal=test.focal,
                            images=test.images[:2], alphas=test.alphas[:2])
    other = SimpleNamespace(**{**vars(views), "images": 1.0 - views.images})  # another ground truth, same alphas
    right = score_frames(EditState(bundle, atlas=baked["stripes"]), views, oracle=("stripes", spec))
    noisy = score_frames(EditState(bundle, atlas=baked["stripes"]), other, oracle=("stripes", spec))
    wrong = score_frames(EditState(bundle, atlas=baked["checker"]), views, oracle=("stripes", spec))
    assert right["psnr_object_vs_oracle"] == noisy["psnr_object_vs_oracle"]
    assert abs(right["psnr_object"] - noisy["psnr_object"]) > 0.2
    assert right["psnr_object_vs_oracle"] > wrong["psnr_object_vs_oracle"] + 3.0


def test_markdown_lists_every_method_and_case():
    meths = methods((1.0, 0.5))
    assert len(meths) == 12 and sum(m.blend == "threshold" for m in meths) == 2
    rows = []
    for pose, mag in (("rest", 0.0), ("bend", 1.0)):
        for i, m in enumerate(meths):
            rows.append({"pose": pose, "magnitude": mag, "edit": m.edit, "correspondence": m.correspondence,
                         "temperature": m.temperature, "blend": m.blend, "psnr": 20.0 + i, "psnr_object": 10.0 + i,
                         "ssim": 0.9, "seconds_per_frame": 0.1, "max_weight": 0.5, "ray_dist": 0.01,
                         "ray_dist_spacings": 0.5, "corr_gap": 0.01, "psnr_object_oracle": 15.0})
    from tools.eval_edits import blend_comparison, retexture_gaps

    result = {"scene_name": "x", "views": 1, "width": 8, "height": 8, "model_points": 10, "point_spacing": 0.1,
              "retexture": "stripes", "seconds_total": 1.0, "rows": rows,
              "blank": [{"pose": p, "magnitude": m, "edit": e, "psnr": 5.0, "psnr_object": 1.0}
                        for p, m in (("rest", 0.0), ("bend", 1.0)) for e in ("geometry", "retexture", "decal")],
              "retexture_gap": retexture_gaps(rows), "blend_comparison": blend_comparison(rows)}
    text = markdown(result)
    assert text.count("| bend | 1 |") == len(meths) + 4 + 1  # every case + the 4 retexture gaps + the ablation row
    assert len(result["retexture_gap"]) == 4 and all(g["gap_psnr_object"] == 0 for g in result["retexture_gap"])
    assert set(result["blend_comparison"]) == {"naive T=1", "deform-aware T=1"}


def test_ablation_rows_per_renderer_and_correspondence():
    meths = methods((1.0,), renderers=("paper", "f-both"), correspondences=("naive", "deform-aware", "deform-gradient"))
    # per renderer: geometry, 3 retexture, 3 decal soft, 3 decal threshold
    assert len(meths) == 2 * 10 and {m.renderer for m in meths} == {"paper", "f-both"}
    rows = [{"pose": p, "magnitude": mg, "edit": m.edit, "correspondence": m.correspondence, "renderer": m.renderer,
             "temperature": m.temperature, "blend": m.blend, "psnr": 20.0, "psnr_object": 10.0 + i, "ssim": 0.9,
             "psnr_object_oracle": 15.0, "seconds_per_frame": 0.5 if m.renderer == "paper" else 0.6}
            for p, mg in (("rest", 0.0), ("stretch", 1.0)) for i, m in enumerate(meths)]
    from tools.eval_edits import ablation_markdown, blend_comparison, retexture_gaps

    text = ablation_markdown({"rows": rows, "temperatures": [1.0], "renderers": ["paper", "f-both"],
                              "correspondences": ["naive", "deform-aware", "deform-gradient"]})
    lines = [ln for ln in text.splitlines() if ln.startswith("| stretch | 1 |")]
    assert len(lines) == 2 and "| f-both |" in lines[1] and lines[1].endswith("| 0.600 |")
    assert "retexture deform-gradient" in text.splitlines()[0]
    # the f-both row's deform-gradient retexture is its own method's figure (index of that method + 10)
    i = next(i for i, m in enumerate(meths) if (m.renderer, m.edit, m.correspondence) == ("f-both", "retexture",
                                                                                         "deform-gradient"))
    assert f"| {10.0 + i:.2f} |" in lines[1]
    gaps = retexture_gaps(rows)
    assert len(gaps) == 6 and {g["renderer"] for g in gaps} == {"paper", "f-both"}
    assert set(blend_comparison(rows)) == {f"{r}{c} T=1" for r in ("", "f-both ")
                                           for c in ("naive", "deform-aware", "deform-gradient")}


SMOKE = textwrap.dedent("""
    import json, sys
    from pathlib import Path
    from tools.scenes.build import make_scene
    from core.atlas.config import AtlasConfig
    from core.bundle import Bundle, save_bundle
    from core.images.dataset import load_split
    from core.pipeline import fit_atlas_stage
    from core.points.train import TrainConfig, fit_points
    from tests.helpers.tiny import model_config
    from tools.cli import main

    d = Path(sys.argv[1])
    make_scene("cloth", d / "scene", size=32, views_train=8, views_val=0, views_test=3, samples=4, log=lambda m: None)
    train, test = load_split(d / "scene", "train"), load_split(d / "scene", "test")
    model, _ = fit_points(train, test, model_config("fast", key_freqs=4),
                          TrainConfig(steps=40, patches=2, patch_size=16, eval_every=1e9, eval_views=1, device="cpu",
                                      prune_every=0, clone_every=0), show_progress=False)
    bundle = Bundle(model=model, meta={})
    fit_atlas_stage(bundle, train, AtlasConfig(steps=40, texture_steps=20, charts="4", device="cpu"),
                    show_progress=False)
    save_bundle(d / "m.pgt", bundle)
    rc = main(["eval-edits", str(d / "m.pgt"), "--scene", str(d / "scene"), "--poses", "bend", "--magnitudes", "1",
               "--views", "1", "--temperatures", "1", "--samples", "4", "--json", str(d / "e.json"),
               "--markdown", str(d / "e.md")])
    if rc == 0:  # the demo's animation of the same model: decal + bend ramp, 2 frames, the last also at 4x
        from tools.demo import render_animation
        anim = render_animation(bundle, d / "scene", d / "anim", 2, "bend", test)
        (d / "anim.json").write_text(json.dumps(anim))
        from tools.eval_edits import ground_truth  # the cached posed renders, at the size --downscale 2 scores at
        full, half = (ground_truth(d / "scene" / "eval_views1", "bend", 1.0, None, downscale=n) for n in (1, 2))
        (d / "gt.json").write_text(json.dumps({"full": list(full.images.shape), "half": list(half.images.shape),
                                               "alpha": [float(full.alphas.mean()), float(half.alphas.mean())]}))
    sys.exit(rc)
""")


@pytest.mark.blender
@pytest.mark.slow
def test_eval_edits_smoke_on_a_tiny_scene(tmp_path):
    proc = subprocess.run([sys.executable, "-c", SMOKE, str(tmp_path)], cwd=ROOT, capture_output=True, text=True,
                          timeout=600)
    assert proc.returncode == 0, proc.stdout[-2000:] + proc.stderr[-3000:]
    assert "warm-up (tiny deformed frames" in proc.stdout + proc.stderr  # compiling is not charged to a row
    assert "warm-up (compiling the frame loops once)" in proc.stdout  # nor to the animation's first frame
    anim = json.loads((tmp_path / "anim.json").read_text())
    assert anim["frames"] == 2 and Path(anim["gif"]).exists() and anim["hires"]["size"] == [128, 128]
    assert math.isfinite(anim["seconds_per_frame"]) and (tmp_path / "anim" / "painted_atlas.png").exists()
    res = json.loads((tmp_path / "e.json").read_text())
    cases = {(r["pose"], r["magnitude"]) for r in res["rows"]}
    assert cases == {("rest", 0.0), ("bend", 1.0)} and res["views"] == 1
    # per case and renderer (by default paper and the default renderer): geometry, and per correspondence (by
    # default all three) a retexture, a soft and a threshold decal
    from tools.eval_edits import default_renderer

    assert len(res["rows"]) == 2 * 2 * 10 and {r["renderer"] for r in res["rows"]} == {"paper", default_renderer()}
    for r in res["rows"]:
        for k in ("psnr", "psnr_object", "ssim", "seconds_per_frame"):
            assert math.isfinite(r[k]), (r, k)
    assert len(res["retexture_gap"]) == 6 and all(math.isfinite(g["gap_psnr_object"]) for g in res["retexture_gap"])
    assert all(math.isfinite(b["psnr"]) for b in res["blank"])
    assert set(res["blend_comparison"]) == {f"{r}{c} T=1" for r in ("", f"{default_renderer()} ")
                                            for c in ("naive", "deform-aware", "deform-gradient")}
    assert 0.0 <= res["median_spread"] <= 1.0  # the model's thickness, which the `auto` rules resolve by
    table = (tmp_path / "e.md").read_text()
    assert "median spread" in table.splitlines()[0]
    assert table.count("| bend | 1 | ") == 2 * (10 + 3 + 1)  # per renderer: every case, 3 retexture gaps, ablation
    assert (tmp_path / "scene" / "eval_views1" / "poses" / "bend_decal" / "variant.json").exists()
    gt = json.loads((tmp_path / "gt.json").read_text())  # --downscale 2: the same renders area-averaged
    assert gt["full"] == [1, 32, 32, 3] and gt["half"] == [1, 16, 16, 3]
    assert gt["alpha"][1] == pytest.approx(gt["alpha"][0], abs=1e-5)


@pytest.mark.parametrize("value", ["0", "65"])
def test_eval_edits_refuses_a_downscale_out_of_range(tmp_path, capsys, value):
    """Checked before anything is read or rendered: the scene folder is not even looked at."""
    rc = main(["eval-edits", str(tmp_path / "m.pgt"), "--scene", str(tmp_path / "no-scene"), "--downscale", value])
    assert rc != 0 and "--downscale" in capsys.readouterr().err


def test_every_renderer_variant_is_a_valid_edit_config():
    """Each eval-edits renderer and each timing variant of tools/bench/deformation sets only EditConfig fields, to
    values EditConfig accepts, and names every F switch (so a changed default does not change a variant); exactly one
    renderer is the defaults' own."""
    import dataclasses

    from tools.bench.deformation import VARIANTS
    from tools.eval_edits import RENDERERS, _PAPER, default_renderer

    fields = {f.name for f in dataclasses.fields(EditConfig)}
    for table in (RENDERERS, VARIANTS):
        for name, over in table.items():
            assert set(over) <= fields, (name, set(over) - fields)
            assert set(_PAPER) <= set(over) | {"correspondence"}, (name, set(_PAPER) - set(over))
            EditConfig(**over)
    defaults = [k for k, v in RENDERERS.items() if all(getattr(EditConfig, f) == x for f, x in v.items())]
    assert defaults == [default_renderer()]
    assert RENDERERS["f-fill-fold-blend-depth-auto-budget-between-gap-tear"]["f_fill_tear"] == 13.5


def test_renderer_help_names_every_variant_by_its_switches():
    from tools.eval_edits import RENDERERS, describe_renderer, renderers_help

    text = renderers_help()
    assert all(f"{n} (" in text for n in RENDERERS)
    assert describe_renderer("paper") == "the paper's renderer, correspondence and atlas lookup"
    # a variant is described by exactly the switches that differ from the paper's renderer
    gap_b2 = describe_renderer("f-fill-fold-blend-depth-auto-budget-gate15-gap-b2")
    assert "f_fill_budget 2.0" in gap_b2 and "f_reach_gate 1.5" in gap_b2 and "f_fill_tear" not in gap_b2
    assert describe_renderer("f-attention") == "f_attention True"
