"""`pointgt fit DATA --out MODEL.pgt`: stage 1 (PAPR points) and stage 2 (UV atlas + texture)."""
from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import dataclasses

from core.atlas.config import AtlasConfig
from core.config import add_to_parser, from_args, to_dict
from core.images.dataset import LoadConfig
from core.points.model import ModelConfig
from core.points.train import TrainConfig

NAME = "fit"
HELP = "train a model from multi-view images (stage 1 points, stage 2 atlas)"
ORDER = 20


def add_arguments(p):
    p.add_argument("data", help="dataset folder: NeRF-synthetic or BlenderNeRF (transforms_train.json, ...), nerfstudio or instant-ngp (transforms.json); see docs/formats.md")
    p.add_argument("--out", required=True, help="model file to write (.pgt); the file that was there before the command is kept as .bak (one backup "
                        "per fit)")
    p.add_argument("--stage", choices=("papr", "atlas", "all"), default="all",
                   help="papr = points only; atlas = refit stage 2 on an existing --out model; all = both")
    p.add_argument("--points", type=int, default=None, help="initial number of points (= --num-points)")
    p.add_argument("--downscale", type=int, default=1, help="integer image downscale factor (1-64)")
    p.add_argument("--no-progress", action="store_true", help="no progress bar")
    p.add_argument("--allow-blank", action="store_true",
                   help="keep going (exit 0, run stage 2) even when the trained model renders the blank frame")
    p.add_argument("--profile", action=argparse.BooleanOptionalAction, default=True,
                   help="measure the scene and choose decoder, K and chart count from it, and say when its colours "
                        "seem to vary with the view (settings given on the command line always win)")
    add_to_parser(p, LoadConfig)
    add_to_parser(p, ModelConfig)
    add_to_parser(p, TrainConfig)
    add_to_parser(p, AtlasConfig, prefix="atlas")
    # images larger than the training size train multi-scale unless the user says otherwise (None: not given)
    p.set_defaults(train_scales=None)


def _outputs(out: Path) -> list[tuple[Path, str]]:
    """The files a fit writes: the model and its history / curve side files."""
    return [(out, "--out"), (out.with_suffix(".history.json"), "--out (history)"),
            (out.with_suffix(".curve.png"), "--out (curve)"),
            (out.with_suffix(".atlas_history.json"), "--out (atlas history)")]


