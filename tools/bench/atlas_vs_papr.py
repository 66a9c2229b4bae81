"""Stage-2 quality on real views: render the test views of a model with the PAPR colours and with every ray coloured
from the atlas (lookup at the ray's surface point x_i), and print PSNR against the ground truth, full frame and on
the object's pixels.

    python -m tools.bench.atlas_vs_papr --model m.pgt --data DIR
    python -m tools.bench.atlas_vs_papr --model m.pgt --data D --fit render --steps 1500 ...

--fit image|render extracts surface samples from the model's training views (colour = ground-truth pixel or the
model's rendered object colour, core/atlas/samples.py), fits a fresh atlas (any AtlasConfig flag) in memory and adds
its row, without touching the model file; --fit-npz does the same from saved samples (arrays xyz, rgb).
--knn-npz adds a bound: each ray coloured by the mean colour of its k nearest surface samples (the best a function
of x alone does on these samples, no atlas involved).
"""
from __future__ import annotations

import dataclasses
import sys
import time

import numpy as np
import torch

from tools.bench import parse_with_config, parser, write_json


def load_npz(path: str) -> tuple[torch.Tensor, torch.Tensor]:
    """xyz [S, 3], rgb [S, 3] from an .npz (no pickle)."""
    from core.util.errors import InputError

    try:
        with np.load(path, allow_pickle=False) as z:
            xyz, rgb = np.asarray(z["xyz"], np.float32), np.asarray(z["rgb"], np.float32)
        return torch.from_numpy(xyz), torch.from_numpy(rgb)
    except KeyError as e:
        raise InputError(f"{path}: needs arrays 'xyz' [S, 3] and 'rgb' [S, 3] ({e} missing)") from e
    except (OSError, ValueError) as e:
        raise InputError(f"{path}: not a readable .npz file ({e})") from e


def atlas_coloured(bundle, atlas, antialias: int | None = None, image=None):
    """The edit state of an atlas-coloured frame (core/frames/edited.py, colour='atlas'): every object ray coloured
    from `atlas` (its packed image, or `image` [H, W, 3] in its layout), or from render_edited's
    texture_fn(x [M, 3]) -> [M, 3] at its surface point, with the frame's own coverage. antialias: lookups per
    pixel side (None = EditConfig's default)."""
    from core.frames.edited import EditConfig, EditState

    cfg = EditConfig(colour="atlas") if antialias is None else EditConfig(colour="atlas", antialias=antialias)
    return EditState(dataclasses.replace(bundle, atlas=atlas), atlas=image, cfg=cfg)


def knn_colour(xyz: torch.Tensor, rgb: torch.Tensor, k: int):
    """colour_fn(x [M, 3]) -> [M, 3]: mean colour of the k nearest samples xyz [S, 3] / rgb [S, 3]."""
    from scipy.spatial import cKDTree

    tree, cols = cKDTree(xyz.numpy()), rgb.numpy()

    def fn(x: torch.Tensor) -> torch.Tensor:
        _, i = tree.query(x.cpu().numpy(), k=k)
        return torch.from_numpy(cols[i.reshape(len(x), k)].mean(1)).float()
    return fn


def with_kernel_texture(atlas, xyz: torch.Tensor, rgb: torch.Tensor, sigma: float):
    """A copy of `atlas` whose textures are the kernel regression of samples xyz [S, 3] / rgb [S, 3] at `sigma`
    (as fit_atlas makes them with texture_mode='kernel')."""
    import copy

    from core.atlas.texture import filled_kernel_texture

    out = copy.deepcopy(atlas)
    probs, uv = out.chart_uv(xyz)
    with torch.no_grad():
        tex, _, _ = filled_kernel_texture(probs, uv, rgb.clamp(0, 1), out.layout.R, sigma, labels=out.blur_labels)
        out.set_textures(tex)
    return out


def model_samples(bundle, split, colour: str, seed: int = 0):
    """Surface samples xyz [S, 3], rgb [S, 3] of a stage-1 model over all views of `split`, exactly as stage 2
    extracts them (core/pipeline.py); colour='render' (the model's own colours) needs a model without a decoder."""
    from core.pipeline import surface_samples
    from core.util.errors import InputError

    if colour == "render" and bundle.model.decoder is not None:
        raise InputError("--fit render: per-ray colours need a model without an image decoder")
    return surface_samples(bundle.model, split, seed=seed, colour=colour)


