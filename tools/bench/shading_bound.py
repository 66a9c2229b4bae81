"""How much of a lit scene's posed loss is shading that should follow the pose.

A model's colours carry the rest pose's shading: a part the pose turns keeps the light it had, where Blender's frame
shades it by its new normal. This tool estimates a shading function of the surface normal from the model itself and
re-shades the default renderer's geometry-only posed frames with it, then scores both against the Cycles ground
truth (object PSNR, eval-edits' cameras); and scores the renderer's own re-shading (EditConfig reshade), which is
off by default.

The estimate (no light is known): every second training view is rendered at rest; each canonical point takes the
mean linear colour of the training pixels whose surface point it is nearest, and its neighbourhood's normal (the
least-spread direction) turned towards the side it was seen from. Over canonical neighbour pairs of one chromaticity
(every channel's log colour minus their mean within `--chroma`: the same paint, so a brightness change is shading),
the log luminance difference is fitted robustly (Huber, iteratively reweighted) by the difference of log S(n) =
b · Y(n), Y the real spherical harmonics of orders 1 and 2 (8 terms; the constant cancels). Pairs across a paint
edge of another chromaticity do not enter; a texture of one chromaticity in several brightnesses (dark lines on
white) is an outlier the robust fit mostly ignores.

Re-shading a posed frame: per object ray its most-attended neighbour's local deformation gradient F and canonical
normal n; the posed normal F⁻ᵀ n turned towards the camera, the rest normal Fᵀ of that, and the object colour (in
linear light, with the render's coverage) times S(posed) / S(rest), within [0.2, 5]. Rest frames are not changed.
The last columns are the renderer's own re-shading (`EditConfig(reshade="on")`), whose shading is fitted to the
model's atlas instead of the training images (core/edits/shading.py).

    python -m tools.bench.shading_bound MODEL.pgt --scene SCENE [--poses bend,twist,...] [--views 4] [--chroma 0.1]
"""
from __future__ import annotations

from pathlib import Path

from core.edits.shading import atlas_shading, fit_shading, sh_basis


