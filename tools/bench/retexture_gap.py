"""Where a baked retexture loses against the perfect atlas: one fitted atlas per texel density, then the same
retexture baked and looked up in several ways, each scored at rest against Blender's frames (object PSNR).

    python -m tools.bench.retexture_gap --scene-root DIR --scenes cloth,tube --steps 600 --threads 1
    python -m tools.bench.retexture_gap ... --texel-densities 4,8 --keep DIR2   (DIR2/<scene>.tpp<D>.pgt)

For every scene DIR/<name>/ with a stage-1 model DIR/<name>.pgt or DIR/<name>.default.pgt (or with --tag T
DIR/<name>.T.default.pgt, as `tools.bench.atlas --scene-root`), stage 2 is fitted in memory with each
--texel-densities value (the `--atlas-texels-per-pixel` rule; the charts are the same fit, only the layout after
them differs) and the rows are:
  perfect atlas      the texture evaluated exactly at the canonical points the render uses (the reference)
  baked              the retexture baked with --bake-source (default: fitted at the stored surface samples), the
                     edit mask from the atlas change; frames look the atlas up as --lookup says (default: through
                     the samples)
  mask = 1           the same image with every texel counted as painted (the edit mask's share of the gap)
  baked at points    fn at each texel's single surface point instead of splatted from the samples
  kernel ×s          the splat bake with its kernel width times s (--bake-sigmas)
  antialias A        lookups per pixel side, for both the bake and the reference (--antialias)
and, per density, the median ratio of the texture coordinates' derivative along the samples' normal to that along
the surface (`normal_ratio`: a chart map that changes across the samples' slab sends a point off its middle to
another place's texels), the share of the test views' object lookups that read a texel without a surface point or one
whose surface point lies more than 3 sample spacings from the looked-up point (a folded chart map), and where the
lookups without a point are (`lookup_stats`: in an island's padding, on another chart than the nearest sample, how far
from that sample in space and in texels).
"""
from __future__ import annotations

import dataclasses
import sys
import time

import torch

from tools.bench import parse_with_config, parser, write_json


def lookup_stats(bundle, gt, spacing: float) -> dict:
    """Object rays of the test views (rest): share whose nearest texel has no surface point (`no_point`) and share
    whose texel's surface point is more than 3 sample spacings from the ray's canonical point (`far`); median
    distance in sample spacings. Of the lookups without a point: the share outside every island (`off_island`, the
    padding; island layouts only), the share whose chart is not the chart of the stored surface sample nearest their
    (projected) point (`no_point_other_chart`), that sample's median distance in sample spacings
    (`no_point_sample_dist`) and how many texels from the lookup it lands (`no_point_sample_texels`, median). Of the
    lookups that are far or without a point, the share for which another chart's texel at that chart's
    coordinates holds a surface point within 3 sample spacings (`bad_other_chart_near`: what choosing the chart
    by the texel map instead of by the chart network could win back)."""
    from scipy.spatial import cKDTree

    from core.atlas.packing import chart_coords, uv_to_pixel
    from core.edits.correspondence import ray_canonical_points
    from core.points.render import trace_frame

    atlas = bundle.atlas
    tp = atlas.texel_points()
    H, W = tp.shape[:2]
    island = atlas.layout.island_pixels if atlas.islands else None
    S = atlas.bake_samples
    tree = cKDTree(S.numpy()) if S is not None and len(S) else None

    def cell(pix):  # continuous (col, row) -> the texel's (row, col)
        return pix[:, 1].floor().long().clamp(0, H - 1), pix[:, 0].floor().long().clamp(0, W - 1)

    no_point, far, dists, total, off_island, other, bad_alt = 0, 0, [], 0, 0, 0, 0
    near_d, near_t = [], []
    for i in range(gt.images.shape[0]):
        tr = trace_frame(bundle.model, gt.c2w[i], gt.height, gt.width, gt.focal)
        hit = tr.active & (tr.fg > 0.5)
        if not bool(hit.any()):
            continue
        x = ray_canonical_points(tr)[hit]
        probs, uv = atlas.chart_uv(x)  # as atlas_pixel_coords: the most probable chart's pixel
        chart = probs.argmax(-1)
        pix = uv_to_pixel(chart_coords(uv, chart), chart, atlas.layout)
        r, c = cell(pix)
        p = tp[r, c]
        ok = torch.isfinite(p).all(-1)
        d = (p[ok] - x[ok]).norm(dim=-1) / max(spacing, 1e-12)
        no_point += int((~ok).sum())
        if island is not None:
            off_island += int((~island[r, c]).sum())
        if tree is not None and bool((~ok).any()):
            xs = atlas.on_surface(x[~ok])
            dn, j = tree.query(xs.cpu().numpy(), k=1)
            near = S[torch.from_numpy(j)].to(xs.device)
            near_chart, near_pix = atlas.atlas_pixel_coords(near)
            other += int((chart[~ok] != near_chart).sum())
            near_d.append(torch.from_numpy(dn) / max(spacing, 1e-12))
            near_t.append((near_pix - pix[~ok]).norm(dim=-1).cpu())
        far += int((d > 3).sum())
        bad = ~ok
        bad[ok] = d > 3
        if bool(bad.any()):  # the other charts' texels at those points
            near = torch.zeros(int(bad.sum()), dtype=torch.bool, device=x.device)
            for k in range(probs.shape[1]):
                ck = torch.full_like(chart[bad], k)
                pt = tp[cell(uv_to_pixel(uv[bad, k], ck, atlas.layout))]
                dk = (pt - x[bad]).norm(dim=-1) / max(spacing, 1e-12)
                near |= (chart[bad] != k) & torch.isfinite(dk) & (dk <= 3)
            bad_alt += int(near.sum())
        dists.append(d)
        total += int(x.shape[0])
    d = torch.cat(dists) if dists else torch.zeros(0)
    med = lambda v: float(torch.cat(v).double().median()) if v else float("nan")  # noqa: E731
    return {"no_point": no_point / max(total, 1), "far": far / max(total, 1),
            "dist_median": float(d.median()) if d.numel() else float("nan"),
            "off_island": off_island / max(total, 1), "no_point_other_chart": other / max(no_point, 1),
            "no_point_sample_dist": med(near_d), "no_point_sample_texels": med(near_t),
            "bad_other_chart_near": bad_alt / max(no_point + far, 1)}


