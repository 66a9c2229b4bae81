"""Frames a model's training views never showed the right way up: a rolled camera, and posed parts turned in the image.

A scene's training cameras look at the object with the world's up axis up (`tools/scenes/cameras.py`), so an image
decoder can learn the training views' orientation. For one or more models of a built-in scene (`pointgt
make-scene`) this scores (object PSNR against Cycles ground truth, geometry only, the default renderer, eval-edits'
test cameras):

  rest        the test views as they are;
  roll D      the same cameras turned by D degrees about their viewing axis (position and direction kept): the
              same object, turned in the image; Cycles renders their ground truth (cached in SCENE/roll_V_D/);
  POSE        each rig pose at magnitude 1 (eval-edits' frames, geometry-only edit).

    python -m tools.bench.orientation A.pgt B.pgt --scene SCENE --views 4 --rolls 30,45,90 \\
        --poses bend,twist,squash,stretch,arm
"""
from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np


def rolled_c2w(c2w: np.ndarray, degrees: float) -> np.ndarray:
    """A camera-to-world matrix [4, 4] turned by `degrees` about the camera's own viewing axis (its local z): the
    position and the viewing direction are kept, the image turns (counter-clockwise as seen by the camera)."""
    a = math.radians(degrees)
    rz = np.array([[math.cos(a), -math.sin(a), 0.0], [math.sin(a), math.cos(a), 0.0], [0.0, 0.0, 1.0]])
    out = np.array(c2w, dtype=np.float64).copy()
    out[:3, :3] = out[:3, :3] @ rz
    return out


def rolled_scene_dir(scene_dir: Path, views: int, degrees: float) -> Path:
    """A scene folder (SCENE/roll_<views>_<degrees>/: links to the scene's blend file and spec) whose test cameras are
    eval-edits' `views` test cameras rolled by `degrees` (`rolled_c2w`); its transforms are rewritten when they
    differ, so `eval_edits.ground_truth` renders (and caches) them."""
    from tools.eval_edits import linked_scene_dir, view_subset_dir

    scene_dir = Path(scene_dir)
    doc = json.loads((view_subset_dir(scene_dir, views) / "transforms_test.json").read_text())
    want = {**doc, "frames": [{**f, "transform_matrix": rolled_c2w(np.array(f["transform_matrix"]), degrees).tolist()}
                              for f in doc["frames"]]}
    out, changed = linked_scene_dir(scene_dir, f"roll_{views}_{degrees:g}", want)
    cached = out / "poses" / "rest" / "variant.json"
    if changed and cached.exists():
        cached.unlink()  # other cameras: render again
    return out


def run(models, scene_dir, views: int = 4, rolls=(30.0, 45.0, 90.0), poses=(), log=print) -> dict:
    """The figures (module doc) as a JSON-able dict: {models: {path: {case: object PSNR}}, ...}."""
    import torch

    from core.bundle import load_bundle
    from core.frames.edited import EditConfig, EditState, render_edited
    from core.images.metrics import mean_scores, score_views
    from tools.eval_edits import deform_points, ground_truth, view_subset_dir
    from tools.machine import machine_info

    scene_dir = Path(scene_dir)
    cases = {"rest": (view_subset_dir(scene_dir, views), "rest")}
    cases.update({f"roll {d:g}": (rolled_scene_dir(scene_dir, views, d), "rest") for d in rolls})
    cases.update({p: (view_subset_dir(scene_dir, views), p) for p in poses})
    truth = {name: ground_truth(d, pose, 1.0, None, log=log) for name, (d, pose) in cases.items()}
    result = {"scene": str(scene_dir), "views": views, "rolls": list(rolls), "poses": list(poses),
              "machine": machine_info(), "models": {}}
    for mp in models:
        bundle = load_bundle(mp)
        can = bundle.model.xyz.detach().cpu().numpy()
        scores = {}
        for name, (_, pose) in cases.items():
            gt = truth[name]
            pts = None if pose == "rest" else torch.from_numpy(deform_points(can, scene_dir, pose, 1.0))
            state = EditState(bundle, points=pts, cfg=EditConfig())
            rows = score_views(lambda i: render_edited(state, gt.c2w[i], gt.height, gt.width, gt.focal),
                               gt.images, gt.alphas)
            scores[name] = mean_scores(rows, ["psnr_object"])["psnr_object"]
            log(f"  {Path(mp).name} {name}: {scores[name]:.2f} dB")
        result["models"][str(mp)] = scores
    return result


def markdown(result: dict) -> str:
    """One row per model: rest, each roll and each pose (object PSNR, dB), and the mean of the rolls and poses."""
    models = result["models"]
    if not models:
        return "(no models)"
    cases = list(next(iter(models.values())))
    turned = [c for c in cases if c != "rest"]
    head = "| model | " + " | ".join(cases) + " | mean of the others |"
    lines = [f"Scene {result['scene']}, {result['views']} views; object PSNR (dB), geometry only, default renderer",
             "", head, "|" + "---|" * (len(cases) + 2)]
    names = [Path(mp).name for mp in models]
    if len(set(names)) < len(names):  # the same file name in several folders: name the folder too
        names = ["/".join(Path(mp).parts[-2:]) for mp in models]
    for name, (mp, s) in zip(names, models.items()):
        mean = float(np.mean([s[c] for c in turned])) if turned else float("nan")
        lines.append(f"| {name} | " + " | ".join(f"{s[c]:.2f}" for c in cases) + f" | {mean:.2f} |")
    return "\n".join(lines)


def main(argv=None) -> int:
    from tools.bench import parse, parser, write_json

    ap = parser(__doc__)
    ap.add_argument("models", nargs="+", help="model files (.pgt) of the scene")
    ap.add_argument("--scene", required=True, help="the scene folder the models were trained on (make-scene)")
    ap.add_argument("--views", type=int, default=4, help="test cameras (evenly spaced, as eval-edits)")
    ap.add_argument("--rolls", default="30,45,90", help="comma-separated camera rolls in degrees")
    ap.add_argument("--poses", default="bend,twist,squash,stretch,arm",
                    help="comma-separated rig poses at magnitude 1 (empty: none)")
    args = parse(ap, argv)
    try:
        rolls = [float(v) for v in args.rolls.split(",") if v.strip()]
    except ValueError:
        raise SystemExit(f"--rolls: expected comma-separated numbers, got {args.rolls!r}") from None
    if any(not math.isfinite(v) for v in rolls):
        raise SystemExit(f"--rolls: angles must be finite, got {args.rolls!r}")
    res = run(args.models, args.scene, args.views, rolls, [p for p in args.poses.split(",") if p])
    print(markdown(res))
    write_json(args.json, res)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
