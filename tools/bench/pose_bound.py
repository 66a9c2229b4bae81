"""How much of a posed frame's gap to rest a renderer can close: the point render against perfect textures.

For poses of a built-in scene (`pointgt make-scene`), each geometry-only frame (eval-edits' test cameras and
Cycles ground truth) is scored (object PSNR) as

  render             the posed points rendered with an eval-edits renderer variant (`--renderers`);
  ..., base          with --base, the same without the decoder's correction (a residual UNet decoder's last
                     layers zeroed: the points' own colours and coverage, which it corrects): whether what a pose
                     loses of the render is the decoder's image-space correction or the points' colours;
  perfect texture    every object ray coloured by the scene's own base texture evaluated exactly at the frame's
                     canonical points (the deform-gradient correspondence, which is exact under an affine map), with
                     the render's coverage: what geometry, coverage and correspondence alone allow;
  texture at s px    the same texture low-passed first: the mean of 4³ evaluations spread over a cube s training
                     pixels wide around the canonical point (one training pixel = the model's `train_footprint` in
                     world units), for each s of `--footprints`: a texture known only as finely as the training
                     images show it;
  ... on the surface each of those two with the canonical point first moved to the nearest point of the scene's
                     own mesh at rest: a 3-D texture that changes across the surface (bands, a 3-D checker) is
                     otherwise read off the surface wherever the frame's canonical points scatter in depth (the
                     point cloud's slab), which speckles the "perfect" frame at rest already.

A pose that magnifies the surface (the 5× stretch) shows the texture's detail finer than a training pixel: where
"texture at 1 px" loses as much against rest as the render, the gap is the training images' resolution, not the
renderer. Rest rows use the model's canonical points (nothing moved).

    python -m tools.bench.pose_bound MODEL.pgt --scene SCENE --poses stretch,arm --views 2 \\
        --renderers f-fill-fold,f-attention --footprints 1,1.5
"""
from __future__ import annotations

import math
from pathlib import Path


def lowpassed(fn, width: float, n: int = 4):
    """fn(x [M, 3]) -> rgb [M, 3] averaged over an n³ grid of offsets spanning a cube `width` wide (world units)
    around each point; width 0 returns fn itself."""
    import torch

    if not width > 0:
        return fn

    def blurred(x):
        offs = ((torch.arange(n, dtype=x.dtype, device=x.device) + 0.5) / n - 0.5) * width
        acc = torch.zeros(x.shape[0], 3, dtype=x.dtype, device=x.device)
        for ox in offs:
            for oy in offs:
                for oz in offs:
                    acc = acc + fn(x + torch.stack([ox, oy, oz])).to(x.dtype)
        return acc / n ** 3
    return blurred


def surface_projector(tree):
    """x [M, 3] (torch) -> the nearest point to each of the mesh in `tree` (a mathutils BVH tree, e.g.
    `colour_field_bound.rest_mesh_tree`), [M, 3] in x's dtype (non-finite points stay as they are)."""
    import bpy  # noqa: F401  (Blender's mathutils comes with bpy)
    import numpy as np
    import torch
    from mathutils import Vector

    def project(x):
        xs = x.detach().cpu().double().numpy()
        out = xs.copy()
        for i, p in enumerate(xs):
            if np.isfinite(p).all():
                loc = tree.find_nearest(Vector(p))[0]
                if loc is not None:
                    out[i] = loc[:]
        return torch.from_numpy(out).to(device=x.device, dtype=x.dtype)
    return project


def object_psnr(rgb, alpha, image, gt_alpha) -> float:
    """Object PSNR (ground truth ∪ rendered foreground) of one frame: rgb/image [H, W, 3], alpha/gt_alpha [H, W]."""
    obj = (gt_alpha > 0.5) | (alpha > 0.5)
    err = float(((rgb - image) ** 2).sum(-1)[obj].sum())
    return -10.0 * math.log10(max(err, 1e-12) / (3 * max(int(obj.sum()), 1)))