def normal_ratio(atlas, max_samples: int = 3000) -> float:
    """Median over the stored surface samples of |J n| / rms(|J t1|, |J t2|): how fast the texture coordinates of
    the sample's chart change along its normal (PCA) against along the surface (central differences)."""
    import numpy as np

    from core.atlas.fit import sample_normals

    S = atlas.bake_samples
    sel = torch.randperm(S.shape[0], generator=torch.Generator().manual_seed(0))[:max_samples]
    x = S[sel].float()
    # the frame of each sample: its normal and two tangents from the same neighbourhood
    normals = torch.from_numpy(sample_normals(S.double().numpy())[sel.numpy()])
    t1 = torch.linalg.cross(normals, torch.tensor([[0.577, 0.577, 0.577]]).expand_as(normals))
    t1 = t1 / t1.norm(dim=-1, keepdim=True).clamp_min(1e-12)
    t2 = torch.linalg.cross(normals, t1)
    eps = 1e-3 * float((S.max(0).values - S.min(0).values).max())
    with torch.no_grad():
        probs, _ = atlas.chart_uv(x, placed=False)
        c = probs.argmax(-1)
        ar = torch.arange(len(x))

        def grad(d):
            return ((atlas.chart_uv(x + eps * d, placed=False)[1] - atlas.chart_uv(x - eps * d, placed=False)[1])
                    [ar, c] / (2 * eps)).norm(dim=-1)
        gn, g1, g2 = grad(normals), grad(t1), grad(t2)
    r = gn / torch.sqrt(0.5 * (g1 ** 2 + g2 ** 2)).clamp_min(1e-12)
    return float(np.median(r[torch.isfinite(r)].numpy()))


