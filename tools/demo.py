"""The main job end to end (`pointgt demo`): scene → fit → atlas → pose + paint → animation → evaluation → report.

Every stage writes its result into the output folder and is skipped when that result is already there, so an
interrupted run resumes where it stopped (delete the folder to start over).
"""
from __future__ import annotations

import dataclasses
import json
import sys
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch

from core.util.atomic import atomic_write_text
from tools.machine import machine_info


@dataclass
class DemoSize:
    """Sizes of one demo run (full or --quick)."""
    size: int
    views_train: int
    views_test: int
    minutes: float
    atlas_steps: int | None          # None = AtlasConfig's defaults
    atlas_texture_steps: int | None
    frames: int
    eval_views: int
    poses: tuple[str, ...]
    magnitudes: tuple[float, ...]
    temperatures: tuple[float, ...]


FULL = DemoSize(size=128, views_train=60, views_test=20, minutes=10.0, atlas_steps=None, atlas_texture_steps=None,
                frames=24, eval_views=4, poses=("bend", "twist", "squash", "stretch", "arm"),
                magnitudes=(0.5, 1.0), temperatures=(1.0,))
QUICK = DemoSize(size=40, views_train=16, views_test=4, minutes=0.5, atlas_steps=200, atlas_texture_steps=50,
                 frames=4, eval_views=2, poses=("bend",), magnitudes=(1.0,), temperatures=(1.0,))


def reuse_message(scene_dir: Path, name: str, default_samples: int) -> str:
    """What the demo says when it reuses the scene in scene_dir: with its Cycles samples per pixel (from
    scene.json), and how to render it again where it has fewer than the default (its frames' own noise then
    lowers every score, docs/results.md "Noise in the ground truth")."""
    try:
        samples = int(json.loads((scene_dir / "scene.json").read_text())["render"]["samples"])
    except (OSError, ValueError, KeyError, TypeError):
        return "reusing the existing scene"
    msg = f"reusing the existing scene ({samples} Cycles samples per pixel)"
    if samples < default_samples:
        msg += (f"; its frames' own noise lowers every score: run the demo into a new --out folder (or delete "
                f"{scene_dir.parent}) to render {name} with {default_samples}")
    return msg


def report_guard(history: list[dict], allow_blank: bool = False) -> bool:
    """Say what the collapse guard did in a fit (its history's last entry): each action, a late decline (a
    warning: the demo goes on), a blank model (an error). Returns whether the demo goes on: False for a blank
    model unless allow_blank."""
    guard = history[-1].get("guard") or {}
    collapsed, declined = guard.get("collapsed"), guard.get("declined")
    for e in guard.get("events", []):
        print(f"the collapse guard at step {e['step']}: {e['action']} ({e['reason']})")
    if declined and not collapsed:
        print(f"WARNING: the fit lost quality late in its budget: {declined} on the curve's views; the demo goes on "
              "with it", file=sys.stderr)
    if collapsed:
        print(f"ERROR: the trained model renders the blank frame ({collapsed}); the atlas, edits and animation "
              "would all carry a blank model. Pass --allow-blank to carry on anyway.", file=sys.stderr)
        return bool(allow_blank)
    return True


def _banner(i: int, n: int, text: str) -> None:
    print(f"\n=== [{i}/{n}] {text}", flush=True)


def _write_json(path: Path, data) -> None:
    atomic_write_text(path, json.dumps(data, indent=1), backup=False)


