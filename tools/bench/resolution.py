"""The resolution benchmark: a model fitted at the training size, rendered at 2x and 4x it, against Cycles at
those sizes.

    python -m tools.bench.resolution --work DIR [--scenes tube,crate,suzanne] [--size 64] [--factors 2,4]
        [--steps 300] [--fit-args "--zoom-frac 0.5" --tag zoom] [--train-hires 4] [--model M.pgt]
        [--views-test 8] [--threads 1] [--render-mode auto,pixels,...] [--json OUT] [--markdown OUT]

Per library scene (`pointgt make-scene --list`): the Cycles ground truth at 1x (`make-scene --size S`, train and
test views) and at each factor F (`--size F*S`, the same test cameras: a scene's cameras depend on the seed, not
on the size), then `pointgt fit --stage papr` at 1x with a step budget (or --model, one scene), each a separate
process as a user runs it; everything is reused when it exists in --work. Then, per factor and test view, one
evaluation loop (`core.images.metrics.score_views`) scores on the object's pixels (ground truth ∪ the native
render's coverage):
- native: `render_frame` at F*S (the rendering mode of --render-mode; several comma-separated modes give one row
  each: every mode of `core.points.render.RENDER_MODES`);
- render 1x + bicubic: the 1x render bicubic-upsampled to F*S (the bar native rendering must beat);
- ground truth 1x + bicubic: the 1x Cycles frame upsampled (what 1x data can hold, the ceiling of 1x training).
Seconds per frame: the native render, and the 1x render plus its upsampling. Specks per frame: pixels away from
the object (outside its true coverage grown by one training pixel) that differ from the white background by
more than SPECK_CONTRAST — stray points — in the native render and in the upsampled 1x render. The error by
region (JSON only): PSNR of all three on the interior (the true coverage shrunk by one training pixel) and on the
band of one training pixel either side of the silhouette. Factor 1 is scored too (native = the training size: a
check that a mode leaves it unchanged). The scale factor of each frame comes from the model's
training footprint (a --model file from before it gets the 1x test cameras').

--train-hires H fits from the ground truth at H x the training size instead (the H x folder then holds the train
views too: `make-scene --size H*S` renders the same training cameras) with multi-scale training,
`pointgt fit --train-scales 1,2,...,H` (the powers of two below H that divide it, and H; a `--train-scales` or
`--train-scale-weights` in --fit-args wins): its coarsest level is the training size S, so the 1x render, the
bicubic rows and the evaluation are those of the 1x fit, and the fit column says `hiresH`. Such a model has seen
the H x data: at H x its ceiling is the ground truth itself, and how far its native render rises above the
upsampled 1x ground truth (the most a 1x fit can hold) is the detail it learned from the finer images. Its
training footprint is the finest level's, so it renders at H x S as it was trained (scale factor 1); its decoder
footprint is the coarsest level's (the training size S, filled in as H x the training footprint for model files
from before it), which the `decoder` and `interior` modes decode at. The mode `auto` is the model's
(`core.points.resolution.auto_mode`, from the interior gain a multi-scale fit measures on its finest level; for
such model files from before that measurement the bench makes it on the H x training images,
`core.points.train.interior_gain`, and prints it; a single-scale fit renders `upsampled`).
--time-steps N (with --train-hires) also times stage-1 steps: per scene, 3 pairs of N-step `fit_points` runs in
this process, the fit from the 1x images and the multi-scale one from the H x images alternating (the settings of
--fit-args, the decoder and K of the fitted model, evaluation excluded): seconds per step, min / median / max.
"""
from __future__ import annotations

import argparse
import json
import math
import shlex
import sys
import time
from pathlib import Path

from tools.bench import add_samples, run_command, samples_flag, write_json
from tools.machine import machine_line

DEFAULT_SCENES = "tube,crate,suzanne"


def hires_scales(factor: int) -> str:
    """The --train-scales of a fit from images `factor` x the training size (`core.images.pyramid.ladder`):
    "1,2,4" for 4, "1,2,6" for 6, "1,3" for 3."""
    from core.images.pyramid import ladder

    return ",".join(map(str, ladder(factor)))


