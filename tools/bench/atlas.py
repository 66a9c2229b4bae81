"""Stage-2 benchmark: fit an atlas to synthetic surface samples (or an .npz with xyz, rgb) and report time,
fitting PSNR against time, distortion statistics with the distortion loss on and off, and utilisation.

    python -m tools.bench.atlas --surface sphere --compare-distortion
    python -m tools.bench.atlas --npz samples.npz --json out.json --png atlas.png
    python -m tools.bench.atlas --scene-root DIR --layouts islands,grid   (needs bpy for the ground truth)
Any AtlasConfig field is a flag (--steps, --batch, --width-map, --charts 8, ...).

--scene-root DIR: for every scene of `pointgt make-scene --list` that DIR holds (DIR/<name>/ from make-scene and
DIR/<name>.pgt, a stage-1 model of it, or DIR/<name>.default.pgt, the scene-library bench's default fit; with --tag T
its fit of a --fit-args setting, DIR/<name>.T.default.pgt), fit stage 2 in memory with each layout and report the
atlas's utilisation (texels with a surface point / image pixels), the texel -> surface -> texel round trip (share
within 1 texel), stage-2 seconds, the atlas-coloured render and, at rest, the retexture (with its perfect-atlas
reference: the texture evaluated exactly at the surface points) and the decal, object PSNR on the scene's test views
(--no-scores: the layout figures only, no renders; --work DIR keeps the ground truth out of the scene folders).
--island-sides splits every chart by side
(core/atlas/sides.py; side_reversed: the samples' share on a reversed sub-chart); --island-pieces cuts charts where
their maps overlap (core/atlas/pieces.py; layout_charts, pieces_seconds); --folds adds the maps' fold report.
--footprint-variants "1;25;0.25,1,4,16,64" fits the maps once per scene and layout, then refits the texture through
the pixel filter once per variant (a single λ, or candidates that footprint_lambdas chooses among from held-out
training views; "charts:1,4,16,64" refits through the chart lookups instead of --footprint-lookup's) and adds a row
per variant (scored with the first --lookups entry, a charts refit with chart lookups and the splat bake).
--lookups "charts:samples,samples:fit:2" scores the same fitted atlas once per lookup:bake[:k] (EditConfig lookup
and lookup_k, the bake's source; the first one is the row's own, each further one adds a row).
"""
from __future__ import annotations

import dataclasses
import sys

import numpy as np
import torch

from tools.bench import parse_with_config, parser, write_json


def load_samples(args) -> tuple[torch.Tensor, torch.Tensor, str]:
    from core.atlas.synthetic import synthetic_samples
    from core.util.errors import InputError

    if args.npz:
        try:
            with np.load(args.npz, allow_pickle=False) as z:
                xyz, rgb = z["xyz"], z["rgb"]
        except KeyError as e:
            raise InputError(f"{args.npz}: needs arrays 'xyz' [S, 3] and 'rgb' [S, 3] ({e} missing)") from e
        except (OSError, ValueError) as e:
            raise InputError(f"{args.npz}: not a readable .npz file ({e})") from e
        return torch.from_numpy(np.asarray(xyz, np.float32)), torch.from_numpy(np.asarray(rgb, np.float32)), args.npz
    xyz, rgb = synthetic_samples(args.surface, args.samples, seed=args.sample_seed)
    return xyz, rgb, f"synthetic {args.surface} ({args.samples} samples)"


