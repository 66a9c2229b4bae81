"""Training curve: test PSNR (full frame and object pixels) against training time, the error-against-run-time
figure of stage 1.

    python -m tools.bench.training_curve --data DIR [--minutes 10] [--history M.history.json] [--plot OUT.png]

Trains with the default settings and the scene profile (as `pointgt fit` does) and prints the curve as a table with
the machine description; `--history` prints the table of an existing run instead of training.
"""
from __future__ import annotations

import argparse
import json

from tools.machine import machine_line


def print_curve(history: list[dict]) -> None:
    print("| training s | steps | points | test PSNR | object PSNR | SSIM |")
    print("|---|---|---|---|---|---|")
    for r in history:
        print(f"| {r['seconds']:.0f} | {r['step']} | {r['points']} | {r['psnr']:.2f} | {r['psnr_object']:.2f} "
              f"| {r.get('ssim', float('nan')):.4f} |")


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--data", help="dataset folder (e.g. made by `pointgt make-scene cloth`)")
    ap.add_argument("--minutes", type=float, default=10.0, help="training budget")
    ap.add_argument("--history", help="print this M.history.json instead of training")
    ap.add_argument("--plot", help="also write the curve as a PNG")
    args = ap.parse_args(argv)
    if args.history:
        history = json.load(open(args.history))["history"]
    else:
        if not args.data:
            ap.error("--data is required unless --history is given")
        from core.atlas.config import AtlasConfig
        from core.images.dataset import load_dataset
        from core.points.model import ModelConfig
        from core.points.train import TrainConfig, fit_points
        from core.profile import apply_profile, scene_profile

        data = load_dataset(args.data, splits=("train", "test"), required=("train", "test"))
        profile = scene_profile(data["train"])
        mcfg, _, _ = apply_profile(profile, ModelConfig(), AtlasConfig(), explicit=set())
        _, history = fit_points(data["train"], data["test"], mcfg, TrainConfig(minutes=args.minutes))
    print(machine_line())
    print_curve(history)
    if args.plot:
        from core.frames.report import plot_curves

        plot_curves(args.plot, {"stage 1": history}, "test PSNR vs training time")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