def main(argv=None) -> int:
    from core.atlas.config import AtlasConfig

    ap = parser(__doc__)
    ap.add_argument("--model", required=True, help="model file (.pgt) with an atlas (never modified)")
    ap.add_argument("--data", required=True, help="its dataset (NeRF-synthetic layout)")
    ap.add_argument("--split", default="test")
    ap.add_argument("--every", type=int, default=2, help="use every n-th view of the split")
    ap.add_argument("--fit", choices=("image", "render"), help="also fit an atlas from samples of the model's "
                    "training views coloured by the image or by the model's render (AtlasConfig flags apply)")
    ap.add_argument("--fit-npz", help="also fit an atlas from these surface samples (AtlasConfig flags apply)")
    ap.add_argument("--texture-sigmas", help="comma-separated kernel widths: extra rows with the fitted maps and the "
                    "kernel texture at each width (--texture-sigma units)")
    ap.add_argument("--save-samples", help="write the --fit samples to this .npz (xyz, rgb)")
    ap.add_argument("--knn-npz", help="also colour rays by the k nearest of these surface samples (a bound)")
    ap.add_argument("--knn", type=int, default=16)
    ap.add_argument("--json", help="write the figures to this JSON file")
    ap.add_argument("--png", help="write [PAPR | atlas | (fitted) | ground truth] of the last view here")
    ap.add_argument("--atlas-png", help="write the packed atlas image of the last atlas row here")
    args, cfg = parse_with_config(ap, AtlasConfig, argv)  # AtlasConfig.threads: the fit and everything else

    from core.bundle import load_bundle
    from core.frames.edited import render_edited
    from core.images.metrics import object_mask, psnr
    from core.points.render import shade_frame
    from core.images.dataset import load_split

    bundle = load_bundle(args.model, "cpu")
    split = load_split(args.data, args.split)
    rows: dict[str, object] = {}
    if bundle.atlas is not None:
        rows["atlas (model file)"] = bundle.atlas
    fit_info = {}
    if args.fit or args.fit_npz:
        from core.atlas.fit import fit_atlas

        if args.fit:
            t = time.perf_counter()
            xyz, rgb = model_samples(bundle, load_split(args.data, "train"), args.fit, seed=cfg.seed)
            fit_info["sample_seconds"] = time.perf_counter() - t
            print(f"{len(xyz)} surface samples coloured by the {args.fit} in {fit_info['sample_seconds']:.0f} s")
            if args.save_samples:
                import io

                from core.util.atomic import atomic_write_bytes
                buf = io.BytesIO()
                np.savez(buf, xyz=xyz.numpy(), rgb=rgb.numpy())
                atomic_write_bytes(args.save_samples, buf.getvalue())
        else:
            xyz, rgb = load_npz(args.fit_npz)
        atlas, hist = fit_atlas(xyz, rgb, cfg, quiet=True)
        fit_info |= {"seconds": hist["total_seconds"], "samples": len(xyz), "fit_psnr": hist["psnr"][-1],
                     "charts": hist["n"], "config": dataclasses.asdict(cfg)}
        print(f"fitted atlas from {args.fit_npz or args.fit + ' samples'}: {hist['n']} charts, "
              f"{hist['total_seconds']:.1f} s, "
              f"fitting PSNR {hist['psnr'][-1]:.2f} dB")
        rows["atlas (fitted)"] = atlas
        for sig in [float(v) for v in (args.texture_sigmas or "").split(",") if v.strip()]:
            rows[f"atlas (fitted), texture sigma {sig:g}"] = with_kernel_texture(atlas, xyz, rgb, sig)
    if not rows:
        print(f"{args.model} has no atlas and no --fit-npz was given", file=sys.stderr)
        return 2
    knn_fn = knn_colour(*load_npz(args.knn_npz), args.knn) if args.knn_npz else None

    # Every row renders through the production path (render_edited); the first row's trace serves the others.
    states = {name: atlas_coloured(bundle, atl) for name, atl in rows.items()}
    first = next(iter(rows))
    scores: dict[str, list] = {}
    t0 = time.perf_counter()
    views = list(range(0, len(split), args.every))
    for i in views:
        cam = (split.c2w[i], split.height, split.width, split.focal)
        out = render_edited(states[first], *cam)
        tr = out["trace"]
        papr = torch.nan_to_num(shade_frame(bundle.model, tr), nan=1.0).clamp(0, 1)
        frames = {"PAPR": papr}
        for name, st in states.items():
            frames[name] = out["rgb"] if name == first else render_edited(st, *cam, trace=tr)["rgb"]
        if knn_fn is not None:
            frames[f"k-NN colour field (k={args.knn})"] = render_edited(states[first], *cam, trace=tr,
                                                                         texture_fn=knn_fn)["rgb"]
        gt, m = split.images[i], object_mask(split.alphas[i], out["alpha"])
        for name, img in frames.items():
            scores.setdefault(name, []).append((psnr(img, gt), psnr(img, gt, m)))
    secs = time.perf_counter() - t0

    print(f"{args.model} on {args.data} ({args.split}, {len(views)} views, {secs:.0f} s)")
    print(f"{'colour':34s} {'full (dB)':>10s} {'object (dB)':>12s}")
    table = {}
    for name, s in scores.items():
        a = np.asarray(s)
        table[name] = {"full": float(a[:, 0].mean()), "object": float(np.nanmean(a[:, 1]))}
        print(f"{name:34s} {table[name]['full']:10.2f} {table[name]['object']:12.2f}")
    write_json(args.json, {"table": table, "fit": fit_info, "views": views})
    if args.png:
        from core.images.png import write_png
        write_png(args.png, torch.cat(list(frames.values()) + [split.images[views[-1]]], 1).numpy())
    if args.atlas_png:
        from core.images.png import write_png
        write_png(args.atlas_png, rows[list(rows)[-1]].packed_image().numpy())
    return 0


if __name__ == "__main__":
    sys.exit(main())
