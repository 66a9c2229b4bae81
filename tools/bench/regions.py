"""Where a posed frame's error sits: object PSNR split by region (joint band, holes, spill, wrong surface).

For one rig pose of a built-in scene, renders the model's posed points with each renderer variant of
`tools.eval_edits.RENDERERS` (geometry only, the same test cameras and Cycles ground truth as `pointgt
eval-edits`) and casts every pixel's ray at the true posed mesh in Blender (mathutils BVH) for its depth and its
canonical (rest-pose) surface point. Each object pixel (ground-truth ∪ rendered foreground, as the object PSNR)
falls into one region:

  hole     the true mesh covers it, the render does not (alpha <= 0.5)
  spill    the render covers it, the true mesh does not
  covered  both; of these, "deep" when the render's surface point lies more than --tau world units from the true
           surface along the ray (the ray shows another part of the surface), the rest "ok"

each split by "joint" (the visible canonical point within --joint world units of the plane through the scene's
centre across the pose's `along` axis: the bones' blend band for the armature pose) or "elsewhere". For each
region: its pixels and the dB the pooled object PSNR would gain if its error were zero. The deep pixels get two
diagnostics: the attention share on neighbours within 0.1 units of the true canonical point, and the mean depth
of the other neighbours behind the true surface, in point spacings.

A line under the table says how far the rig itself moves the model's points from the posed mesh (`rig_offsets`):
for every pixel the true mesh covers, the distance from the true posed surface point to the nearest of the posed
model points whose canonical positions are the 4 nearest to the pixel's true canonical point, in spacings (median
and 90th percentile, joint band / elsewhere). A rig whose weights change fast across the model's own position
noise (an envelope's falloff band) puts the points off the posed mesh before any renderer sees them.

    python -m tools.bench.regions MODEL.pgt --scene SCENE --pose arm --views 2 \\
        --renderers paper,f-fill-fold,f-fill-fold-occ --variant "f-fill-fold:f_fill_ratio=2.5,temperature=0.5"

--variant RENDERER:FIELD=VALUE,... adds a renderer with some EditConfig fields changed (repeatable).
"""
from __future__ import annotations

import math
from pathlib import Path

import numpy as np

REGIONS = ("hole", "spill", "deep", "ok")


def parse_variant(text: str, renderers: dict) -> tuple[str, dict]:
    """"RENDERER:FIELD=VALUE,..." -> (its name, the EditConfig fields): the renderer's fields with these changed
    (values read as JSON numbers / booleans, else kept as text)."""
    import dataclasses
    import json

    from core.frames.edited import EditConfig

    base, _, rest = text.partition(":")
    if base not in renderers:
        raise SystemExit(f"--variant {text!r}: unknown renderer {base!r}; choose from {', '.join(renderers)}")
    fields = {f.name for f in dataclasses.fields(EditConfig)}
    over = {}
    for item in filter(None, rest.split(",")):
        key, eq, value = item.partition("=")
        if not eq or key not in fields:
            raise SystemExit(f"--variant {text!r}: {item!r} is not FIELD=VALUE with a field of EditConfig")
        try:
            over[key] = json.loads(value)
        except ValueError:
            over[key] = value
    return text, {**renderers[base], **over}


def region_gains(err: np.ndarray, masks: dict) -> dict:
    """dB the pooled PSNR over all pixels of `err` gains if the error of each region were zero.

    err [P] squared error per pixel summed over its channels (the pixels the PSNR pools: 3 channels each);
    masks: name -> [P] bool. Returns name -> (gain dB, pixels). Pixels outside every mask still count."""
    total = float(err.sum())
    n = 3 * err.shape[0]
    out = {}
    base = -10.0 * math.log10(max(total, 1e-12) / n)
    for name, m in masks.items():
        rest = total - float(err[m].sum())
        out[name] = (-10.0 * math.log10(max(rest, 1e-12) / n) - base, int(m.sum()))
    return out