def run_demo(args) -> int:
    from core.atlas.config import AtlasConfig
    from core.bundle import Bundle, load_bundle, save_bundle
    from core.config import to_dict
    from core.frames.report import plot_curves, write_history
    from core.images.dataset import load_dataset
    from core.pipeline import fit_atlas_stage
    from core.points.model import ModelConfig
    from core.points.train import TrainConfig, fit_points
    from tools.scenes import library
    from tools.scenes.build import make_scene

    sz = QUICK if args.quick else FULL
    if args.minutes is not None:
        sz = dataclasses.replace(sz, minutes=float(args.minutes))
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    name = args.scene or library.scene_names()[0]
    scene_dir = out / "scene"
    model_path = out / "model.pgt"
    n = 7
    t_all = time.perf_counter()
    report: dict = {"scene": name, "quick": bool(args.quick), "sizes": dataclasses.asdict(sz), "machine": machine_info(),
                    "stages": {}}

    def stage_done(key, t0, **info):
        report["stages"][key] = {"seconds": round(time.perf_counter() - t0, 2), **info}

    # 1. images: Blender renders the scene
    _banner(1, n, f"scene '{name}' rendered by Blender (Cycles) -> {scene_dir}")
    t0 = time.perf_counter()
    if (scene_dir / "scene.json").exists():
        from tools.scenes.render import DEFAULT_SAMPLES
        print(reuse_message(scene_dir, name, DEFAULT_SAMPLES))
    else:
        make_scene(name, scene_dir, size=sz.size, views_train=sz.views_train, views_test=sz.views_test)
    stage_done("scene", t0)
    data = load_dataset(scene_dir, splits=("train", "test"), required=("train", "test"))
    train, test = data["train"], data["test"]

    # 2. points: stage 1
    _banner(2, n, f"stage 1: PAPR points, {sz.minutes:g} min budget -> {model_path}")
    t0 = time.perf_counter()
    if model_path.exists():
        print("reusing the existing model")
        bundle = load_bundle(model_path, device=args.device)
        history = json.loads(model_path.with_suffix(".history.json").read_text())["history"]
    else:
        from core.profile import apply_profile, scene_profile

        from core.util.device import resolve_device

        profile = scene_profile(train, device=str(resolve_device(args.device)))
        mcfg, _, applied = apply_profile(profile, ModelConfig(), AtlasConfig(), explicit=set())
        report["profile"] = {**profile.to_dict(), "applied": applied}
        print(f"scene profile: decoder={profile.decoder} k={profile.k} charts={profile.charts}")
        tcfg = TrainConfig(minutes=sz.minutes, device=args.device)
        model, history = fit_points(train, test, mcfg, tcfg)
        bundle = Bundle(model=model, meta={"scene": {"name": name, "data": str(scene_dir.resolve())},
                                           "train": {"config": to_dict(tcfg), "final": history[-1]}})
        save_bundle(model_path, bundle, backup=False)
        write_history(model_path.with_suffix(".history.json"), history, {"model": to_dict(mcfg), "train": to_dict(tcfg)})
    if not report_guard(history, getattr(args, "allow_blank", False)):
        return 3
    plot_curves(out / "curve.png", {"stage 1": history}, f"{name}: test PSNR vs training time")
    stage_done("fit", t0, train_seconds=history[-1]["seconds"], steps=history[-1]["step"])
    report["test_psnr_during_training"] = history[-1]

    # 3. atlas: stage 2
    _banner(3, n, "stage 2: UV atlas and texture")
    t0 = time.perf_counter()
    if bundle.atlas is None:
        charts = (report.get("profile") or {}).get("charts", "auto")
        sizes = {k: v for k, v in (("steps", sz.atlas_steps), ("texture_steps", sz.atlas_texture_steps)) if v}
        acfg = AtlasConfig(charts=charts, device=args.device, **sizes)
        hist = fit_atlas_stage(bundle, train, acfg)
        save_bundle(model_path, bundle, backup=False)
        report["atlas"] = {k: v for k, v in hist.items() if not isinstance(v, list)}
    else:
        print("reusing the existing atlas")
        report["atlas"] = bundle.meta.get("atlas_fit", {})
    stage_done("atlas", t0)

    # 4. evaluation of the reconstruction on all test views
    _banner(4, n, "novel-view evaluation on the test split")
    t0 = time.perf_counter()
    report["novel_views"] = evaluate_views(bundle, test)
    stage_done("eval", t0)
    print(f"test PSNR {report['novel_views']['psnr']:.2f} dB, object {report['novel_views']['psnr_object']:.2f} dB, "
          f"SSIM {report['novel_views']['ssim']:.4f}, atlas-coloured {report['novel_views']['atlas_psnr']:.2f} dB")

    # 5. edits: paint a decal into the atlas, pose with the rig, render an animation
    _banner(5, n, f"pose with the rig + paint a decal: {sz.frames}-frame animation")
    t0 = time.perf_counter()
    anim = render_animation(bundle, scene_dir, out / "animation", sz.frames, sz.poses[0], test)
    stage_done("animation", t0, **anim)

    # 6. ground truth: the same edits rendered by Blender
    _banner(6, n, "edits against Blender's ground truth")
    t0 = time.perf_counter()
    from tools.eval_edits import CORRESPONDENCES, compared_renderers, markdown, run_eval

    # the paper's renderer and correspondences beside the deformation-gradient ones (and the default renderer)
    ev = run_eval(model_path, scene_dir, poses=sz.poses, magnitudes=sz.magnitudes, views=sz.eval_views,
                  temperatures=sz.temperatures, device=args.device,
                  renderers=compared_renderers(), correspondences=CORRESPONDENCES)
    _write_json(out / "edits.json", ev)
    (out / "edits.md").write_text(markdown(ev))
    report["edits"] = [{k: r[k] for k in ("pose", "magnitude", "renderer", "edit", "correspondence", "temperature",
                                         "blend",
                                         "psnr", "psnr_object", "ssim", "seconds_per_frame") if k in r}
                       for r in ev["rows"]]
    report["edits_blank_floor"] = ev.get("blank")
    report["retexture_gap"] = ev.get("retexture_gap")
    stage_done("edit_eval", t0)

    # 7. report
    _banner(7, n, "report")
    report["test_psnr"] = report["novel_views"]["psnr"]
    report["test_psnr_object"] = report["novel_views"]["psnr_object"]
    report["training_seconds"] = history[-1]["seconds"]
    report["total_seconds"] = round(time.perf_counter() - t_all, 1)
    _write_json(out / "report.json", report)
    write_report_image(out / "report.png", history, report)
    print(f"report: {out / 'report.json'} and {out / 'report.png'}; animation: {anim['gif']}")
    print(f"total {report['total_seconds']:.0f} s")
    return 0