def gap_rows(bundle_path, scene, cfg, densities, views: int, bake_sigmas, antialias, retexture: str = "stripes",
             keep=None, log=print, lookup: str = "samples", bake_source: str = "auto") -> list[dict]:
    """The rows (module doc) for one scene: dicts with density, row label, object PSNR against Blender and against
    the perfect-atlas frame. lookup: the frames' (EditConfig lookup); bake_source: the bake's ("kernel" rows splat)."""
    from core.bundle import load_bundle, save_bundle
    from core.edits.bake import bake
    from core.edits.procedural import evaluate
    from core.frames.edited import EditConfig, EditState
    from core.images.dataset import load_split
    from core.pipeline import fit_atlas_stage
    from tools.eval_edits import ground_truth, score_frames, view_subset_dir
    from tools.scenes.spec import load_scene_spec

    spec = load_scene_spec(scene)
    gt = ground_truth(view_subset_dir(scene, views), "rest", 0.0, retexture, None, log)
    train = load_split(scene, "train")
    box, params = spec["bbox"], spec["texture"]["params"]

    def fn(p):
        return evaluate(retexture, p, box["center"], box["half_size"], params.get(retexture))[0], None

    rows = []
    traces: dict = {}
    for dens in densities:
        bundle = load_bundle(bundle_path, "cpu")
        t0 = time.perf_counter()
        hist = fit_atlas_stage(bundle, train, dataclasses.replace(cfg, texels_per_pixel=dens), show_progress=False)
        seconds = time.perf_counter() - t0
        if keep:
            save_bundle(f"{keep}/{scene.name}.tpp{dens:g}.pgt", bundle, backup=False)
        atlas = bundle.atlas
        H, W = atlas.layout.shape
        info = {"scene": scene.name, "density": dens, "size": f"{W}x{H}", "seconds": round(seconds, 1),
                **lookup_stats(bundle, gt, float(hist["spacing"])), "normal_ratio": normal_ratio(atlas)}
        log(f"[{scene.name} tpp {dens:g}] " + "  ".join(f"{k}={v}" for k, v in info.items()))

        def score(label, image, ecfg=None, **kw):
            state = EditState(bundle, atlas=image, cfg=dataclasses.replace(ecfg or EditConfig(), lookup=lookup))
            r = score_frames(state, gt, oracle=(retexture, spec), traces=traces)
            row = {**info, "row": label, "psnr_object": r["psnr_object"], "perfect": r["psnr_object_oracle"],
                   "vs_perfect": r["psnr_object_vs_oracle"], **kw}
            rows.append(row)
            log(f"  {label:<22} object {row['psnr_object']:.2f}  perfect {row['perfect']:.2f}  "
                f"gap {row['perfect'] - row['psnr_object']:+.2f}  vs perfect {row['vs_perfect']:.2f}")

        base = bake(atlas, fn, source=bake_source)
        score("baked", base)
        score("mask = 1", base, EditConfig(colour="atlas"))
        score("baked at points", bake(atlas, fn, source="points"))
        sigma0 = atlas.bake_sigma
        for s in bake_sigmas:
            atlas.bake_sigma = sigma0 * s
            score(f"kernel x{s:g}", bake(atlas, fn, source="samples"), sigma=s)
        atlas.bake_sigma = sigma0
        for a in antialias:
            score(f"antialias {a}", base, EditConfig(antialias=a), antialias=a)
    return rows


def main(argv=None) -> int:
    from pathlib import Path

    from core.atlas.config import LOOKUPS, AtlasConfig
    from core.edits.bake import SOURCES
    from tools.bench.atlas import scene_model
    from tools.scenes.library import scene_names

    ap = parser(__doc__)
    ap.add_argument("--scene-root", required=True, help="DIR/<scene>/ and DIR/<scene>.pgt (or .default.pgt)")
    ap.add_argument("--scenes", default="cloth", help="scenes (comma-separated)")
    ap.add_argument("--views", type=int, default=4, help="test views scored")
    ap.add_argument("--lookup", default="samples", choices=LOOKUPS, help="how the frames read the "
                    "atlas (EditConfig lookup)")
    ap.add_argument("--bake-source", default="auto", choices=SOURCES,
                    help="the baked row's bake (core.edits.bake.bake source; the kernel rows splat)")
    ap.add_argument("--texel-densities", default=f"{AtlasConfig.texels_per_pixel:g}",
                    help="texels per training pixel to fit (comma-separated; default AtlasConfig's)")
    ap.add_argument("--bake-sigmas", default="0.5,2", help="bake kernel width factors (comma-separated)")
    ap.add_argument("--antialias", default="1,4", help="lookups per pixel side besides the default 2")
    ap.add_argument("--tag", default="", help="read DIR/<scene>.<tag>.default.pgt, the scene-library bench's fit of "
                    "a --fit-args setting (`tools.bench.scenes --tag`), instead of DIR/<scene>.pgt or .default.pgt")
    ap.add_argument("--keep", default="", help="save each fitted model as KEEP/<scene>.tpp<D>.pgt")
    ap.add_argument("--json", default="", help="write the rows to this JSON file")
    args, cfg = parse_with_config(ap, AtlasConfig, argv)
    from tools.machine import machine_info

    root = Path(args.scene_root)
    floats = lambda s: [float(x) for x in s.split(",") if x]  # noqa: E731
    rows = []
    for name in [x for x in args.scenes.split(",") if x]:
        model = scene_model(root, name, args.tag)
        if name not in scene_names() or model is None or not (root / name / "transforms_train.json").exists():
            want = f"{root / name}.{args.tag}.default.pgt" if args.tag else f"{root / name}.pgt"
            print(f"[{name}] skipped: needs {root / name}/ and {want}")
            continue
        rows += gap_rows(model, root / name, cfg, floats(args.texel_densities), args.views, floats(args.bake_sigmas),
                         [int(a) for a in floats(args.antialias)], keep=args.keep or None, lookup=args.lookup,
                         bake_source=args.bake_source)
    machine = machine_info()
    print(f"machine: {machine}")
    write_json(args.json, [dict(r, machine=machine) for r in rows])
    return 0


if __name__ == "__main__":
    sys.exit(main())
