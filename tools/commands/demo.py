"""`pointgt demo [--out DIR] [--quick]`: the main job end to end on the built-in default scene.

make the scene with Blender → fit (stage 1 points, stage 2 atlas) → pose with the rig and paint a decal →
render an animation → evaluate against Blender's ground truth → report.json + report.png.
Stages that are already done in DIR are reused (delete DIR to start over).
"""
from __future__ import annotations

NAME = "demo"
HELP = "run the whole pipeline on the default scene and write a report (make-scene, fit, edit, render, eval)"
DESCRIPTION = __doc__
ORDER = 5


def add_arguments(p):
    p.add_argument("--out", default="out/demo", help="working folder for the scene, model, frames and report")
    p.add_argument("--scene", default=None, help="built-in scene (default: the first of `make-scene --list`)")
    p.add_argument("--quick", action="store_true", help="toy sizes: the same steps in a few minutes (smoke test)")
    p.add_argument("--minutes", type=float, default=None, help="stage-1 training budget (default 10, quick 0.5)")
    p.add_argument("--device", default="auto", help="cpu | cuda | auto")
    p.add_argument("--allow-blank", action="store_true",
                   help="carry on even when the trained model renders the blank frame (otherwise: stop, exit 3)")


def run(args) -> int:
    from core.config import check_flag
    from core.util.atomic import check_output_dir
    from core.util.device import check_device
    from tools.demo import run_demo

    check_output_dir(args.out, "--out")
    check_flag(args.minutes, "--minutes", min=0.0)
    check_device(args.device, "--device")

    return run_demo(args)
