"""`pointgt eval MODEL.pgt DATA`: PSNR, SSIM and seconds per frame on a split."""
from __future__ import annotations

import json
import time

NAME = "eval"
HELP = "evaluate a model on a dataset split (PSNR, object PSNR, SSIM, seconds per frame)"
ORDER = 30


def add_arguments(p):
    p.add_argument("model", help="model file (.pgt)")
    p.add_argument("data", help="dataset folder (NeRF-synthetic layout)")
    p.add_argument("--split", default="test", help="split to evaluate")
    p.add_argument("--json", default=None, help="write the figures to this JSON file")
    p.add_argument("--device", default="auto", help="cpu | cuda | auto")
    p.add_argument("--downscale", type=int, default=1, help="integer image downscale factor")
    p.add_argument("--limit", type=int, default=0, help="evaluate only the first N views (0 = all)")


def run(args) -> int:
    import torch

    from core.bundle import load_bundle
    from core.images.metrics import object_mask, psnr, ssim
    from core.points.render import render_frame
    from core.images.dataset import load_split
    from core.util.atomic import atomic_write_text

    bundle = load_bundle(args.model, device=args.device)
    split = load_split(args.data, args.split, downscale=args.downscale)
    n = len(split) if args.limit <= 0 else min(args.limit, len(split))
    rows = []
    for i in range(n):
        t0 = time.perf_counter()
        out = render_frame(bundle.model, split.c2w[i], split.height, split.width, split.focal)
        sec = time.perf_counter() - t0
        gt = split.images[i].to(out["rgb"].device)
        m = object_mask(split.alphas[i].to(gt.device), out["alpha"])
        rows.append({"view": split.files[i].name, "psnr": psnr(out["rgb"], gt), "psnr_object": psnr(out["rgb"], gt, m),
                     "ssim": float(ssim(out["rgb"], gt)), "seconds": sec})
    blank = torch.ones_like(split.images[0])
    summary = {k: sum(r[k] for r in rows) / len(rows) for k in ("psnr", "psnr_object", "ssim", "seconds")}
    summary["blank_frame_psnr"] = sum(psnr(blank, split.images[i]) for i in range(n)) / n
    summary["blank_frame_psnr_object"] = sum(psnr(blank, split.images[i], split.alphas[i] > 0.5) for i in range(n)) / n
    result = {"model": str(args.model), "data": str(args.data), "split": args.split, "views": n,
              "width": split.width, "height": split.height, **summary, "per_view": rows}
    print(f"{args.split}: {n} views  PSNR {summary['psnr']:.2f} dB  object PSNR {summary['psnr_object']:.2f} dB  "
          f"SSIM {summary['ssim']:.4f}  {summary['seconds']:.3f} s/frame  "
          f"(blank frame: {summary['blank_frame_psnr']:.2f} / {summary['blank_frame_psnr_object']:.2f} dB)")
    if args.json:
        atomic_write_text(args.json, json.dumps(result, indent=1))
    return 0
