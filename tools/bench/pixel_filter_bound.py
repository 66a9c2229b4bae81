"""How much of a test frame can texture lookups reproduce, with one lookup per pixel or pixel-filtered (needs bpy)?

    python -m tools.bench.pixel_filter_bound --scene DIR [--model M.pgt] [--every 2] [--sub 4] [--json OUT]

DIR is a scene made by `pointgt make-scene`: its `scene.blend` holds the true mesh and `scene.json` names the
procedural base texture the ground truth was rendered with, so the *true* colour of every surface point is known.
Each test view's object pixels are coloured from that true texture, composited with the image's own alpha (no model
colour and no model coverage anywhere), in these ways:

- true hit at the pixel centre: one ray per pixel cast against the mesh, the texture at its hit — what one lookup
  per pixel can reach with perfect geometry and a perfect texture;
- true hits, Blackman-Harris filter over a support of w pixels, display space or linear light: `--sub` x `--sub`
  rays per pixel, hits filtered like `core/images/filter.py` does (which supports match Cycles' default width
  setting of 1.5 is what these rows measure);
- with --model (a model with an atlas): the model's surface points x_i (on their rays) instead of the true hits, at
  the pixel centre and filtered (3-pixel support) in linear light from 2 x 2 interpolated sub-pixel points —
  rendered by core/frames/edited.py (render_edited with the texture as its texture_fn, the coverage divided out),
  so exactly as an edited frame is — what the model's geometry allows with a perfect texture;
- with --model and an atlas: the true texture *baked into the atlas* (core/edits/bake.py; `--bake-from`: splatted
  from the stored surface samples and/or evaluated at each texel's map point) and looked up at x_i, one lookup or
  filtered — what baking loses. `--texel-maps splat,inverse` recomputes the
  map in memory with each rule first (the model file is not written).

Object PSNR over ground-truth alpha > 0.5 ∪ the rows' own coverage, as elsewhere.
"""
from __future__ import annotations

import json
import sys
import time
from pathlib import Path

import numpy as np
import torch

from tools.bench import add_scene, parse, parser, write_json
from tools.machine import machine_line


def _subpixel_grid(height: int, width: int, sub: int) -> torch.Tensor:
    """Sub-pixel centres [sub*H*sub*W, 2] (col, row), row-major over the fine grid."""
    r = (torch.arange(sub * height, dtype=torch.float64) + 0.5) / sub
    c = (torch.arange(sub * width, dtype=torch.float64) + 0.5) / sub
    rr, cc = torch.meshgrid(r, c, indexing="ij")
    return torch.stack([cc.reshape(-1), rr.reshape(-1)], -1)