def train_views(folder: Path) -> int:
    """Number of training frames of a rendered scene folder (0 when it has none)."""
    try:
        return len(json.loads((folder / "transforms_train.json").read_text())["frames"])
    except (OSError, ValueError, KeyError, TypeError):
        return 0


def step_seconds(model_cfg, fit_args: list[str], low_train, high_train, test, steps: int, pairs: int = 3,
                 seed: int = 0) -> dict:
    """Seconds per stage-1 step of the fit from the 1x split low_train and of the one --fit-args describe (its
    --train-scales) from high_train, `pairs` times each, alternating (so a drift of the machine's speed hits both).
    model_cfg: the ModelConfig both use. Returns {"1x": [s/step, ...], "hires": [...]}."""
    import argparse
    import dataclasses

    from core.config import add_to_parser, from_args
    from core.points.train import TrainConfig, fit_points

    ap = argparse.ArgumentParser(add_help=False)
    add_to_parser(ap, TrainConfig)
    hires_cfg, _ = ap.parse_known_args(fit_args)
    hires_cfg = from_args(TrainConfig, hires_cfg)
    plain = dataclasses.replace(hires_cfg, train_scales="", train_scale_weights="")
    out = {"1x": [], "hires": []}
    for i in range(pairs):
        for key, split, cfg in (("1x", low_train, plain), ("hires", high_train, hires_cfg)):
            cfg = dataclasses.replace(cfg, steps=steps, minutes=0.0, eval_every=1e9, eval_views=1, seed=seed + i,
                                      device="cpu")
            _, hist = fit_points(split, test, model_cfg, cfg, show_progress=False)
            out[key].append(hist[-1]["seconds"] / max(hist[-1]["step"], 1))
    return out


SPECK_CONTRAST = 0.1  # a speck pixel differs from the white background by more than this in some channel


def specks(rgb, gt_alpha, factor: int) -> int:
    """Speck pixels of a frame rendered over white: rgb [H, W, 3] differing from white by more than SPECK_CONTRAST
    in some channel, away from the object — outside the ground truth's coverage gt_alpha [H, W] (> 0.05) grown
    by one training pixel (`factor` pixels; its anti-aliased rim is not a speck)."""
    import torch.nn.functional as F
    r = max(int(factor), 1)
    near = F.max_pool2d((gt_alpha > 0.05).float()[None, None], 2 * r + 1, stride=1, padding=r)[0, 0] > 0
    far = (1.0 - rgb).abs().amax(-1) > SPECK_CONTRAST
    return int((far & ~near.to(far.device)).sum())


def region_masks(gt_alpha, factor: int):
    """The true coverage gt_alpha [H, W] (> 0.5) split for the error by region: (interior [H, W] bool: the coverage
    shrunk by one training pixel, `factor` pixels; edge [H, W] bool: the band of one training pixel either side of
    the silhouette)."""
    import torch.nn.functional as F
    r = max(int(factor), 1)
    m = (gt_alpha > 0.5).float()[None, None]
    grown = F.max_pool2d(m, 2 * r + 1, stride=1, padding=r)[0, 0] > 0
    inner = ~(F.max_pool2d(1.0 - m, 2 * r + 1, stride=1, padding=r)[0, 0] > 0)
    return inner, grown & ~inner


def region_psnr(rgb, gt, mask) -> float:
    """PSNR of rgb against gt ([H, W, 3]) on the pixels of mask [H, W] (NaN when it is empty)."""
    if not bool(mask.any()):
        return float("nan")
    mse = float(((rgb - gt.to(rgb.device)) ** 2)[mask.to(rgb.device)].mean())
    return 10.0 * math.log10(1.0 / max(mse, 1e-10))