def rig_offsets(canonical: np.ndarray, posed: np.ndarray, true_can: np.ndarray, true_posed: np.ndarray,
                in_joint: np.ndarray, spacing: float, near: int = 4) -> dict:
    """How far the rig put the model's points from the posed mesh (module doc). canonical / posed [N, 3] the
    model's points before / after the rig, true_can / true_posed [P, 3] the canonical and posed true surface points
    of the P pixels the mesh covers, in_joint [P] bool. Returns {"joint": (median, p90), "elsewhere": (median,
    p90)} in spacings (NaN where a group has no pixel or no finite point)."""
    from scipy.spatial import cKDTree

    ok = np.isfinite(canonical).all(1) & np.isfinite(posed).all(1)
    keep = np.isfinite(true_can).all(1) & np.isfinite(true_posed).all(1)
    out = {"joint": (math.nan, math.nan), "elsewhere": (math.nan, math.nan)}
    if not ok.any() or not keep.any():
        return out
    can, pos = canonical[ok], posed[ok]
    k = min(int(near), can.shape[0])
    _, j = cKDTree(can).query(true_can[keep], k=k)
    j = j.reshape(j.shape[0], k)
    dist = np.linalg.norm(pos[j] - true_posed[keep][:, None], axis=-1).min(1) / max(float(spacing), 1e-30)
    for name, m in (("joint", in_joint[keep]), ("elsewhere", ~in_joint[keep])):
        if m.any():
            out[name] = (float(np.median(dist[m])), float(np.quantile(dist[m], 0.9)))
    return out


def true_surface(scene_dir: Path, pose: str, magnitude: float, c2w: np.ndarray, height: int, width: int, focal):
    """Ray cast of the true posed mesh (Blender): per view, hit [V, R] bool, depth [V, R] along the ray and the
    canonical surface point [V, R, 3] (NaN where the ray misses), R = height * width."""
    import bpy
    import torch
    from mathutils import Vector
    from mathutils.bvhtree import BVHTree

    from core.images.cameras import pixel_rays
    from tools.scenes.poses import apply_pose
    from tools.scenes.render import open_scene, world_vertices

    spec, obj = open_scene(scene_dir)
    rest = world_vertices(obj)
    if pose != "rest":
        apply_pose(obj, spec, pose, magnitude)
        mod = obj.modifiers[f"pgt_{pose}"]
        mod.show_viewport = mod.show_render = True
    deps = bpy.context.evaluated_depsgraph_get()
    deps.update()
    me = obj.evaluated_get(deps).to_mesh()
    me.calc_loop_triangles()
    posed = world_vertices(obj, me)
    tris = np.array([t.vertices[:] for t in me.loop_triangles])
    bvh = BVHTree.FromPolygons([tuple(p) for p in posed], [tuple(t) for t in tris])
    hits, depths, cans = [], [], []
    for i in range(c2w.shape[0]):
        o, d = pixel_rays(torch.as_tensor(c2w[i], dtype=torch.float64), height, width, focal)
        o, d = o.reshape(-1, 3).numpy(), d.reshape(-1, 3).numpy()
        hit = np.zeros(len(o), bool)
        dep = np.full(len(o), np.nan)
        can = np.full((len(o), 3), np.nan)
        for r in range(len(o)):
            loc, _, ti, dist = bvh.ray_cast(Vector(o[r]), Vector(d[r]))
            if loc is None:
                continue
            a, b, c = posed[tris[ti]]
            v0, v1, v2 = b - a, c - a, np.array(loc) - a
            d00, d01, d11, d20, d21 = v0 @ v0, v0 @ v1, v1 @ v1, v2 @ v0, v2 @ v1
            den = d00 * d11 - d01 * d01
            if abs(den) < 1e-30:
                continue
            wb, wc = (d11 * d20 - d01 * d21) / den, (d00 * d21 - d01 * d20) / den
            hit[r], dep[r] = True, dist
            can[r] = (1 - wb - wc) * rest[tris[ti][0]] + wb * rest[tris[ti][1]] + wc * rest[tris[ti][2]]
        hits.append(hit)
        depths.append(dep)
        cans.append(can)
    return np.array(hits), np.array(depths), np.array(cans)