@torch.no_grad()
def evaluate_views(bundle, split) -> dict:
    """PSNR/SSIM of the point render and of the atlas-coloured render on every view of a split."""
    from core.frames.edited import EditConfig, EditState, render_edited
    from core.images.metrics import mean_scores, score_views

    plain = EditState(bundle)
    atlas = EditState(bundle, cfg=EditConfig(colour="atlas")) if bundle.atlas is not None else None

    def render(i):
        view = (split.c2w[i], split.height, split.width, split.focal)
        r = render_edited(plain, *view)
        out = {"rgb": r["rgb"].cpu(), "alpha": r["alpha"].cpu(), "extra": {"seconds": r["stats"]["seconds"]}}
        if atlas is not None:
            out["also"] = {"atlas_{}": render_edited(atlas, *view)["rgb"].cpu()}
        return out
    return mean_scores(score_views(render, split.images, split.alphas))


@torch.no_grad()
def render_animation(bundle, scene_dir: Path, out: Path, frames: int, pose: str, test) -> dict:
    """Decal painted into the atlas + `pose` ramping 0 → 1: PNG frames and a GIF from the first test camera."""
    from PIL import Image

    from core.edits.bake import bake
    from core.edits.procedural import evaluate
    from core.frames.edited import EditState, render_edited, warm_up
    from core.images.png import write_png
    from tools.eval_edits import deform_points
    from tools.scenes.spec import load_scene_spec

    spec = load_scene_spec(scene_dir)
    c, h = spec["bbox"]["center"], spec["bbox"]["half_size"]
    painted = bake(bundle.atlas, lambda p: evaluate("decal", p, c, h, spec["texture"]["params"].get("decal")))
    out.mkdir(parents=True, exist_ok=True)
    write_png(out / "painted_atlas.png", painted.cpu().numpy())
    canonical = bundle.model.xyz.detach().cpu().numpy()
    images, secs = [], []
    cam = test.c2w[0]
    print(f"  warm-up (compiling the frame loops once): {warm_up(bundle):.2f} s", flush=True)
    state = None
    for f in range(frames):
        m = f / max(frames - 1, 1)
        pts = deform_points(canonical, scene_dir, pose, m) if m > 0 else None
        # the atlas is painted once: each pose takes the previous frame's prepared paint, as the add-on does
        state = EditState(bundle, points=None if pts is None else torch.from_numpy(pts), atlas=painted,
                          paint_from=state)
        r = render_edited(state, cam, test.height, test.width, test.focal)
        secs.append(r["stats"]["seconds"])
        rgb = r["rgb"].cpu().numpy()
        write_png(out / f"frame_{f:03d}.png", rgb)
        images.append(Image.fromarray((np.clip(rgb, 0, 1) * 255 + 0.5).astype(np.uint8)))
        print(f"  frame {f + 1}/{frames}: {pose} magnitude {m:.2f}, {secs[-1]:.3f} s", flush=True)
    gif = out / "animation.gif"
    images[0].save(gif, save_all=True, append_images=images[1:], duration=120, loop=0)
    # the last (fully posed, painted) frame again at 4x the training size, beside the training-size frame
    big = render_scaled(state, cam, test, 4)
    write_png(out / f"frame_last_{big['width']}.png", big["rgb"].cpu().numpy())
    small = images[-1].resize((big["width"], big["height"]), Image.NEAREST)
    side = Image.new("RGB", (2 * big["width"] + 8, big["height"]), "white")
    side.paste(small, (0, 0))
    side.paste(Image.fromarray((np.clip(big["rgb"].cpu().numpy(), 0, 1) * 255 + 0.5).astype(np.uint8)),
               (big["width"] + 8, 0))
    side.save(out / "last_frame_1x_4x.png")
    print(f"  last frame at {big['width']}x{big['height']}: {big['seconds']:.2f} s -> {out / 'last_frame_1x_4x.png'}",
          flush=True)
    return {"frames": frames, "pose": pose, "seconds_per_frame": float(np.mean(secs)), "gif": str(gif),
            "hires": {"size": [big["height"], big["width"]], "seconds": big["seconds"],
                      "image": str(out / "last_frame_1x_4x.png")}}