def xatlas_utilisation(atlas) -> tuple[float, float]:
    """(grid, xatlas) coverage: valid texels (texel map not NaN) over all pixels of the grid-packed image, and
    the same texels packed by xatlas (same texel size, same padding) over the xatlas image."""
    import xatlas

    L = atlas.layout
    valid = torch.isfinite(atlas.texel_points()).all(-1).cpu().numpy()
    xa = xatlas.Atlas()
    total = 0
    for c in range(L.n):
        r0, c0 = L.origin(c)
        rr, cc = np.nonzero(valid[r0:r0 + L.R, c0:c0 + L.R])
        if len(rr) == 0:
            continue
        total += len(rr)
        corner = lambda r, k: r * (L.R + 1) + k  # noqa: E731  two triangles per valid texel, shared corners
        quads = np.stack([corner(rr, cc), corner(rr, cc + 1), corner(rr + 1, cc + 1), corner(rr + 1, cc)], -1)
        tris = np.concatenate([quads[:, [0, 1, 2]], quads[:, [0, 2, 3]]]).astype(np.uint32)
        gr, gc = np.meshgrid(np.arange(L.R + 1), np.arange(L.R + 1), indexing="ij")
        uvs = np.stack([gc.reshape(-1), gr.reshape(-1)], -1).astype(np.float32) / L.R
        xa.add_uv_mesh(uvs, tris)
    if total == 0:
        return 0.0, 0.0
    pack = xatlas.PackOptions()
    pack.padding = 2 * L.pad
    pack.texels_per_unit = float(L.R)
    xa.generate(pack_options=pack)
    return total / float(L.shape[0] * L.shape[1]), total / float(xa.width * xa.height)


def run_one(xyz, rgb, cfg, label: str, out: dict, png: str | None = None) -> None:
    from core.atlas.fit import fit_atlas, quality_report

    atlas, hist = fit_atlas(xyz, rgb, cfg, quiet=True)
    q = quality_report(atlas, xyz, rgb, hist["area"], cfg.chart_fill)
    q["grid_coverage"], q["xatlas_coverage"] = xatlas_utilisation(atlas)
    q.update(charts=hist["n"], flatness=hist["flatness"], R=hist["R"], seconds=hist["total_seconds"],
             image_shape=list(atlas.layout.shape), area=hist["area"], spacing=hist["spacing"])
    q["history"] = [(round(s, 2), st, round(p, 2), ph) for s, st, p, ph in
                    zip(hist["seconds"], hist["steps"], hist["psnr"], hist["phase"])]
    out[label] = q
    print(f"[{label}] charts={hist['n']} (flatness {hist['flatness']:.3f}) R={hist['R']} "
          f"image={atlas.layout.shape[1]}x{atlas.layout.shape[0]} time={hist['total_seconds']:.1f}s "
          f"PSNR={q['psnr']:.2f} dB area={hist['area']:.3f} spacing={hist['spacing']:.4g}")
    print(f"[{label}] sigma1/sigma2 median={q['aniso_median']:.3f} p95={q['aniso_p95']:.3f}   "
          f"sigma1*sigma2 median={q['area_median']:.3f} p5={q['area_p5']:.3f} p95={q['area_p95']:.3f}")
    print(f"[{label}] utilisation grid={q['utilisation']:.3f} (chart interiors {q['utilisation_interior']:.3f}) "
          f"valid texels={q['texel_valid']:.3f}\n[{label}] valid-texel coverage grid={q['grid_coverage']:.3f} "
          f"xatlas={q['xatlas_coverage']:.3f}  "
          f"chart share={[round(s, 2) for s in q['chart_share']]}")
    print(f"[{label}] PSNR vs time: " + "  ".join(f"{s:.0f}s:{p:.1f}" for s, _, p, _ in q["history"][::4]))
    if png:
        from PIL import Image
        img = (atlas.packed_image().cpu().numpy() * 255 + 0.5).astype(np.uint8)
        Image.fromarray(img).save(png)


def round_trip(atlas) -> float:
    """Share of the texels with a surface point whose point maps back (its chart, t_c, placement) within 1 texel."""
    tp = atlas.texel_points()
    ok = torch.isfinite(tp).all(-1)
    if not bool(ok.any()):
        return float("nan")
    _, pix = atlas.atlas_pixel_coords(tp[ok])
    rows, cols = torch.nonzero(ok, as_tuple=True)
    miss = (pix - torch.stack([cols + 0.5, rows + 0.5], -1)).norm(dim=-1)
    return float((miss <= 1.0).float().mean())


def scene_model(root, name: str, tag: str = ""):
    """DIR/<name>.pgt, else the scene-library bench's DIR/<name>.default.pgt (None when neither exists); with a tag
    the library bench's fit of that setting only, DIR/<name>.<tag>.default.pgt (`tools.bench.scenes --tag`)."""
    from pathlib import Path

    from tools.bench.scenes import model_path

    root = Path(root)
    candidates = [model_path(root, name, None, tag)] if tag else [root / f"{name}.pgt", root / f"{name}.default.pgt"]
    for model in candidates:
        if model.exists():
            return model
    return None