def main(argv=None) -> int:
    ap = parser(__doc__)
    add_scene(ap, "use every n-th test view")
    ap.add_argument("--model", default=None, help="model file (.pgt): adds the rows with its surface points")
    ap.add_argument("--sub", type=int, default=4, help="rays per pixel side for the filtered true-hit rows")
    ap.add_argument("--supports", default="1.5,3", help="filter supports (pixels) to compare; support * sub - sub "
                    "must be even")
    ap.add_argument("--bake-from", default="samples,points",
                    help="comma-separated bake sources: samples (fn splatted from the stored surface samples, the "
                         "default of core/edits/bake.py) and/or points (fn at each texel's map point)")
    ap.add_argument("--texel-maps", default="", help="comma-separated texel-map rules (splat, inverse) to recompute "
                    "and compare; empty = the model's stored map")
    args = parse(ap, argv)
    from core.edits.procedural import evaluate
    from core.images.colour import linear_to_srgb, srgb_to_linear
    from core.images.filter import filter_down
    from core.images.metrics import object_mask, psnr
    from core.images.cameras import rays_for_pixels
    from core.images.dataset import load_split
    from tools.bench.colour_field_bound import mesh_ray_caster

    t_start = time.perf_counter()
    scene = Path(args.scene)
    meta = json.loads((scene / "scene.json").read_text())
    box, texture = meta["bbox"], meta["texture"]["base"]
    cast = mesh_ray_caster(scene)
    test = load_split(scene, "test")
    H, W, focal = test.height, test.width, test.focal
    widths = [float(w) for w in args.supports.split(",") if w.strip()]

    def colour(pts: torch.Tensor) -> torch.Tensor:
        return evaluate(texture, pts.double(), box["center"], box["half_size"])[0]

    def true_hits(c2w, px):
        o, d = rays_for_pixels(c2w.double(), px, H, W, focal)
        return torch.from_numpy(cast(o.expand_as(d).contiguous().numpy(), d.numpy()))

    model, baked = None, {}
    if args.model:
        from core.bundle import load_bundle
        from core.edits.bake import bake
        from core.frames.edited import render_edited
        from core.points.render import straight_colour, trace_frame
        from tools.bench.atlas_vs_papr import atlas_coloured
        bundle = load_bundle(args.model, "cpu")
        model = bundle.model
        if bundle.atlas is None:
            raise SystemExit(f"{args.model}: the model rows render like an atlas-coloured edited frame, which needs "
                             "a model with an atlas; run `pointgt atlas` on it first")
        atlas = bundle.atlas
        rules = [r.strip() for r in args.texel_maps.split(",") if r.strip()]
        if rules:
            from core.atlas.config import AtlasConfig
            from core.pipeline import refresh_texel_map
            train = load_split(scene, "train")
        sources = [b.strip() for b in args.bake_from.split(",") if b.strip()]
        for rule in rules or ["stored"]:
            if rule != "stored":
                refresh_texel_map(bundle, train, AtlasConfig(texel_map=rule, device="cpu"))
            for src in sources:
                if src == "samples" and atlas.bake_samples is None:
                    print(f"{args.model}: no stored surface samples (older file); `pointgt atlas M.pgt DIR "
                          f"--texel-map-only` on a copy stores them")
                    continue
                baked[f"{rule}, from {src}"] = bake(atlas, lambda p: (colour(p).float(), None), source=src)

    scores: dict[str, list[float]] = {}
    centres = _subpixel_grid(H, W, 1)
    fine = _subpixel_grid(H, W, args.sub)
    for i in range(0, len(test), args.every):
        gt, alpha = test.images[i], test.alphas[i]
        a = alpha[..., None].double()
        frames = {}

        def composite(obj_rgb: torch.Tensor, on: torch.Tensor) -> torch.Tensor:
            """obj_rgb [H, W, 3] object colour where on [H, W]; white elsewhere; true alpha as coverage."""
            out = torch.where(on[..., None], a * obj_rgb.double() + (1 - a), torch.ones_like(a).expand(H, W, 3))
            return out.float()

        hits = true_hits(test.c2w[i], centres).reshape(H, W, 3)
        on = torch.isfinite(hits).all(-1)
        rgb = torch.ones(H, W, 3, dtype=torch.float64)
        rgb[on] = colour(hits[on])
        frames["true hit at the pixel centre"] = composite(rgb, on)
        hits_f = true_hits(test.c2w[i], fine).reshape(args.sub * H, args.sub * W, 3)
        on_f = torch.isfinite(hits_f).all(-1)
        col_f = torch.zeros(3, *on_f.shape, dtype=torch.float64)
        col_f[:, on_f] = colour(hits_f[on_f]).T
        for w in widths:
            for space in ("display", "linear"):
                vals = srgb_to_linear(col_f) if space == "linear" else col_f
                px = filter_down(vals, on_f, args.sub, w).permute(1, 2, 0)
                ok = torch.isfinite(px).all(-1)
                px = linear_to_srgb(px) if space == "linear" else px
                frames[f"true hits, filter over {w:g} px, {space}"] = composite(torch.nan_to_num(px, nan=1.0), ok)
        if model is not None:
            tr = trace_frame(model, test.c2w[i], H, W, focal)
            valid = (1 - tr.bg).reshape(H, W) > 0.5

            def object_colour(image=None, texture_fn=None, sub=1):
                """The object colour [H, W, 3] an edited frame gives each ray: rendered over black, coverage divided
                out. texture_fn: the true texture; else the atlas with `image`."""
                state = atlas_coloured(bundle, atlas, antialias=sub, image=image)
                out = render_edited(state, test.c2w[i], H, W, focal, background=(0.0, 0.0, 0.0), trace=tr,
                                    texture_fn=texture_fn)
                return straight_colour(out["rgb"], out["alpha"])

            frames["model x_i at the pixel centre"] = composite(object_colour(texture_fn=colour), valid)
            frames["model x_i, 2 x 2 sub-pixel points, filter over 3 px, linear"] = composite(
                object_colour(texture_fn=colour, sub=2), valid)
            for rule, tex in baked.items():
                frames[f"model x_i, baked ({rule}), pixel centre"] = composite(object_colour(tex), valid)
                frames[f"model x_i, baked ({rule}), filter over 3 px, linear"] = composite(
                    object_colour(tex, sub=2), valid)
        mask = object_mask(alpha, None)
        for name, frame in frames.items():
            scores.setdefault(name, []).append(psnr(frame, gt, mask))
        print(f"view {i}: " + ", ".join(f"{v[-1]:.2f}" for v in scores.values()), flush=True)

    result = {"scene": str(scene), "texture": texture, "model": args.model, "every": args.every, "sub": args.sub,
              "object_psnr": {k: float(np.mean(v)) for k, v in scores.items()},
              "seconds": round(time.perf_counter() - t_start, 1)}
    print(machine_line())
    print(f"{scene} (texture {texture}): test views every {args.every}, {args.sub}x{args.sub} rays per pixel for the "
          f"filtered true-hit rows, {result['seconds']} s")
    print("| object colour from the true texture at | object PSNR (dB) |")
    print("|---|---|")
    for k, v in result["object_psnr"].items():
        print(f"| {k} | {v:.2f} |")
    write_json(args.json, result)
    return 0


if __name__ == "__main__":
    sys.exit(main())