def run(model_path, scene_dir, poses=("stretch",), views: int = 2, renderers=("f-fill-fold",),
        footprints=(1.0,), base_rows: bool = False, log=print) -> dict:
    """The figures (module doc) as a JSON-able dict: per pose ("rest" first), row name -> mean object PSNR.
    base_rows: also each renderer without the decoder's correction (models with a residual UNet decoder)."""
    import json

    import torch

    from core.bundle import load_bundle
    from core.edits.procedural import evaluate
    from core.frames.edited import EditConfig, EditState, render_edited
    from tools.bench.colour_field_bound import rest_mesh_tree
    from tools.eval_edits import RENDERERS, deform_points, ground_truth, view_subset_dir
    from tools.machine import machine_info

    scene_dir = Path(scene_dir)
    spec = json.loads((scene_dir / "scene.json").read_text())
    box, base_texture = spec["bbox"], spec["texture"]["base"]
    params = spec["texture"].get("params", {}).get(base_texture)
    bundle = load_bundle(model_path)
    footprint = float(bundle.model.train_footprint)
    plain = None  # the same model without the decoder's correction (--base)
    if base_rows and bundle.model.decoder is not None and bundle.model.cfg.decoder_residual:
        plain = load_bundle(model_path)
        plain.model.decoder.reset_correction()
    for rd in renderers:
        if rd not in RENDERERS:
            raise SystemExit(f"--renderers: unknown renderer {rd!r}; choose from {', '.join(RENDERERS)}")

    def texture(x):
        return evaluate(base_texture, x, box["center"], box["half_size"], params)[0]

    result = {"model": str(model_path), "scene": spec.get("name"), "texture": base_texture, "views": views,
              "train_footprint": footprint, "machine": machine_info(), "poses": {}}
    can = bundle.model.xyz.detach().numpy()
    project = surface_projector(rest_mesh_tree(scene_dir))
    for pose in ["rest", *[p for p in poses if p != "rest"]]:
        gt = ground_truth(view_subset_dir(scene_dir, views), pose, 1.0, None, log=log)
        points = None if pose == "rest" else torch.from_numpy(deform_points(can, scene_dir, pose, 1.0))
        rows = {}
        for rd in renderers:
            state = EditState(bundle, points=points, cfg=EditConfig(**RENDERERS[rd]))
            rows[f"render {rd}"] = [render_edited(state, gt.c2w[i], gt.height, gt.width, gt.focal)
                                    for i in range(gt.c2w.shape[0])]
            if plain is not None:
                state = EditState(plain, points=points, cfg=EditConfig(**RENDERERS[rd]))
                rows[f"render {rd}, base"] = [render_edited(state, gt.c2w[i], gt.height, gt.width, gt.focal)
                                              for i in range(gt.c2w.shape[0])]
        perfect = EditState(bundle, points=points, cfg=EditConfig(colour="atlas", correspondence="deform-gradient"))
        for name, width in [("perfect texture", 0.0), *[(f"texture at {s:g} px", s * footprint) for s in footprints]]:
            fn = lowpassed(texture, width)
            rows[name] = [render_edited(perfect, gt.c2w[i], gt.height, gt.width, gt.focal, texture_fn=fn)
                          for i in range(gt.c2w.shape[0])]
            rows[f"{name} on the surface"] = [
                render_edited(perfect, gt.c2w[i], gt.height, gt.width, gt.focal,
                              texture_fn=lambda x, fn=fn: fn(project(x))) for i in range(gt.c2w.shape[0])]
        scores = {}
        for name, outs in rows.items():
            s = [object_psnr(o["rgb"], o["alpha"], gt.images[i], gt.alphas[i]) for i, o in enumerate(outs)]
            scores[name] = sum(s) / len(s)
        result["poses"][pose] = scores
        log(f"  {pose}: " + ", ".join(f"{k} {v:.2f}" for k, v in scores.items()))
    return result


def markdown(result: dict) -> str:
    """One table: a row per pose, a column per row name, cells 'PSNR (gap to rest)'."""
    poses = result["poses"]
    names = list(poses["rest"])
    lines = [f"Scene `{result['scene']}` (texture `{result['texture']}`), {result['views']} views, object PSNR dB "
             "(change against rest)", "",
             "| pose | " + " | ".join(names) + " |", "|---|" + "---|" * len(names)]
    for pose, row in poses.items():
        cells = [f"{row[n]:.2f}" + ("" if pose == "rest" else f" ({row[n] - poses['rest'][n]:+.2f})") for n in names]
        lines.append(f"| {pose} | " + " | ".join(cells) + " |")
    return "\n".join(lines)


def main(argv=None) -> int:
    from tools.bench import parse, parser, write_json
    from tools.eval_edits import default_renderer

    ap = parser(__doc__)
    ap.add_argument("model", help="model file (.pgt)")
    ap.add_argument("--scene", required=True, help="the scene folder the model was trained on (make-scene)")
    ap.add_argument("--poses", default="stretch", help="comma-separated rig poses (rest is always scored)")
    ap.add_argument("--views", type=int, default=2, help="test cameras (evenly spaced, as eval-edits)")
    ap.add_argument("--renderers", default=default_renderer(),
                    help="comma-separated eval-edits renderer variants (default: the default renderer)")
    ap.add_argument("--footprints", default="1", help="comma-separated low-pass widths in training pixels")
    ap.add_argument("--base", action="store_true", help="also each renderer without the decoder's correction (a "
                    "residual UNet decoder's points' own colours and coverage)")
    args = parse(ap, argv)
    try:
        footprints = [float(v) for v in args.footprints.split(",") if v.strip()]
    except ValueError:
        raise SystemExit(f"--footprints: expected comma-separated numbers, got {args.footprints!r}") from None
    if any(not (math.isfinite(v) and v >= 0) for v in footprints):
        raise SystemExit(f"--footprints: widths must be finite and >= 0, got {args.footprints!r}")
    res = run(args.model, args.scene, [p for p in args.poses.split(",") if p], args.views,
              [r for r in args.renderers.split(",") if r], footprints, base_rows=args.base)
    print(markdown(res))
    write_json(args.json, res)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