def scene_mirror(scene, work):
    """A folder work/<scene's name> that stands for the scene where ground truth is written (its test views'
    subset, the Cycles renders of its variants): links to the scene's scene.blend, scene.json and transforms files,
    so a read-only scene library stays untouched. Returns its path."""
    from pathlib import Path

    scene, mirror = Path(scene), Path(work) / Path(scene).name
    mirror.mkdir(parents=True, exist_ok=True)
    for name in ("scene.blend", "scene.json", "transforms_train.json", "transforms_test.json"):
        link, target = mirror / name, (scene / name).resolve()
        if target.exists() and not link.exists():
            link.symlink_to(target)
    return mirror


def parse_lookups(text: str) -> list[tuple[str, str, int]]:
    """"lookup:bake[:k],..." -> [(lookup, bake source, k)]; "" -> the defaults alone."""
    from core.edits.bake import SOURCES
    from core.atlas.config import LOOKUPS
    from core.frames.edited import EditConfig
    from core.util.errors import InputError

    out = []
    for item in [x.strip() for x in text.split(",") if x.strip()] or ["samples:auto"]:
        parts = item.split(":")
        k = EditConfig().lookup_k if len(parts) < 3 else int(parts[2]) if parts[2].isdigit() else 0
        if len(parts) not in (2, 3) or parts[0] not in LOOKUPS or parts[1] not in SOURCES or not 1 <= k <= 64:
            raise InputError(f"--lookups: expected lookup:bake[:k] with lookup in {LOOKUPS}, bake in {SOURCES}, "
                             f"k in 1-64, got {item!r}")
        out.append((parts[0], parts[1], k))
    return out


def lookup_scores(bundle, spec, retexture: str, gts: dict, test, lookup: tuple[str, str, int]) -> dict:
    """Atlas-coloured, retexture (with its perfect-atlas reference) and decal object PSNR with one lookup:bake:k."""
    from core.frames.edited import EditConfig, EditState
    from tools.eval_edits import edited_atlases, score_frames

    kind, source, k = lookup
    ecfg = EditConfig(lookup=kind, lookup_k=k)
    edits = edited_atlases(bundle, spec, retexture, source=source)
    r = score_frames(EditState(bundle, atlas=edits["retexture"], cfg=ecfg), gts["retexture"], oracle=(retexture, spec))
    return {"atlas_colour": score_frames(EditState(bundle, cfg=dataclasses.replace(ecfg, colour="atlas")),
                                         test)["psnr_object"],
            "retexture": r["psnr_object"], "retexture_perfect": r["psnr_object_oracle"],
            "decal": score_frames(EditState(bundle, atlas=edits["decal"], cfg=ecfg), gts["decal"])["psnr_object"]}


