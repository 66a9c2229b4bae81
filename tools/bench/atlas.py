"""Stage-2 benchmark: fit an atlas to synthetic surface samples (or an .npz with xyz, rgb) and report time,
fitting PSNR against time, distortion statistics with the distortion loss on and off, and utilisation.

    python -m tools.bench.atlas --surface sphere --compare-distortion
    python -m tools.bench.atlas --npz samples.npz --json out.json --png atlas.png
Any AtlasConfig field is a flag (--steps, --batch, --width-map, --charts 8, ...).
"""
from __future__ import annotations

import dataclasses
import json
import sys

import numpy as np
import torch

from tools.bench import parse_with_config, parser


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
    args, cfg = parse_with_config(ap, AtlasConfig, argv)  # AtlasConfig.threads: the fit and everything else
    xyz, rgb, source = load_samples(args)
    print(f"samples: {source}; config: steps={cfg.steps} batch={cfg.batch} width_map={cfg.width_map} "
          f"depth_map={cfg.depth_map} charts={cfg.charts} threads={cfg.threads}")
    out: dict = {"source": source, "config": dataclasses.asdict(cfg)}
    run_one(xyz, rgb, cfg, "distortion on" if cfg.distortion else "distortion off", out, args.png)
    if args.compare_distortion and cfg.distortion:
        run_one(xyz, rgb, dataclasses.replace(cfg, distortion=False), "distortion off", out)
    if args.json:
        from core.util.atomic import atomic_write_text
        atomic_write_text(args.json, json.dumps(out, indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())