def run(model_path, scene_dir, poses=("bend", "twist", "squash", "stretch", "arm"), views: int = 4,
        chroma: float = 0.1, every: int = 2, log=print) -> dict:
    """The figures (module doc) as a JSON-able dict."""
    import torch
    from scipy.spatial import cKDTree

    from core.bundle import load_bundle
    from core.edits.deformation import field_for
    from core.frames.edited import EditConfig, EditState, render_edited, reshade_rays
    from core.images.colour import srgb_to_linear
    from core.images.dataset import load_split
    from tools.bench.pose_bound import object_psnr
    from tools.eval_edits import deform_points, ground_truth, view_subset_dir
    from tools.machine import machine_info

    scene_dir = Path(scene_dir)
    bundle = load_bundle(model_path)
    xyz = bundle.model.xyz.detach()
    fld = field_for(bundle.model)
    normals = fld.normals().double()
    tree = cKDTree(xyz.numpy())
    n_pts = xyz.shape[0]
    csum = torch.zeros(n_pts, 3, dtype=torch.float64)
    dsum = torch.zeros(n_pts, 3, dtype=torch.float64)
    cnt = torch.zeros(n_pts, dtype=torch.float64)
    train = load_split(scene_dir, "train")
    rest = EditState(bundle)
    for i in range(0, len(train), max(1, int(every))):
        tr = render_edited(rest, train.c2w[i], train.height, train.width, train.focal)["trace"]
        x = tr.x.reshape(-1, 3)
        ok = tr.active & (tr.fg > 0.5) & torch.isfinite(x).all(1) & (train.alphas[i].reshape(-1) > 0.99)
        if not bool(ok.any()):
            continue
        j = torch.from_numpy(tree.query(x[ok].numpy())[1])
        csum.index_add_(0, j, srgb_to_linear(train.images[i].reshape(-1, 3)[ok]).double())
        dsum.index_add_(0, j, -tr.dirs.reshape(-1, 3)[ok].double())
        cnt.index_add_(0, j, torch.ones(j.shape[0], dtype=torch.float64))
    seen = cnt > 0
    colour = csum / cnt.clamp_min(1)[:, None]
    oriented = torch.where(((normals * dsum).sum(1, keepdim=True) < 0), -normals, normals)
    nbr = fld.nbr
    ii = torch.arange(n_pts)[:, None].expand_as(nbr)
    ok = (nbr >= 0) & seen[:, None] & seen[nbr.clamp_min(0)]
    b, used = fit_shading(colour, oriented, torch.stack([ii[ok], nbr[ok]], 1), chroma)
    log_s = sh_basis(oriented[seen]) @ b
    spread = float(log_s.quantile(0.95) - log_s.quantile(0.05)) if log_s.numel() else 0.0
    own = atlas_shading(bundle)
    result = {"model": str(model_path), "scene": scene_dir.name, "views": views, "chroma": chroma,
              "pairs": used, "log_shading_range": spread, "coefficients": [float(v) for v in b],
              "atlas_log_shading_range": None if own is None else own.log_range,
              "machine": machine_info(), "poses": {}}
    log(f"  shading fit: {used} pairs of one chromaticity, log S range (5-95 %) {spread:.3f}; the renderer's own "
        f"(from the atlas): {'none' if own is None else f'{own.log_range:.3f}'}")
    for pose in poses:
        gt = ground_truth(view_subset_dir(scene_dir, views), pose, 1.0, None, log=log)
        pts = torch.from_numpy(deform_points(xyz.numpy(), scene_dir, pose, 1.0)).float()
        plain, shaded, renderer = [], [], []
        st = EditState(bundle, points=pts, cfg=EditConfig())  # one pose: F, the fill and their tables once
        on = EditState(bundle, points=pts, cfg=EditConfig(reshade="on")) if own is not None else None
        for i in range(gt.c2w.shape[0]):
            if on is not None:  # the renderer's own re-shading (EditConfig reshade, its shading fitted to the atlas)
                r = render_edited(on, gt.c2w[i], gt.height, gt.width, gt.focal)
                renderer.append(object_psnr(r["rgb"], r["alpha"], gt.images[i], gt.alphas[i]))
            out = render_edited(st, gt.c2w[i], gt.height, gt.width, gt.focal)
            tr = out["trace"]
            rgb = out["rgb"].reshape(-1, 3).double()
            sel = torch.nonzero(tr.active & (tr.fg > 1e-4)).squeeze(1)
            if sel.numel():  # as the renderer's own re-shading, with the shading fitted to the training images
                reshade_rays(st, tr, rgb, out["alpha"].reshape(-1).double(), sel, b)
            plain.append(object_psnr(out["rgb"], out["alpha"], gt.images[i], gt.alphas[i]))
            shaded.append(object_psnr(rgb.reshape(out["rgb"].shape).float(), out["alpha"], gt.images[i],
                                      gt.alphas[i]))
        row = {"render": sum(plain) / len(plain), "re-shaded": sum(shaded) / len(shaded),
               "renderer re-shaded": sum(renderer) / len(renderer) if renderer else None}
        result["poses"][pose] = row
        log(f"  {pose}: render {row['render']:.2f}, re-shaded {row['re-shaded']:.2f}, by the renderer "
            f"{row['renderer re-shaded'] if renderer else float('nan'):.2f}")
    return result


def markdown(result: dict) -> str:
    own = result.get("atlas_log_shading_range")
    lines = [f"Scene `{result['scene']}`, {result['views']} views; shading fit: {result['pairs']} pairs, log S range "
             f"{result['log_shading_range']:.3f}; the renderer's own fit (from the atlas): "
             f"{'none' if own is None else f'{own:.3f}'}; object PSNR dB", "",
             "| pose | render | re-shaded | change | re-shaded by the renderer (reshade on) | change |",
             "|---|---|---|---|---|---|"]
    for pose, row in result["poses"].items():
        mine = row.get("renderer re-shaded")
        tail = "– | –" if mine is None else f"{mine:.2f} | {mine - row['render']:+.2f}"
        lines.append(f"| {pose} | {row['render']:.2f} | {row['re-shaded']:.2f} | "
                     f"{row['re-shaded'] - row['render']:+.2f} | {tail} |")
    return "\n".join(lines)


def main(argv=None) -> int:
    from tools.bench import parse, parser, write_json

    ap = parser(__doc__)
    ap.add_argument("model", help="model file (.pgt)")
    ap.add_argument("--scene", required=True, help="the scene folder the model was trained on (make-scene)")
    ap.add_argument("--poses", default="bend,twist,squash,stretch,arm", help="comma-separated rig poses")
    ap.add_argument("--views", type=int, default=4, help="test cameras (evenly spaced, as eval-edits)")
    ap.add_argument("--chroma", type=float, default=0.1, help="pairs of one chromaticity: every channel's log "
                    "colour minus their mean within this")
    ap.add_argument("--every", type=int, default=2, help="every how many-th training view is rendered for the fit")
    args = parse(ap, argv)
    if not args.chroma > 0:
        raise SystemExit(f"--chroma: expected a positive number, got {args.chroma}")
    res = run(args.model, args.scene, [p for p in args.poses.split(",") if p], args.views, args.chroma, args.every)
    print(markdown(res))
    write_json(args.json, res)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