def evaluate(model, low, high, factor: int, mode: str, cache: dict | None = None) -> dict:
    """Scores of one model at one factor: low/high the test splits at 1x and factor x (same cameras).
    cache: {view: (1x rgb [H, W, 3], seconds)} shared between modes (the 1x render does not depend on the mode).
    Returns the mean {psnr, psnr_object, up_render_psnr(_object), up_gt_psnr(_object), seconds, seconds_up, specks,
    specks_up (`specks` per frame of the native render and of the upsampled 1x render), native_interior,
    native_edge, up_render_interior, ..., up_gt_edge (PSNR on `region_masks`' regions)} and per_view rows."""
    from core.images.metrics import mean_scores, score_views
    from core.points.render import render_frame
    from core.points.resolution import upsample_frame

    cache = {} if cache is None else cache

    def upsample(img, f: int):  # the `upsampled` mode's bicubic, by a whole factor
        return upsample_frame(img, f * img.shape[0], f * img.shape[1])

    def render(i):
        if i not in cache:
            t0 = time.perf_counter()
            rgb = render_frame(model, low.c2w[i], low.height, low.width, low.focal)["rgb"]
            cache[i] = (rgb, time.perf_counter() - t0)
        t0 = time.perf_counter()
        out = render_frame(model, high.c2w[i], high.height, high.width, high.focal, mode=mode)
        seconds = time.perf_counter() - t0
        low_rgb, low_s = cache[i]
        t0 = time.perf_counter()
        up = upsample(low_rgb, factor)
        up_s = low_s + time.perf_counter() - t0
        gt_alpha = high.alphas[i]
        up_gt = upsample(low.images[i], factor)
        inner, edge = region_masks(gt_alpha, factor)
        regions = {f"{name}_{part}": region_psnr(img, high.images[i], mask)
                   for name, img in (("native", out["rgb"]), ("up_render", up), ("up_gt", up_gt))
                   for part, mask in (("interior", inner), ("edge", edge))}
        return {"rgb": out["rgb"], "alpha": out["alpha"],
                "also": {"up_render_{}": up, "up_gt_{}": up_gt},
                "extra": {"seconds": seconds, "seconds_up": up_s, "scale": out["scale"],
                          "specks": specks(out["rgb"], gt_alpha, factor), "specks_up": specks(up, gt_alpha, factor),
                          **regions}}

    rows = score_views(render, high.images, high.alphas)
    keys = ("psnr", "psnr_object", "up_render_psnr", "up_render_psnr_object", "up_gt_psnr", "up_gt_psnr_object",
            "seconds", "seconds_up", "scale", "specks", "specks_up",
            *(f"{n}_{p}" for n in ("native", "up_render", "up_gt") for p in ("interior", "edge")))
    return {**mean_scores(rows, keys), "per_view": rows}


def markdown(rows: list[dict], header: str) -> str:
    out = [header, "",
           "| scene | fit | size | mode | native object (full) | render 1x + bicubic | ground truth 1x + bicubic | "
           "native − upsampled | s/frame native | s/frame 1x + up | specks: native / 1x + up |",
           "|---|---|---|---|---|---|---|---|---|---|---|"]
    for r in rows:
        out.append(f"| {r['scene']} | {r.get('fit', 'default')} | {r['size']}² ({r['factor']}x) | {r['mode']} | {r['psnr_object']:.2f} "
                   f"({r['psnr']:.2f}) | {r['up_render_psnr_object']:.2f} | {r['up_gt_psnr_object']:.2f} | "
                   f"{r['psnr_object'] - r['up_render_psnr_object']:+.2f} | {r['seconds']:.2f} | "
                   f"{r['seconds_up']:.2f} | {r.get('specks', float('nan')):.1f} / {r.get('specks_up', float('nan')):.1f} |")
    return "\n".join(out) + "\n"


def summary(rows: list[dict], factor: int) -> str:
    """One line per fit setting and mode: the mean and the worst native − upsampled gap over the scenes at
    `factor`."""
    out = []
    for fit, mode in dict.fromkeys((r.get("fit", "default"), r["mode"]) for r in rows):
        gaps = [r["psnr_object"] - r["up_render_psnr_object"] for r in rows
                if r["mode"] == mode and r.get("fit", "default") == fit and r["factor"] == factor
                and math.isfinite(r["psnr_object"])]
        if gaps:
            out.append(f"{factor}x {fit} fit, {mode}: native − upsampled mean {sum(gaps) / len(gaps):+.2f} dB, "
                       f"worst {min(gaps):+.2f} dB over {len(gaps)} scene(s)")
    return "\n".join(out)


