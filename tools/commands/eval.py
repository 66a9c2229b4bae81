"""`pointgt eval MODEL.pgt DATA`: PSNR, SSIM and seconds per frame on a split."""
from __future__ import annotations

import json
import time

NAME = "eval"
HELP = "evaluate a model on a dataset split (PSNR, object PSNR, SSIM, seconds per frame)"
ORDER = 30


def add_arguments(p):
    from tools.commands import add_model_and_data

    add_model_and_data(p, "model file (.pgt)", "dataset folder (any layout of docs/formats.md)")
    p.add_argument("--split", default="test", help="split to evaluate")
    p.add_argument("--json", default=None, help="write the figures to this JSON file")
    p.add_argument("--device", default="auto", help="cpu | cuda | auto")
    p.add_argument("--limit", type=int, default=0, help="evaluate only the first N views (0 = all)")
    from core.config import add_to_parser
    from core.images.dataset import LoadConfig

    add_to_parser(p, LoadConfig)


def run(args) -> int:
    from core.bundle import load_bundle
    from core.images.dataset import load_split
    from core.images.metrics import blank_floor, mean_scores, score_views
    from core.points.render import render_frame
    from core.util.atomic import atomic_write_text

    from core.config import check_flag
    from core.util.atomic import check_output_file
    from core.util.device import check_device

    if args.json:
        check_output_file(args.json, "--json")
    check_flag(args.downscale, "--downscale", min=1, max=64)
    check_flag(args.limit, "--limit", min=0)
    check_device(args.device, "--device")
    from core.config import from_args
    from core.images.dataset import LoadConfig

    load_kw = from_args(LoadConfig, args).loader_kwargs()
    bundle = load_bundle(args.model, device=args.device)
    split = load_split(args.data, args.split, downscale=args.downscale, **load_kw)
    n = len(split) if args.limit <= 0 else min(args.limit, len(split))

    def render(i):
        t0 = time.perf_counter()
        out = render_frame(bundle.model, split.c2w[i], split.height, split.width, split.focal)
        out["extra"] = {"seconds": time.perf_counter() - t0}
        return out
    rows = [{"view": split.files[i].name, **row}
            for i, row in enumerate(score_views(render, split.images, split.alphas, range(n)))]
    summary = mean_scores(rows, ("psnr", "psnr_object", "ssim", "seconds"))
    blank = blank_floor(split.images, split.alphas, range(n))
    summary["blank_frame_psnr"], summary["blank_frame_psnr_object"] = blank["psnr"], blank["psnr_object"]
    result = {"model": str(args.model), "data": str(args.data), "split": args.split, "views": n,
              "width": split.width, "height": split.height, **summary, "per_view": rows}
    print(f"{args.split}: {n} views  PSNR {summary['psnr']:.2f} dB  object PSNR {summary['psnr_object']:.2f} dB  "
          f"SSIM {summary['ssim']:.4f}  {summary['seconds']:.3f} s/frame  "
          f"(blank frame: {summary['blank_frame_psnr']:.2f} / {summary['blank_frame_psnr_object']:.2f} dB)")
    if args.json:
        atomic_write_text(args.json, json.dumps(result, indent=1))
    return 0
