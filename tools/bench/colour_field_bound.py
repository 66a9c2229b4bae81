"""How well can *any* colour field on the surface reproduce the test views? Bounds for the atlas (needs bpy).

    python -m tools.bench.colour_field_bound --model M.pgt --scene DIR [--every 2] [--knn 16] [--json OUT]

M.pgt needs an atlas (the rows render like an atlas-coloured edited frame).

DIR is a scene made by `pointgt make-scene` (its `scene.blend` holds the true mesh). An atlas colours each ray by
a function of one surface point, so two things bound it: how view-consistent the surface points are, and how much
of the image a per-point colour can hold at all at this resolution (anti-aliased pixels, thin stripes). Rows, all
on the test views with the model's coverage (as an atlas-coloured edited frame: the decoder's mask head, else
1 − background weight) and its point render elsewhere, so that only the object colour differs:

- point render: the model as trained (decoder included);
- colour field at the true surface: each ray's true hit point (the ray cast against the scene mesh) coloured by the
  mean pixel colour of the k nearest training samples taken at their own true hits — the best a function of the
  surface point can do with perfect geometry;
- colour field at x_i: the same with the model's surface points x_i (projected on their rays, as the atlas samples
  are made) — the best any atlas of this model can do;
- colour field at the true surface, true coverage: true hits composited with the image's own alpha, no model at
  all — what a per-surface-point colour can hold at this resolution;

and the error of x_i against the true hit (distance, and its component along the ray). Object PSNR uses ground
truth ∪ rendered foreground like everywhere else.
"""
from __future__ import annotations

import sys
import time
from dataclasses import replace
from pathlib import Path

import numpy as np
import torch

from tools.bench import add_scene, parse, parser, write_json
from tools.machine import machine_line


def rest_mesh_tree(scene_dir: Path):
    """A mathutils BVH tree of the scene's object at rest, in world space (opens its scene.blend). Callable first
    in a process: bpy (imported by tools.scenes.render) must come before mathutils, which ships inside it."""
    from tools.scenes.render import open_scene, world_vertices  # imports bpy

    from mathutils.bvhtree import BVHTree

    _, obj = open_scene(scene_dir)
    verts = [tuple(v) for v in world_vertices(obj)]
    return BVHTree.FromPolygons(verts, [tuple(p.vertices) for p in obj.data.polygons])


def mesh_ray_caster(scene_dir: Path):
    """cast(origins [R, 3], dirs [R, 3]) -> hits [R, 3] float64 (NaN = miss) against the scene's rest mesh."""
    from mathutils import Vector

    tree = rest_mesh_tree(scene_dir)

    def cast(o: np.ndarray, d: np.ndarray) -> np.ndarray:
        out = np.full((len(o), 3), np.nan)
        for i in range(len(o)):  # mathutils has no batched ray cast; ~5 µs a ray
            loc = tree.ray_cast(Vector(o[i]), Vector(d[i]))[0]
            if loc is not None:
                out[i] = loc
        return out
    return cast