def run(model_path, scene_dir, pose: str = "arm", magnitude: float = 1.0, views: int = 2,
        renderers=("f-fill-fold",), joint: float = 0.5, tau: float = 0.15, variants=(), log=print) -> dict:
    """The figures (module doc) as a JSON-able dict; renderers: names of eval-edits' RENDERERS, variants:
    "RENDERER:FIELD=VALUE,..." strings (`parse_variant`)."""
    import torch

    from core.bundle import load_bundle
    from core.frames.edited import EditConfig, EditState, render_edited
    from tools.eval_edits import RENDERERS, deform_points, ground_truth, view_subset_dir
    from tools.machine import machine_info
    from tools.scenes.poses import pose_spec
    from tools.scenes.spec import load_scene_spec

    scene_dir = Path(scene_dir)
    spec = load_scene_spec(scene_dir)
    along = int(pose_spec(spec, pose).get("along", 0)) if pose != "rest" else 0
    centre = float(spec["bbox"]["center"][along])
    configs = {}
    for rd in renderers:
        if rd not in RENDERERS:
            raise SystemExit(f"--renderers: unknown renderer {rd!r}; choose from {', '.join(RENDERERS)}")
        configs[rd] = RENDERERS[rd]
    configs.update(parse_variant(v, RENDERERS) for v in variants)
    bundle = load_bundle(model_path)
    spacing = float(bundle.model.spacing)
    gt = ground_truth(view_subset_dir(scene_dir, views), pose, magnitude, None, log=log)
    can = bundle.model.xyz.detach().numpy()
    points = None if pose == "rest" else torch.from_numpy(deform_points(can, scene_dir, pose, magnitude))
    hit, gdepth, gcan = true_surface(scene_dir, pose, magnitude, gt.c2w.numpy(), gt.height, gt.width, gt.focal)
    result = {"model": str(model_path), "scene": spec.get("name"), "pose": pose, "magnitude": magnitude,
              "views": int(gt.c2w.shape[0]), "size": gt.width, "joint": joint, "tau": tau, "spacing": spacing,
              "machine": machine_info(), "renderers": {}}
    if points is not None:  # the rig's own offset of the model's points from the posed mesh, over every view
        from core.images.cameras import pixel_rays

        tc, tp, tj = [], [], []
        for i in range(gt.c2w.shape[0]):
            o, d = pixel_rays(gt.c2w[i].double(), gt.height, gt.width, gt.focal)
            o, d = o.reshape(-1, 3).numpy(), d.reshape(-1, 3).numpy()
            h = hit[i]
            tc.append(gcan[i][h])
            tp.append(o[h] + d[h] * gdepth[i][h][:, None])
            tj.append(np.abs(gcan[i][h][:, along] - centre) < joint)
        result["rig_offsets_spacings"] = rig_offsets(can, points.numpy(), np.concatenate(tc), np.concatenate(tp),
                                                     np.concatenate(tj), spacing)
    for rd, fields in configs.items():
        state = EditState(bundle, points=points, cfg=EditConfig(**fields))
        errs, masks, psnrs = [], {}, []
        share, behind = [], []
        for i in range(gt.c2w.shape[0]):
            out = render_edited(state, gt.c2w[i], gt.height, gt.width, gt.focal)
            tr = out["trace"]
            rgb, cover = out["rgb"].reshape(-1, 3).numpy(), out["alpha"].reshape(-1).numpy()
            img, alpha = gt.images[i].reshape(-1, 3).numpy(), gt.alphas[i].reshape(-1).numpy()
            obj = (alpha > 0.5) | (cover > 0.5)
            err = ((rgb - img) ** 2).sum(1)
            psnrs.append(-10.0 * math.log10(max(float(err[obj].sum()), 1e-12) / (3 * int(obj.sum()))))
            sel = torch.nonzero(tr.active & (tr.fg > 1e-4)).squeeze(1)
            xc = np.full((err.shape[0], 3), np.nan)
            if sel.numel():
                xc[sel.numpy()] = state.canonical_surface(tr, sel).numpy()
            # the visible canonical point: the true one where the mesh is hit, else the render's
            vis = np.where(hit[i], gcan[i][:, along], xc[:, along])
            in_joint = np.abs(np.nan_to_num(vis - centre, nan=np.inf)) < joint
            ours, true = cover > 0.5, alpha > 0.5
            off = np.abs(np.nan_to_num(tr.depth.numpy() - gdepth[i], nan=np.inf)) > tau
            reg = {"hole": true & ~ours, "spill": ~true & ours, "deep": true & ours & hit[i] & off,
                   "ok": true & ours & ~(hit[i] & off)}
            for name, m in reg.items():
                for where, wm in (("joint", in_joint), ("elsewhere", ~in_joint)):
                    masks.setdefault(f"{name} {where}", []).append((m & wm)[obj])
            errs.append(err[obj])
            deep = torch.from_numpy(np.nonzero(reg["deep"] & in_joint)[0])
            if deep.numel():
                idx = tr.idx[deep]
                valid = idx >= 0
                w = tr.fg_weights[deep] * valid
                near = (state.p_can[idx.clamp_min(0)] - torch.from_numpy(gcan[i][deep.numpy()]).float()[:, None]
                        ).norm(dim=-1) < 0.1
                t = ((state.points[idx.clamp_min(0)] - tr.origins[deep][:, None]) * tr.dirs[deep][:, None]).sum(-1)
                rel = (t - torch.from_numpy(gdepth[i][deep.numpy()]).float()[:, None]) / spacing
                other = w * (~near & valid)
                share += (w * near).sum(1).tolist()
                behind += ((other * rel).sum(1) / other.sum(1).clamp_min(1e-12)).tolist()
        err = np.concatenate(errs)
        gains = region_gains(err, {k: np.concatenate(v) for k, v in masks.items()})
        result["renderers"][rd] = {
            "psnr_object": float(np.mean(psnrs)), "filled_points": state.filled_points,
            "regions": {k: {"gain_db": g, "pixels": n} for k, (g, n) in gains.items()},
            "deep_joint_true_share": float(np.mean(share)) if share else float("nan"),
            "deep_joint_others_behind_spacings": float(np.nanmean(behind)) if behind else float("nan")}
    return result


