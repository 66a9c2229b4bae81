"""Stage-2 benchmark: fit an atlas to synthetic surface samples (or an .npz with xyz, rgb) and report time,
fitting PSNR against time, distortion statistics with the distortion loss on and off, and utilisation.

    python -m tools.bench.atlas --surface sphere --compare-distortion
    python -m tools.bench.atlas --npz samples.npz --json out.json --png atlas.png
Any AtlasConfig field is a flag (--steps, --batch, --width-map, --charts 8, ...).
"""
from __future__ import annotations

import argparse
import dataclasses
import json
import sys
import time

import numpy as np
import torch

from core.config import add_to_parser, from_args


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


def xatlas_utilisation(atlas, xyz) -> float:
    """Utilisation if the used texels of each chart were packed by xatlas instead of the grid (same texel size)."""
    import xatlas

    from core.atlas.packing import texel_uv  # noqa: F401  (documents the texel convention used below)

    L = atlas.layout
    chart, pix = atlas.atlas_pixel_coords(xyz)
    pix = pix.cpu().numpy()
    ch = chart.cpu().numpy()
    xa = xatlas.Atlas()
    total_used = 0
    for c in range(L.n):
        r0, c0 = L.origin(c)
        p = pix[ch == c]
        cols = np.clip(np.floor(p[:, 0]).astype(int) - c0, 0, L.R - 1)
        rows = np.clip(np.floor(p[:, 1]).astype(int) - r0, 0, L.R - 1)
        used = np.zeros((L.R, L.R), bool)
        used[rows, cols] = True
        rr, cc = np.nonzero(used)
        if len(rr) == 0:
            continue
        total_used += len(rr)
        # two triangles per used texel; shared corners so xatlas sees connected charts
        corner = lambda r, c: r * (L.R + 1) + c  # noqa: E731
        quads = np.stack([corner(rr, cc), corner(rr, cc + 1), corner(rr + 1, cc + 1), corner(rr + 1, cc)], -1)
        tris = np.concatenate([quads[:, [0, 1, 2]], quads[:, [0, 2, 3]]]).astype(np.uint32)
        gr, gc = np.meshgrid(np.arange(L.R + 1), np.arange(L.R + 1), indexing="ij")
        uvs = np.stack([gc.reshape(-1), gr.reshape(-1)], -1).astype(np.float32) / L.R
        xa.add_uv_mesh(uvs, tris)
    pack = xatlas.PackOptions()
    pack.padding = 2 * L.pad
    pack.texels_per_unit = float(L.R)
    xa.generate(pack_options=pack)
    return total_used / float(xa.width * xa.height)


def run_one(xyz, rgb, cfg, label: str, out: dict, png: str | None = None) -> None:
    from core.atlas.fit import fit_atlas, quality_report

    atlas, hist = fit_atlas(xyz, rgb, cfg, quiet=True)
    q = quality_report(atlas, xyz, rgb, hist["area"], cfg.chart_fill)
    q["xatlas_utilisation"] = xatlas_utilisation(atlas, xyz)
    q.update(charts=hist["n"], flatness=hist["flatness"], R=hist["R"], seconds=hist["total_seconds"],
             image_shape=list(atlas.layout.shape))
    q["history"] = [(round(s, 2), st, round(p, 2), ph) for s, st, p, ph in
                    zip(hist["seconds"], hist["steps"], hist["psnr"], hist["phase"])]
    out[label] = q
    print(f"[{label}] charts={hist['n']} (flatness {hist['flatness']:.3f}) R={hist['R']} "
          f"image={atlas.layout.shape[1]}x{atlas.layout.shape[0]} time={hist['total_seconds']:.1f}s "
          f"PSNR={q['psnr']:.2f} dB")
    print(f"[{label}] sigma1/sigma2 median={q['aniso_median']:.3f} p95={q['aniso_p95']:.3f}   "
          f"sigma1*sigma2 median={q['area_median']:.3f} p5={q['area_p5']:.3f} p95={q['area_p95']:.3f}")
    print(f"[{label}] utilisation grid={q['utilisation']:.3f} (chart interiors {q['utilisation_interior']:.3f}) "
          f"xatlas={q['xatlas_utilisation']:.3f}  valid texels={q['texel_valid']:.3f}  "
          f"chart share={[round(s, 2) for s in q['chart_share']]}")
    print(f"[{label}] PSNR vs time: " + "  ".join(f"{s:.0f}s:{p:.1f}" for s, _, p, _ in q["history"][::4]))
    if png:
        from PIL import Image
        img = (atlas.packed_image().cpu().numpy() * 255 + 0.5).astype(np.uint8)
        Image.fromarray(img).save(png)


def main(argv=None) -> int:
    from core.atlas.config import AtlasConfig

    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--surface", default="sphere", choices=("strip", "sphere", "torus"))
    ap.add_argument("--samples", type=int, default=30000, help="synthetic samples")
    ap.add_argument("--sample-seed", type=int, default=0)
    ap.add_argument("--npz", help="samples file with arrays xyz [S, 3], rgb [S, 3]")
    ap.add_argument("--compare-distortion", action="store_true", help="also run with the distortion loss off")
    ap.add_argument("--threads", type=int, default=1, help="torch CPU threads (1 is fastest on a busy 2-core box)")
    ap.add_argument("--json", help="write all figures to this JSON file")
    ap.add_argument("--png", help="save the packed atlas image (first run) as PNG")
    add_to_parser(ap, AtlasConfig)
    args = ap.parse_args(argv)
    torch.set_num_threads(args.threads)
    cfg = from_args(AtlasConfig, args)
    xyz, rgb, source = load_samples(args)
    print(f"samples: {source}; config: steps={cfg.steps} batch={cfg.batch} width_map={cfg.width_map} "
          f"depth_map={cfg.depth_map} charts={cfg.charts} threads={args.threads}")
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