def scene_rows(root, layouts, cfg, views: int, retexture: str = "stripes", only=None, log=print,
               scores: bool = True, folds: bool = False, work=None,
               footprint_variants: list[str] | None = None, tag: str = "",
               lookups: list[tuple[str, str, int]] | None = None) -> list[dict]:
    """The per-scene figures (module doc) for every scene of the library found under root (or those in only);
    scores False: the layout figures only (utilisation, round trip, islands, seconds), no renders; folds: also
    `core.atlas.fit.fold_report` on the atlas's stored samples (reversed, crease). work: a folder for the ground
    truth (`scene_mirror`); None writes it into the scene folders. footprint_variants: after the row of cfg's own
    refit, one row per variant (footprint_lambdas strings), the texture refitted from the same kernel texture.
    lookups: (lookup, bake source, k) to score (`parse_lookups`): the first in the row, each further one in a row
    of its own (None: the defaults)."""
    import time
    from pathlib import Path

    from core.bundle import load_bundle
    from core.images.dataset import load_split
    from core.pipeline import fit_atlas_stage, footprint_views
    from tools.eval_edits import ground_truth, view_subset_dir
    from tools.scenes.library import scene_names
    from tools.scenes.spec import load_scene_spec

    root, rows = Path(root), []
    for name in scene_names():
        if only and name not in only:
            continue
        scene, model = root / name, scene_model(root, name, tag)
        if not (scene / "transforms_train.json").exists() or model is None:
            want = f"{root / name}.{tag}.default.pgt (tools.bench.scenes --tag)" if tag else \
                f"{root / name}.pgt (pointgt fit)"
            log(f"[{name}] skipped: needs {scene}/ (pointgt make-scene) and {want}")
            continue
        train = load_split(scene, "train")
        if scores:
            spec = load_scene_spec(scene)
            gt_dir = view_subset_dir(scene if work is None else scene_mirror(scene, work), views)
            gts = {e: ground_truth(gt_dir, "rest", 0.0, t, None, log) for e, t in (("retexture", retexture),
                                                                                   ("decal", "decal"))}
            test = ground_truth(gt_dir, "rest", 0.0, None, None, log)
        for layout in layouts:
            bundle = load_bundle(model, "cpu")
            t0 = time.perf_counter()
            if footprint_variants:  # the kernel texture kept for the variants' refits
                hist = fit_atlas_stage(bundle, train, dataclasses.replace(cfg, layout=layout, footprint=False),
                                       show_progress=False)
                kernel_texture = bundle.atlas.textures.detach().clone()
                fp_views = footprint_views(bundle.model, train)  # traced once, refitted through per variant
                hist["footprint"] = (footprint_variant(bundle, fp_views, cfg, cfg.footprint_lambdas, kernel_texture)
                                     if cfg.footprint else {})
            else:
                hist = fit_atlas_stage(bundle, train, dataclasses.replace(cfg, layout=layout), show_progress=False)
            seconds = time.perf_counter() - t0
            atlas = bundle.atlas
            H, W = atlas.layout.shape
            row = {"scene": name, "layout": layout, "size": f"{W}x{H}", "seconds": seconds,
                   "utilisation": float(torch.isfinite(atlas.texel_points()).all(-1).float().mean()),
                   "round_trip": round_trip(atlas),
                   "round_trip_all": hist.get("texel_stats", {}).get("round_trip_1", float("nan")),
                   "islands": hist.get("islands", 0), "layout_seconds": hist.get("island_seconds", float("nan")),
                   "island_share": float(atlas.layout.island_pixels.float().mean()) if atlas.islands else float("nan"),
                   "footprint_seconds": hist.get("footprint", {}).get("seconds", float("nan")),
                   "footprint_lambda": hist.get("footprint", {}).get("lambda", float("nan"))}
            if hist.get("footprint", {}).get("holdout_psnr"):  # footprint_lambdas: each candidate's held-out PSNR
                row["footprint_holdout_psnr"] = hist["footprint"]["holdout_psnr"]
            if "sides" in hist:  # charts split by side: share of the samples on a reversed sub-chart
                row["side_reversed"] = hist["sides"]["reversed"]
            if "pieces" in hist:  # charts cut where their maps overlap: layout charts, seconds of the cut
                row["layout_charts"], row["pieces_seconds"] = hist["pieces"]["charts"], hist["pieces"]["seconds"]
            if folds and atlas.bake_samples is not None:
                from core.atlas.fit import fold_report

                rep = fold_report(atlas, atlas.bake_samples)
                row["reversed"], row["crease"] = rep["reversed"], rep["crease"]
            looks = lookups or parse_lookups("")
            if scores:
                row["lookup"] = ":".join(map(str, looks[0]))
                row.update(lookup_scores(bundle, spec, retexture, gts, test, looks[0]))
            rows.append(row)
            log(f"[{name}/{layout}] " + "  ".join(f"{k}={v:.3f}" if isinstance(v, float) else f"{k}={v}"
                                                  for k, v in row.items() if k not in ("scene", "layout")))
            for look in looks[1:] if scores else []:
                lrow = {**{k: row[k] for k in ("scene", "layout", "size", "utilisation")},
                        "lookup": ":".join(map(str, look)), **lookup_scores(bundle, spec, retexture, gts, test, look)}
                rows.append(lrow)
                log(f"[{name}/{layout} lookup {lrow['lookup']}] " + "  ".join(
                    f"{k}={v:.3f}" for k, v in lrow.items() if isinstance(v, float)))
            for variant in footprint_variants or []:
                info = footprint_variant(bundle, fp_views, cfg, variant, kernel_texture)
                vrow = {**{k: row[k] for k in ("scene", "layout", "size", "utilisation")},
                        "footprint_variant": variant, "footprint_lambda": info.get("lambda", float("nan")),
                        "footprint_seconds": info["seconds"]}
                if info.get("holdout_psnr"):
                    vrow["footprint_holdout_psnr"] = info["holdout_psnr"]
                if scores:  # read as the refit read: a refit through the charts with chart lookups and the splat
                    look = looks[0] if info["lookup"] == "samples" else ("charts", "samples", looks[0][2])
                    vrow["lookup"] = ":".join(map(str, look))
                    vrow.update(lookup_scores(bundle, spec, retexture, gts, test, look))
                rows.append(vrow)
                log(f"[{name}/{layout} footprint {variant}] " + "  ".join(
                    f"{k}={v:.3f}" if isinstance(v, float) else f"{k}={v}" for k, v in vrow.items()
                    if k not in ("scene", "layout", "footprint_variant")))
    return rows