def main(argv=None) -> int:
    ap = parser(__doc__)
    add_scene(ap, "use every n-th view of the train and test splits")
    ap.add_argument("--model", required=True, help="model file (.pgt)")
    ap.add_argument("--knn", type=int, default=16, help="training samples averaged per ray")
    args = parse(ap, argv)
    from core.bundle import load_bundle
    from core.images.metrics import object_mask, psnr
    from core.points.render import shade_frame, trace_frame
    from core.images.dataset import load_split
    from core.edits.correspondence import ray_canonical_points
    from core.frames.edited import render_edited
    from tools.bench.atlas_vs_papr import atlas_coloured, knn_colour

    t_start = time.perf_counter()
    scene = Path(args.scene)
    cast = mesh_ray_caster(scene)
    bundle = load_bundle(args.model, "cpu")
    if bundle.atlas is None:
        raise SystemExit(f"{args.model}: the colour-field rows render like an atlas-coloured edited frame, which "
                         "needs a model with an atlas; run `pointgt atlas` on it first")
    model = bundle.model
    state = atlas_coloured(bundle, bundle.atlas, antialias=1)  # one lookup per pixel, at the ray's point
    train, test = load_split(scene, "train"), load_split(scene, "test")

    def view(split, i):
        """(trace, true hits [R, 3] (NaN = miss), x_i on its ray [R, 3], coverage [R]) of view i."""
        tr = trace_frame(model, split.c2w[i], split.height, split.width, split.focal)
        fg = 1.0 - tr.bg
        x = ray_canonical_points(tr)
        hits = torch.full_like(x, float("nan"))
        look = (split.alphas[i].reshape(-1) > 0.5) | (fg > 0.5)
        hits[look] = torch.from_numpy(cast(tr.origins[look].double().numpy(),
                                           tr.dirs[look].double().numpy())).float()
        return tr, hits, x, fg

    samples = {"true surface": ([], []), "x_i": ([], [])}
    for i in range(0, len(train), args.every):
        _, hits, x, fg = view(train, i)
        sel = train.alphas[i].reshape(-1) > 0.5
        rgb = train.images[i].reshape(-1, 3)
        for name, pts, ok in (("true surface", hits, sel & torch.isfinite(hits).all(1)), ("x_i", x, sel & (fg > 0.5))):
            samples[name][0].append(pts[ok]), samples[name][1].append(rgb[ok])
    fields = {}
    for name, (xs, cs) in samples.items():
        xyz, col = torch.cat(xs), torch.cat(cs)
        fields[name] = knn_colour(xyz, col, args.knn)
        print(f"{name}: {len(xyz)} training samples", flush=True)

    scores = {"point render": [], "colour field at the true surface": [], "colour field at x_i": [],
              "colour field at the true surface, true coverage": []}
    dist, along = [], []
    for i in range(0, len(test), args.every):
        tr, hits, x, fg = view(test, i)
        h, w = tr.shape
        papr = shade_frame(model, tr).clamp(0, 1)
        gt, alpha = test.images[i], test.alphas[i]
        mask = object_mask(alpha, fg.reshape(h, w))
        found = torch.isfinite(hits).all(1)
        # rays whose true ray misses the mesh keep x_i as their colour source
        at_true = torch.where(found[:, None], hits, x)
        cam = (test.c2w[i], test.height, test.width, test.focal)
        frames = {"point render": papr,
                  "colour field at the true surface": render_edited(state, *cam, trace=replace(tr, x=at_true),
                                                                    texture_fn=fields["true surface"])["rgb"],
                  "colour field at x_i": render_edited(state, *cam, trace=replace(tr, x=x),
                                                       texture_fn=fields["x_i"])["rgb"]}
        # per-point colour capacity alone: true hits and the image's own alpha as coverage (no model at all)
        a = alpha.reshape(-1)
        use = found & (a > 0)
        rgb = torch.ones(len(a), 3)
        rgb[use] = a[use, None] * fields["true surface"](hits[use]) + (1 - a[use, None])
        frames["colour field at the true surface, true coverage"] = rgb.reshape(h, w, 3)
        for name, frame in frames.items():
            scores[name].append(psnr(frame, gt, mask))
        both = (fg > 0.5) & found
        dv = (x[both] - hits[both]).double()
        dist.append(dv.norm(dim=1).numpy())
        along.append((dv * tr.dirs[both].double()).sum(1).abs().numpy())
    dist, along = np.concatenate(dist), np.concatenate(along)
    pixel = float(np.median(np.linalg.norm(test.c2w[:, :3, 3].numpy(), axis=1))) / test.focal
    result = {"model": args.model, "scene": str(scene), "every": args.every, "knn": args.knn,
              "object_psnr": {k: float(np.mean(v)) for k, v in scores.items()},
              "x_error": {"median": float(np.median(dist)), "p90": float(np.percentile(dist, 90)),
                          "along_ray_median": float(np.median(along)), "pixel_footprint": pixel},
              "seconds": round(time.perf_counter() - t_start, 1)}
    print(machine_line())
    print(f"{args.model} on {scene}: test views every {args.every}, k = {args.knn}, {result['seconds']} s")
    print("| colour of each object ray | object PSNR (dB) |")
    print("|---|---|")
    for k, v in result["object_psnr"].items():
        print(f"| {k} | {v:.2f} |")
    e = result["x_error"]
    print(f"x_i against the true hit: median {e['median']:.4f}, p90 {e['p90']:.4f}, along the ray (median) "
          f"{e['along_ray_median']:.4f} world units; one pixel is {e['pixel_footprint']:.4f} at the camera distance")
    write_json(args.json, result)
    return 0


if __name__ == "__main__":
    sys.exit(main())