def main(argv=None) -> int:
    import torch

    from core.bundle import load_bundle
    from core.images.dataset import load_split
    from core.points.render import RENDER_MODES
    from core.points.resolution import check_mode, training_footprint
    from tools.scenes.library import scene_names

    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--work", required=True, help="folder for the scenes and models (reused between runs)")
    ap.add_argument("--scenes", default=DEFAULT_SCENES,
                    help=f"comma-separated library scenes (default {DEFAULT_SCENES}; all: {','.join(scene_names())})")
    ap.add_argument("--size", type=int, default=64, help="training image size (1x)")
    ap.add_argument("--factors", default="2,4", help="comma-separated render size factors (1 is always scored)")
    ap.add_argument("--views-train", type=int, default=40)
    ap.add_argument("--views-test", type=int, default=8)
    ap.add_argument("--steps", type=int, default=300, help="stage-1 steps of the fit")
    ap.add_argument("--fit-args", default="", help="more `pointgt fit` flags for the fit (one string)")
    ap.add_argument("--tag", default="", help="name of this fit setting: the model file is model_<steps>[_hires<H>]_<tag>.pgt "
                                             "(needed with --fit-args, so settings do not share a file)")
    ap.add_argument("--train-hires", type=int, default=0,
                    help="fit from the ground truth at this factor x --size with multi-scale training "
                         "(`fit --train-scales 1,2,...,H`); 0 = fit at 1x")
    ap.add_argument("--time-steps", type=int, default=0,
                    help="with --train-hires: also time this many stage-1 steps of both fits, 3 pairs alternating")
    ap.add_argument("--model", default=None, help="a model fitted at --size on the one scene of --scenes "
                                                  "(instead of fitting)")
    ap.add_argument("--render-mode", default="auto",
                    help=f"comma-separated rendering modes to score: auto (the model's mode), "
                         f"{', '.join(RENDER_MODES)}")
    ap.add_argument("--threads", type=int, default=1, help="torch threads (fits and renders)")
    ap.add_argument("--seed", type=int, default=0)
    add_samples(ap)
    ap.add_argument("--json", default=None, help="write all figures here")
    ap.add_argument("--markdown", default=None, help="write the table here")
    args = ap.parse_args(argv)
    scenes = [s for s in args.scenes.split(",") if s]
    modes = [m for m in args.render_mode.split(",") if m]
    bad = [m for m in modes if m not in ("auto", *RENDER_MODES)]
    if bad:
        ap.error(f"--render-mode: unknown {bad}; choose from auto, {', '.join(RENDER_MODES)}")
    try:
        factors = sorted({1, *(int(f) for f in args.factors.split(",") if f)})
    except ValueError:
        ap.error(f"--factors: comma-separated integers, got {args.factors!r}")
    if factors[0] < 1:
        ap.error("--factors: integers >= 1")
    if args.fit_args and not args.tag:
        ap.error("--fit-args: name the setting with --tag (the model file's name)")
    if args.train_hires < 0 or args.train_hires == 1:
        ap.error("--train-hires: a factor >= 2 (0 = fit at 1x)")
    if args.time_steps and not args.train_hires:
        ap.error("--time-steps compares the 1x fit with --train-hires's: give --train-hires")
    if args.train_hires and args.model:
        ap.error("--train-hires fits a model: leave out --model")
    hires = args.train_hires
    fit_args = shlex.split(args.fit_args)
    if hires and "--train-scales" not in fit_args:
        fit_args += ["--train-scales", hires_scales(hires)]
    if args.model and len(scenes) != 1:
        ap.error("--model: give exactly one scene in --scenes (the scene the model was fitted on)")
    if args.threads > 0:
        torch.set_num_threads(args.threads)
    work = Path(args.work)
    work.mkdir(parents=True, exist_ok=True)
    py = [sys.executable, "-m", "tools.cli"]
    fit_desc = f"{args.steps} steps{(' ' + shlex.join(fit_args)) if fit_args else ''}"
    if hires:
        fit_desc += f" from the {args.size * hires}² images"
    if args.model:
        fit_desc = f"the model {args.model}"
    head = (f"{machine_line()}\n1x = {args.size}², fit: {fit_desc}, {args.threads} thread(s), "
            f"{args.views_train} train / {args.views_test} test views, seed {args.seed}")
    print(head, flush=True)
    rows = []
    timing: dict = {}
    for name in scenes:
        for f in sorted({*factors, *([hires] if hires else [])}):
            folder = work / name / f"x{f}"
            train = args.views_train if f in (1, hires) else 1  # only the training size's views are used
            if not (folder / "scene.json").exists() or train_views(folder) < train:
                run_command(py + ["make-scene", name, "--out", str(folder), "--size", str(args.size * f),
                                  "--views-train", str(train), "--views-val", "0", "--views-test", str(args.views_test),
                                  "--seed", str(args.seed), "--force",
                                  *samples_flag(args.samples)], print, check=True)
        suffix = (f"_hires{hires}" if hires else "") + (f"_{args.tag}" if args.tag else "")
        model_path = Path(args.model) if args.model else work / name / f"model_{args.steps}{suffix}.pgt"
        if not model_path.exists():
            run_command(py + ["fit", str(work / name / f"x{hires or 1}"), "--stage", "papr", "--steps",
                              str(args.steps), "--minutes", "0", "--threads", str(args.threads), "--no-progress",
                              "--seed", str(args.seed), "--allow-blank", *fit_args, "--out", str(model_path)],
                        print, check=True)
        bundle = load_bundle(model_path, device="cpu")
        size = bundle.meta.get("scene", {}).get("width")
        if size is not None and size != args.size:
            raise SystemExit(f"{model_path}: trained at {size}², not --size {args.size}² (with --train-hires, the "
                             "coarsest of --train-scales must be the hires factor)")
        model = bundle.model.eval()
        low = load_split(work / name / "x1", "test")
        if not float(model.train_footprint) > 0:  # a model file from before the footprint: the 1x test cameras'
            model.train_footprint.fill_(training_footprint(low.c2w, low.focal, model.xyz.detach()))
        if hires and not float(model.decoder_footprint) > 0:  # a multi-scale model file from before the decoder's
            model.decoder_footprint.fill_(hires * float(model.train_footprint))  # footprint: its coarsest level's
        if hires and float(model.interior_gain) == 0.0:  # a multi-scale model file from before the fit measured
            from core.points.train import interior_gain  # it: the same measurement on its finest training images

            gain = interior_gain(model, load_split(work / name / f"x{hires}", "train"))
            model.interior_gain.fill_(gain if math.isfinite(gain) else 0.0)
        print(f"{name}: auto = {check_mode('auto', model)} (interior gain {float(model.interior_gain):+.2f} dB)",
              flush=True)
        cache: dict = {}
        for f in factors:
            high = low if f == 1 else load_split(work / name / f"x{f}", "test")
            for mode in modes:
                res = evaluate(model, low, high, f, mode, cache)
                fit = "+".join(t for t in (f"hires{hires}" if hires else "", args.tag) if t) or "default"
                row = {"scene": name, "factor": f, "size": high.width, "mode": mode, "fit": fit,
                       **res}
                rows.append(row)
                print(markdown([row], "").strip().splitlines()[-1], flush=True)
        if args.time_steps:
            import statistics

            times = step_seconds(model.cfg, fit_args, load_split(work / name / "x1", "train"),
                                 load_split(work / name / f"x{hires}", "train"), low, args.time_steps,
                                 seed=args.seed)
            for key, vals in times.items():
                print(f"{name}: seconds per step, {key} fit, min / median / max of {len(vals)}: "
                      f"{min(vals):.3f} / {statistics.median(vals):.3f} / {max(vals):.3f}", flush=True)
            timing[name] = times
        write_json(args.json, {"machine": head, "rows": rows, "step_seconds": timing})
    table = markdown(rows, "```\n" + head + "\n```")
    print(table)
    for f in factors[1:]:
        print(summary(rows, f))
    if args.markdown:
        Path(args.markdown).write_text(table + "\n" + "\n".join(summary(rows, f) for f in factors[1:]) + "\n")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