def split_variant(variant: str, cfg) -> tuple[str, str]:
    """A --footprint-variants entry "[LOOKUP:]LAMBDAS" -> (lookup, lambdas); no prefix: cfg.footprint_lookup."""
    from core.atlas.config import LOOKUPS
    from core.util.errors import InputError

    lookup, _, lambdas = variant.rpartition(":")
    lookup = lookup or cfg.footprint_lookup
    if lookup not in LOOKUPS:
        raise InputError(f"--footprint-variants: the lookup before ':' must be samples or charts, got {variant!r}")
    dataclasses.replace(cfg, footprint_lambdas=lambdas).lambda_candidates()  # a bad list fails here
    return lookup, lambdas


def footprint_variant(bundle, views, cfg, variant: str, kernel_texture: torch.Tensor) -> dict:
    """Put the kernel texture back into bundle.atlas and refit it through the pixel filter on `views`
    (`core.pipeline.footprint_views`) with the variant's lambdas (one λ, or candidates chosen from held-out views;
    empty: cfg.footprint_lambda) and lookup (`split_variant`). Returns the refit's info with seconds (the views'
    tracing not included)."""
    import time

    from core.atlas.footprint import refit_texture_footprint

    lookup, lambdas = split_variant(variant, cfg)
    with torch.no_grad():
        bundle.atlas.textures.copy_(kernel_texture)
    cands = dataclasses.replace(cfg, footprint_lambdas=lambdas).lambda_candidates()
    t0 = time.perf_counter()
    info = refit_texture_footprint(bundle.atlas, views, lam=cfg.footprint_lambda, iters=cfg.footprint_iters,
                                   lambdas=cands, lookup=lookup)
    return {**info, "lookup": lookup, "seconds": round(time.perf_counter() - t0, 2)}


def markdown_rows(rows: list[dict]) -> str:
    """The docs' per-scene table: one row per scene and layout (islands: the packed islands; – for the grid),
    with the retexture's gap to the perfect atlas (reference − retexture, dB) in brackets."""
    head = ("| scene | layout | atlas | islands | utilisation | round trip ≤ 1 texel | stage 2 (s) | atlas-coloured | "
            "retexture / perfect atlas (gap) | decal |")
    out = [head, "|" + "---|" * 10]
    for r in rows:
        if "footprint_variant" in r:  # --footprint-variants rows: in the JSON and the log only
            continue
        if "seconds" not in r:  # a further --lookups row: the scores of another lookup of the row above
            gap = r["retexture_perfect"] - r["retexture"]
            out.append(f"| {r['scene']} | lookup {r['lookup']} | | | | | | {r['atlas_colour']:.2f} | "
                       f"{r['retexture']:.2f} / {r['retexture_perfect']:.2f} ({gap:.2f}) | {r['decal']:.2f} |")
            continue
        scored = "atlas_colour" in r
        gap = r["retexture_perfect"] - r["retexture"] if scored else 0.0
        out.append(f"| {r['scene']} | {r['layout']} | {r['size']} | {r.get('islands') or '–'} | "
                   f"{100 * r['utilisation']:.1f} % | {100 * r['round_trip']:.1f} % | {r['seconds']:.0f} | "
                   + (f"{r['atlas_colour']:.2f} | {r['retexture']:.2f} / {r['retexture_perfect']:.2f} ({gap:.2f}) | "
                      f"{r['decal']:.2f} |" if scored else "– | – | – |"))
    return "\n".join(out)


