"""`pointgt render MODEL.pgt --cameras transforms.json --out DIR`: one PNG per camera."""
from __future__ import annotations

import json
import time
from pathlib import Path

NAME = "render"
HELP = "render a model from the cameras of a transforms JSON (one RGBA PNG per camera)"
ORDER = 40


def add_arguments(p):
    p.add_argument("model", help="model file (.pgt)")
    p.add_argument("--cameras", required=True, help="transforms_*.json whose cameras to render")
    p.add_argument("--out", required=True, help="output folder for the PNGs")
    p.add_argument("--size", type=int, default=None, help="square image size (default: size of the JSON's images)")
    p.add_argument("--device", default="auto", help="cpu | cuda | auto")
    p.add_argument("--json", default=None, help="write timings and counts to this JSON file")


def run(args) -> int:
    import numpy as np
    import torch

    from core.bundle import load_bundle
    from core.frames.render import render_frame
    from core.images.dataset import load_cameras
    from core.images.png import write_png
    from core.util.atomic import atomic_write_text
    from core.util.progress import Progress

    bundle = load_bundle(args.model, device=args.device)
    cams = load_cameras(args.cameras, size=args.size)
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    times = []
    with Progress(len(cams.names), "render") as bar:
        for i, name in enumerate(cams.names):
            t0 = time.perf_counter()
            res = render_frame(bundle.model, cams.c2w[i], cams.height, cams.width, cams.focal)
            times.append(time.perf_counter() - t0)
            rgba = torch.cat([res["rgb"], res["alpha"][..., None]], dim=-1).cpu().numpy()
            write_png(out / f"{name}.png", rgba)
            bar.update(1)
    summary = {"frames": len(times), "seconds_per_frame": float(np.mean(times)), "out": str(out)}
    print(f"rendered {len(times)} frames to {out} ({summary['seconds_per_frame']:.3f} s/frame)")
    if args.json:
        atomic_write_text(args.json, json.dumps(summary, indent=1))
    return 0
