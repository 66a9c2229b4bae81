"""How noisy Blender's ground truth is: each library scene's test views at several Cycles sample counts against a
many-sample reference rendered with another seed.

A render scored against frames that carry Monte Carlo noise reads that noise as its own error; this measures,
per scene, the object PSNR of frames rendered with N samples
(the scene's own seed, 0) against a reference of --reference samples (seed 1, so no sample is shared), on the
reference's object pixels and the N-sample frame's foreground (`core.images.metrics.score_frame`), with the render
seconds per view. `pointgt make-scene`'s default sample count (`tools/scenes/render.py` DEFAULT_SAMPLES) is
chosen from this table.

    python -m tools.bench.gt_noise --work DIR [--scenes cloth,tube,...] [--size 128] [--views 6]
        [--samples 16,32,64,128] [--reference 1024] [--markdown OUT] [--json OUT]

Per scene, DIR/<name>/ holds a scene made with `views` test views (one training view; made once and reused) and
noise/<N>/ the frames of each sample count.
"""
from __future__ import annotations

import json
import time
from pathlib import Path

from core.util.atomic import atomic_write_text
from tools.bench import parse, parser, write_json
from tools.machine import machine_line


def render_test_views(scene_dir: Path, samples: int, seed: int, out: Path) -> float:
    """The scene's test cameras rendered with `samples` Cycles samples and `seed` into out/test/ (with its
    transforms_test.json); returns the seconds per view. Needs bpy."""
    import bpy
    import numpy as np

    from tools.scenes import render

    frames = json.loads((scene_dir / "transforms_test.json").read_text())
    c2ws = np.asarray([f["transform_matrix"] for f in frames["frames"]], dtype=np.float64)
    render.open_scene(scene_dir)
    scene = bpy.context.scene
    scene.cycles.samples = int(samples)
    scene.cycles.seed = int(seed)
    t0 = time.perf_counter()
    rendered = render.render_views(scene, scene.camera, c2ws, out, "test", log=lambda *_: None)
    seconds = (time.perf_counter() - t0) / max(len(c2ws), 1)
    atomic_write_text(out / "transforms_test.json", json.dumps({"camera_angle_x": frames["camera_angle_x"],
                                                                "frames": rendered}, indent=2) + "\n")
    return seconds


def object_psnr(reference: Path, other: Path) -> float:
    """Mean object PSNR over the test views of the frames in `other` against those in `reference`."""
    from core.images.dataset import load_split
    from core.images.metrics import mean_scores, score_views

    ref, o = load_split(reference, "test"), load_split(other, "test")
    rows = score_views(lambda i: {"rgb": o.images[i], "alpha": o.alphas[i]}, ref.images, ref.alphas)
    return mean_scores(rows, ("psnr_object",))["psnr_object"]


def main(argv=None) -> int:
    ap = parser(__doc__)
    ap.add_argument("--work", required=True, help="folder for the scenes and their frames")
    ap.add_argument("--scenes", default="", help="comma-separated library scenes (default: all)")
    ap.add_argument("--size", type=int, default=128, help="frame side in pixels")
    ap.add_argument("--views", type=int, default=6, help="test views per scene")
    ap.add_argument("--samples", default="16,32,64,128", help="comma-separated sample counts to score")
    ap.add_argument("--reference", type=int, default=1024, help="samples of the reference frames (seed 1)")
    ap.add_argument("--markdown", default=None, help="also write the table to this file")
    args = parse(ap, argv)

    from tools.scenes import library
    from tools.scenes.build import make_scene

    work = Path(args.work)
    names = [s for s in args.scenes.split(",") if s] or library.scene_names()
    counts = [int(s) for s in args.samples.split(",") if s]
    rows = []
    for name in names:
        sdir = work / name
        if not (sdir / "scene.json").exists():
            make_scene(name, sdir, size=args.size, views_train=1, views_val=0, views_test=args.views,
                       samples=min(counts), log=lambda *_: None)
        ref = sdir / "noise" / f"ref{args.reference}"
        ref_s = render_test_views(sdir, args.reference, 1, ref)
        row = {"scene": name, "lit": bool(library.SCENES[name].lit), "reference_s_per_view": ref_s, "samples": {}}
        for n in counts:
            d = sdir / "noise" / str(n)
            s = render_test_views(sdir, n, 0, d)
            row["samples"][n] = {"psnr_object": object_psnr(ref, d), "s_per_view": s}
        rows.append(row)
        print(name, {n: round(v["psnr_object"], 2) for n, v in row["samples"].items()}, flush=True)

    head = "| scene | lit | " + " | ".join(f"{n} samples: dB / s per view" for n in counts) + " |"
    lines = [f"Test views' object PSNR against {args.reference} samples (seed 1), {args.views} views at "
             f"{args.size}²; {machine_line()}", "", head, "|" + "---|" * (2 + len(counts))]
    for r in rows:
        cells = [f"{r['samples'][n]['psnr_object']:.2f} / {r['samples'][n]['s_per_view']:.2f}" for n in counts]
        lines.append(f"| {r['scene']} | {'yes' if r['lit'] else 'no'} | " + " | ".join(cells) + " |")
    text = "\n".join(lines)
    print(text)
    if args.markdown:
        Path(args.markdown).write_text(text + "\n")
    write_json(args.json, rows)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