@torch.no_grad()
def render_scaled(state, c2w, split, factor: int) -> dict:
    """One edited frame of `state` from camera c2w [4, 4] at `factor` times the split's image size (focal scaled
    with it, the same view): dict(rgb [factor·H, factor·W, 3], height, width, seconds). factor 1 is the split's own
    frame."""
    import time as _time

    from core.frames.edited import render_edited
    from core.images.cameras import scaled_focal

    h, w = split.height * factor, split.width * factor
    focal = scaled_focal(split.focal, factor)
    t0 = _time.perf_counter()
    r = render_edited(state, c2w, h, w, focal)
    return {"rgb": r["rgb"], "height": h, "width": w, "seconds": _time.perf_counter() - t0}


def write_report_image(path: Path, history: list[dict], report: dict) -> None:
    """PSNR-vs-time curve beside the edit-fidelity table, one PNG."""
    import matplotlib

    from core.frames.edited import EditConfig
    from tools.eval_edits import default_renderer

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, (ax, tb) = plt.subplots(1, 2, figsize=(13, 8), dpi=100, gridspec_kw={"width_ratios": [1, 1.4]})
    for key, style in (("psnr", "-"), ("psnr_object", "--")):
        ax.plot([r["seconds"] for r in history], [r[key] for r in history], style, marker=".",
                label=key.replace("_", " "))
    ax.set_xlabel("training time (s)")
    ax.set_ylabel("test PSNR (dB)")
    ax.set_title(f"{report['scene']}: error against run time")
    ax.grid(alpha=0.3)
    ax.legend()
    tb.axis("off")
    rows = [r for r in report.get("edits", []) if r.get("blend", "soft") == "soft" and r.get("temperature", 1.0) == 1.0
            and r.get("correspondence") in ("-", EditConfig.correspondence)
            and r.get("renderer", "paper") == default_renderer()]
    cells = [[r["pose"], f"{r['magnitude']:g}", r["edit"], f"{r['psnr']:.2f}", f"{r['psnr_object']:.2f}",
              f"{r['seconds_per_frame']:.3f}"] for r in rows][:40]
    if cells:
        t = tb.table(cellText=cells, colLabels=["pose", "mag", "edit", "PSNR", "object", "s/frame"],
                     loc="upper center", cellLoc="center", bbox=[0, 0, 1, 0.95])
        t.auto_set_font_size(False)
        t.set_fontsize(7)
    tb.set_title(f"edits vs Blender ground truth, {EditConfig.correspondence} correspondence, {default_renderer()} "
                 "renderer (dB); all cases: edits.md", fontsize=9)
    fig.tight_layout()
    fig.savefig(path)
    plt.close(fig)
