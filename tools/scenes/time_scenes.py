"""Time `pointgt make-scene <scene>` for every built-in scene (each in a fresh process) and print a Markdown table.

Usage: python -m tools.scenes.time_scenes [--size 64] [--views-train 60] [--views-val 8] [--views-test 20]
       [--samples N] [--lit] [--out DIR]   (DIR defaults to a temporary folder, deleted afterwards)
"""
from __future__ import annotations

import argparse
import json
import subprocess
import sys
import tempfile
import time
from pathlib import Path


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--size", type=int, default=64)
    ap.add_argument("--views-train", type=int, default=60)
    ap.add_argument("--views-val", type=int, default=8)
    ap.add_argument("--views-test", type=int, default=20)
    ap.add_argument("--samples", type=int, default=None)
    ap.add_argument("--lit", action="store_true")
    ap.add_argument("--out", default=None)
    args = ap.parse_args(argv)
    from tools.scenes.library import scene_names

    with tempfile.TemporaryDirectory() as tmp:
        root = Path(args.out or tmp)
        rows = []
        for name in scene_names():
            cmd = [sys.executable, "-m", "tools.cli", "make-scene", name, "--out", str(root / name), "--force",
                   "--size", str(args.size), "--views-train", str(args.views_train), "--views-val",
                   str(args.views_val), "--views-test", str(args.views_test)]
            cmd += (["--samples", str(args.samples)] if args.samples else []) + (["--lit"] if args.lit else [])
            t0 = time.perf_counter()
            subprocess.run(cmd, check=True, capture_output=True)
            wall = time.perf_counter() - t0
            spec = json.loads((root / name / "scene.json").read_text())
            views = args.views_train + args.views_val + args.views_test
            rows.append((name, spec["vertices"], views, spec["render"]["samples"], spec["seconds"], wall))
    print("| scene | vertices | views | samples | build+render s | wall s (incl. bpy start) | s/view |")
    print("|---|---|---|---|---|---|---|")
    for name, nv, views, spp, sec, wall in rows:
        print(f"| {name} | {nv} | {views} | {spp} | {sec:.1f} | {wall:.1f} | {sec / views:.3f} |")
    return 0


if __name__ == "__main__":
    sys.exit(main())