def main(argv=None) -> int:
    from core.atlas.config import AtlasConfig

    ap = parser(__doc__)
    ap.add_argument("--surface", default="sphere", choices=("strip", "sphere", "torus"))
    ap.add_argument("--samples", type=int, default=30000, help="synthetic samples")
    ap.add_argument("--sample-seed", type=int, default=0)
    ap.add_argument("--npz", help="samples file with arrays xyz [S, 3], rgb [S, 3]")
    ap.add_argument("--compare-distortion", action="store_true", help="also run with the distortion loss off")
    ap.add_argument("--json", help="write all figures to this JSON file")
    ap.add_argument("--png", help="save the packed atlas image (first run) as PNG")
    ap.add_argument("--scene-root", help="per-scene mode: DIR/<scene>/ and DIR/<scene>.pgt for the library scenes")
    ap.add_argument("--tag", default="", help="per-scene mode: read the scene-library bench's fits of a --fit-args "
                    "setting, DIR/<scene>.<tag>.default.pgt (`tools.bench.scenes --tag`), instead of DIR/<scene>.pgt "
                    "or DIR/<scene>.default.pgt")
    ap.add_argument("--layouts", default="islands,grid", help="per-scene mode: layouts to compare")
    ap.add_argument("--views", type=int, default=4, help="per-scene mode: test views scored")
    ap.add_argument("--scenes", default="", help="per-scene mode: only these scenes (comma-separated)")
    ap.add_argument("--work", help="per-scene mode: folder for the ground truth the scores need (test-view subsets, "
                    "Cycles renders); default: inside each scene folder")
    ap.add_argument("--no-scores", action="store_true", help="per-scene mode: layout figures only, no renders")
    ap.add_argument("--footprint-variants", default="", help="per-scene mode: ';'-separated footprint refits to "
                    "compare on the same maps (each a λ or comma-separated candidates; module doc)")
    ap.add_argument("--lookups", default="", help="per-scene mode: lookup:bake[:k] pairs to score on the same "
                    "atlas (comma-separated; e.g. charts:samples,samples:fit:4; default: the defaults)")
    ap.add_argument("--folds", action="store_true", help="per-scene mode: also the share of samples whose chart map "
                    "is reversed on the surface (core.atlas.fit.fold_report)")
    args, cfg = parse_with_config(ap, AtlasConfig, argv)  # AtlasConfig.threads: the fit and everything else
    if args.scene_root:
        from tools.machine import machine_info

        machine = machine_info()
        variants = [v.strip() for v in args.footprint_variants.split(";") if v.strip()]
        for v in variants:  # a bad list fails before any fit
            split_variant(v, cfg)
        lookups = parse_lookups(args.lookups)  # a bad list fails before any fit
        rows = scene_rows(args.scene_root, [x for x in args.layouts.split(",") if x], cfg, args.views,
                          only=[x for x in args.scenes.split(",") if x], scores=not args.no_scores,
                          folds=args.folds, work=args.work, footprint_variants=variants, tag=args.tag,
                          lookups=lookups)
        print(markdown_rows(rows))
        print(f"machine: {machine}")
        rows = [dict(r, machine=machine) for r in rows]
        write_json(args.json, rows)
        return 0
    xyz, rgb, source = load_samples(args)
    print(f"samples: {source}; config: steps={cfg.steps} batch={cfg.batch} width_map={cfg.width_map} "
          f"depth_map={cfg.depth_map} charts={cfg.charts} threads={cfg.threads}")
    out: dict = {"source": source, "config": dataclasses.asdict(cfg)}
    run_one(xyz, rgb, cfg, "distortion on" if cfg.distortion else "distortion off", out, args.png)
    if args.compare_distortion and cfg.distortion:
        run_one(xyz, rgb, dataclasses.replace(cfg, distortion=False), "distortion off", out)
    write_json(args.json, out)
    return 0


if __name__ == "__main__":
    sys.exit(main())