def run(args) -> int:
    from core.bundle import Bundle, load_bundle, save_bundle
    from core.config import check_flag
    from core.frames.report import plot_curves, write_history
    from core.images.dataset import load_dataset
    from core.points.train import fit_points
    from core.util.atomic import check_output_file
    from core.util.errors import PointGTError

    out = Path(args.out)
    if out.suffix != ".pgt":
        from tools.cli import UserError
        raise UserError(f"--out must end in .pgt, got {out}")
    # Everything the user typed is checked before the dataset is read or a step is trained.
    for path, flag in _outputs(out):
        check_output_file(path, flag)
    check_flag(args.downscale, "--downscale", min=1, max=64)
    explicit_scales = args.train_scales is not None
    if not explicit_scales:  # the default: images larger than the training size train on their pyramid
        args.train_scales = "auto"
    load_kw = from_args(LoadConfig, args).loader_kwargs()
    if args.points is not None:
        args.num_points = args.points
    model_cfg = from_args(ModelConfig, args, names={"num_points": "--points"} if args.points is not None else None)
    train_cfg = from_args(TrainConfig, args)
    atlas_cfg = from_args(AtlasConfig, args, prefix="atlas")
    from core.util.device import check_device

    check_device(train_cfg.device, "--device")
    from core.images.pyramid import (AUTO_MAX_FACTOR, auto_train_scales, check_divides, downscale_split,
                                     parse_scales, parse_weights)

    # --downscale N sets the training size (the images / N); --train-scales auto reads the images at a finer size
    # and trains on their pyramid down to the training size (auto_train_scales).
    read_factor, auto = args.downscale, None
    if train_cfg.train_scales.strip().lower() == "auto":
        load, auto_scales, auto_weights = auto_train_scales(args.downscale)
        if auto_scales and args.stage in ("papr", "all"):
            read_factor, auto = load, auto_scales
        elif args.stage in ("papr", "all") and explicit_scales:
            print(f"[fit] --train-scales auto: --downscale {args.downscale} leaves no finer images within "
                  f"{AUTO_MAX_FACTOR}x the training size; training on the loaded images alone")
        weights = (train_cfg.train_scale_weights or auto_weights) if auto else train_cfg.train_scale_weights
        train_cfg = dataclasses.replace(train_cfg, train_scales=auto or "", train_scale_weights=weights)
    if train_cfg.train_scales.strip().lower() == "off":
        train_cfg = dataclasses.replace(train_cfg, train_scales="")
    scales = parse_scales(train_cfg.train_scales)  # multi-scale training (--train-scales), [] = off
    if scales:
        parse_weights(train_cfg.train_scale_weights, len(scales))
    check_device(atlas_cfg.device, "--atlas-device")
    existed = out.exists()
    bundle = None
    if args.stage == "atlas":
        bundle = load_bundle(out, device=train_cfg.device)  # before the images: a missing model is found at once
    try:
        data = load_dataset(args.data, splits=("train", "test"), required=("train", "test"), downscale=read_factor,
                            progress=not args.no_progress, **load_kw)
    except PointGTError as exc:
        if auto:  # the finer images did not fit (memory) or divide: say what read them
            raise type(exc)(f"{exc}; --train-scales auto{'' if explicit_scales else ' (the default)'} with "
                            f"--downscale {args.downscale} reads the images at 1/{read_factor} of their size (levels "
                            f"{auto}); add --train-scales off to read them at the training size only") from exc
        raise
    train, test = data["train"], data["test"]
    print(f"[fit] {args.data}: {len(train)} train / {len(test)} test views at {train.width}x{train.height}")
    images = train  # what stage 1 trains on: the loaded images, or with --train-scales the finest level's
    if scales:
        check_divides(train.height, train.width, scales, where="training")
        check_divides(test.height, test.width, scales, where="test")
        # The coarsest level is the training size: profile, test renders, atlas and the model's meta use it.
        train, test = downscale_split(train, scales[-1]), downscale_split(test, scales[-1])
        print(f"[fit] multi-scale training on levels {', '.join(f'{images.width // s}x{images.height // s}' for s in scales)}; "
              f"training size {train.width}x{train.height}"
              + (f" (--train-scales auto with --downscale {args.downscale}: --train-scales {train_cfg.train_scales} "
                 f"--train-scale-weights {train_cfg.train_scale_weights})" if auto else ""))
    profile = None
    if args.profile and args.stage in ("papr", "all"):
        from core.profile import apply_profile, explicit_fields, scene_profile
        from core.util.device import resolve_device

        profile = scene_profile(train, seed=train_cfg.seed, device=str(resolve_device(train_cfg.device)),
                                num_points=model_cfg.num_points)
        explicit = explicit_fields(args, ModelConfig) | explicit_fields(args, AtlasConfig, prefix="atlas")
        if args.points is not None:
            explicit.add("num_points")
        model_cfg, atlas_cfg, applied = apply_profile(profile, model_cfg, atlas_cfg, explicit)
        m = profile.measured
        print(f"[fit] scene profile: decoder={profile.decoder} view_dependent={profile.view_dependent} "
              f"k={profile.k} charts={profile.charts} (view variation {m['view_variation']:.3f}, hull flatness "
              f"{m['hull_flatness']:.2f}, {m['pixels_per_point']:.2f} foreground pixels per point); applied {applied or 'nothing (set on the command line)'}")
        if m.get("view_dependent_hint") and not model_cfg.view_dependent:
            print(f"[fit] the same surface points change colour across the views (view variation "
                  f"{m['view_variation']:.3f} > {m['thresholds']['view_variation']}): if the object is glossy or "
                  f"lit, --view-dependent may fit it better (at about half the steps per minute); on an unlit object "
                  f"with a busy texture this measure also rises, and plain colours fit better")
    if args.stage in ("papr", "all"):
        t0 = time.perf_counter()
        try:
            model, history = fit_points(images, test, model_cfg, train_cfg, show_progress=not args.no_progress)
        except KeyboardInterrupt:
            raise KeyboardInterrupt(f"nothing was saved; {out} is unchanged") from None
        seconds = time.perf_counter() - t0
        final = history[-1]
        # The curve uses a few views (eval_views); the summary is measured on the whole test split.
        from core.points.model import TRAIN_BACKGROUND
        from core.points.train import evaluate
        from core.images.metrics import blank_floor
        from core.points.train import collapse_reason

        all_views = {"views": len(test.files), **evaluate(model, test, range(len(test.files)), TRAIN_BACKGROUND)}
        floor = blank_floor(test.images, test.alphas, value=TRAIN_BACKGROUND)
        guard = {**final.get("guard", {}), "blank_floor_all_views": floor,
                 "collapsed": collapse_reason(all_views, floor, train_cfg.guard_margin)}
        meta = {"scene": {"data": str(Path(args.data).resolve()), "width": train.width, "height": train.height,
                          "camera_angle_x": train.camera_angle_x, "layout": train.layout,
                          "intrinsics": dict(zip(("fx", "fy", "cx", "cy"), train.intrinsics.as_list())),
                          **({"train_images": {"width": images.width, "height": images.height}}
                             if images is not train else {})},
                "profile": profile.to_dict() if profile else None,
                "train": {"config": to_dict(train_cfg), "seconds": round(seconds, 2),
                          "train_seconds": final["seconds"], "steps": final["step"], "final": final,
                          "test_all_views": all_views, "guard": guard}}
        bundle = Bundle(model=model, meta=meta)
        save_bundle(out, bundle)  # the one backup of this fit: what was at --out before the command ran
        hist_path = write_history(out.with_suffix(".history.json"), history,
                                  {"model": to_dict(model_cfg), "train": to_dict(train_cfg),
                                   "test_all_views": all_views})
        plot_curves(out.with_suffix(".curve.png"), {"stage 1": history},
                    f"{Path(args.data).name}: test PSNR vs training time")
        print(f"[fit] stage 1: {final['step']} steps in {final['seconds']:.0f} s, test PSNR {all_views['psnr']:.2f} dB "
              f"(object {all_views['psnr_object']:.2f} dB, SSIM {all_views['ssim']:.3f}) on all {all_views['views']} "
              f"test views ({final['psnr']:.2f} / {final['psnr_object']:.2f} dB on the curve's "
              f"{train_cfg.eval_views}), {model.num_points} points"
              + (f" ({final['floaters_removed']} floater{'s' * (final['floaters_removed'] > 1)} removed)"
                 if final.get("floaters_removed") else "")
              + f" -> {out}")
        print(f"[fit] PSNR-vs-time log {hist_path} and plot {out.with_suffix('.curve.png')}")
        for e in guard.get("events", []):
            print(f"[fit] the collapse guard at step {e['step']}: {e['action']} ({e['reason']})")
        if guard.get("declined") and not guard["collapsed"]:
            print(f"[fit] WARNING: the fit lost quality late in its budget: {guard['declined']} on the curve's "
                  f"views. It was saved to {out}; another --seed (a different random course) may not lose it.",
                  file=sys.stderr)
        if guard["collapsed"]:
            print(f"[fit] WARNING: the model renders the blank frame: {guard['collapsed']} (blank frame: "
                  f"{floor['psnr']:.2f} / {floor['psnr_object']:.2f} dB on all test views). It was saved to {out} for "
                  "inspection; it is not fit to edit. Try `--decoder none`, another --seed, or more --points; "
                  "pass --allow-blank to keep it anyway.", file=sys.stderr)
            if not args.allow_blank:
                return 3
    if args.stage in ("atlas", "all"):
        from core.pipeline import fit_atlas_stage, stage_time_text

        try:
            if args.stage == "all":
                bundle = load_bundle(out, device=train_cfg.device)  # stage 2 starts from the saved stage-1 model
            hist = fit_atlas_stage(bundle, train, atlas_cfg, show_progress=not args.no_progress)
            # After stage 1 of this fit, --out.bak already holds the user's previous model: no second backup.
            save_bundle(out, bundle, backup=args.stage == "atlas")
        except (KeyboardInterrupt, PointGTError) as exc:
            if args.stage == "atlas":
                if isinstance(exc, KeyboardInterrupt):
                    raise KeyboardInterrupt(f"nothing was saved; {out} is unchanged") from None
                raise
            note = (f"{out} holds this fit's stage-1 model (points, no atlas: it renders, but painting needs an "
                    f"atlas)" + (f"; the model that was there before is {out.name}.bak" if existed else "")
                    + f"; add the atlas with `pointgt atlas {out} {args.data}`")
            if isinstance(exc, KeyboardInterrupt):
                raise KeyboardInterrupt(note) from None
            raise type(exc)(f"{exc}; {note}") from exc
        write_history(out.with_suffix(".atlas_history.json"), [], {"atlas": hist, "config": to_dict(atlas_cfg)})
        print(f"[fit] stage 2: {hist['n']} charts from {hist['samples']} surface samples in "
              f"{stage_time_text(hist)} (fitting PSNR {hist['psnr'][-1]:.2f} dB) -> {out}")
    return 0