def markdown(result: dict) -> str:
    """The figures as one table: a row per renderer, per region its gain (dB) / pixels."""
    names = [f"{r} {w}" for r in REGIONS for w in ("joint", "elsewhere")]
    lines = [f"Scene `{result['scene']}`, pose {result['pose']} m={result['magnitude']:g}, {result['views']} views at "
             f"{result['size']}², joint band ±{result['joint']:g}, deep = surface > {result['tau']:g} off the true one; "
             "per region: dB gained if its error were zero / pixels", "",
             "| renderer | object PSNR | " + " | ".join(names) + " | deep joint: true share / others behind (sp) |",
             "|---|---|" + "---|" * len(names) + "---|"]
    for rd, row in result["renderers"].items():
        cells = [f"{row['regions'][n]['gain_db']:.2f} / {row['regions'][n]['pixels']}" for n in names]
        lines.append(f"| {rd} | {row['psnr_object']:.2f} | " + " | ".join(cells) +
                     f" | {row['deep_joint_true_share']:.2f} / {row['deep_joint_others_behind_spacings']:.1f} |")
    rig = result.get("rig_offsets_spacings")
    if rig:
        lines += ["", "Rig: posed model points from the posed mesh (best of the 4 canonically nearest, spacings, "
                  f"median / 90th percentile): joint {rig['joint'][0]:.2f} / {rig['joint'][1]:.2f}, elsewhere "
                  f"{rig['elsewhere'][0]:.2f} / {rig['elsewhere'][1]:.2f}"]
    return "\n".join(lines)


def main(argv=None) -> int:

    from tools.bench import parse, parser, write_json
    from tools.eval_edits import compared_renderers

    ap = parser(__doc__)
    ap.add_argument("model", help="model file (.pgt)")
    ap.add_argument("--scene", required=True, help="the scene folder the model was trained on (make-scene)")
    ap.add_argument("--pose", default="arm", help="rig pose of the scene (default: the armature joint)")
    ap.add_argument("--magnitude", type=float, default=1.0, help="pose magnitude")
    ap.add_argument("--views", type=int, default=2, help="test cameras (evenly spaced, as eval-edits)")
    ap.add_argument("--renderers", default=",".join(compared_renderers()),
                    help="comma-separated eval-edits renderer variants (default: the paper's and the default one)")
    ap.add_argument("--joint", type=float, default=0.5, help="half width of the joint band (world units)")
    ap.add_argument("--tau", type=float, default=0.15, help="surface depth error that counts as another part")
    ap.add_argument("--variant", action="append", default=[],
                    help="RENDERER:FIELD=VALUE,... a renderer with EditConfig fields changed (repeatable)")
    args = parse(ap, argv)
    res = run(args.model, args.scene, args.pose, args.magnitude, args.views,
              [r for r in args.renderers.split(",") if r], args.joint, args.tau, args.variant)
    print(markdown(res))
    write_json(args.json, res)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
