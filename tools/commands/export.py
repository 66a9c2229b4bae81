"""`pointgt export MODEL.pgt [--points P.npy] [--atlas A.png] [--texels T.npy] [--outlines O.png]`."""
from __future__ import annotations

NAME = "export"
HELP = ("write a model's canonical points (N, 3), its atlas PNG, its texel->surface map (H, W, 3) and its island "
        "outlines (RGBA PNG overlay)")
ORDER = 45


def add_arguments(p):
    p.add_argument("model", help="model file (.pgt)")
    p.add_argument("--points", default=None, help="canonical points, float32 [N, 3] in model order (.npy)")
    p.add_argument("--atlas", default=None, help="packed atlas image (.png), the one to paint")
    p.add_argument("--texels", default=None,
                   help="texel->surface map, float32 [H, W, 3] aligned with the atlas PNG (row 0 = top), NaN = none")
    p.add_argument("--outlines", default=None,
                   help="island outlines as an RGBA PNG the size of the atlas (transparent elsewhere), to lay over it "
                        "while painting; atlases without islands outline the texels that have a surface point")


def run(args) -> int:
    import io

    import numpy as np

    from core.images.png import write_png
    from core.modelfile import PgtFile
    from core.util.atomic import atomic_write_bytes
    from core.util.errors import ModelFileError
    from tools.cli import UserError

    from core.util.atomic import check_output_file

    if not (args.points or args.atlas or args.texels or args.outlines):
        raise UserError("nothing to export: give --points, --atlas, --texels and/or --outlines")
    for path, flag in ((args.points, "--points"), (args.atlas, "--atlas"), (args.texels, "--texels"),
                       (args.outlines, "--outlines")):
        if path:
            check_output_file(path, flag)
    with PgtFile(args.model) as f:  # numpy only: export needs no torch and never builds the networks
        names = set(f.names)
        if (args.atlas or args.texels or args.outlines) and "atlas/image" not in names:
            raise ModelFileError(f"{args.model}: has no atlas yet; run `pointgt atlas {args.model} DATA` first")

        def save_npy(path, arr):
            buf = io.BytesIO()
            np.save(buf, np.ascontiguousarray(arr, dtype=np.float32), allow_pickle=False)
            atomic_write_bytes(path, buf.getvalue())
            print(f"wrote {path} {tuple(arr.shape)} float32")

        if args.points:
            save_npy(args.points, f.read("points/xyz"))
        if args.atlas:
            img = f.read("atlas/image")
            if not np.isfinite(img).all():  # a black PNG would hide the damage
                raise ModelFileError(f"{args.model}: array 'atlas/image' holds NaN or infinite values; the atlas is "
                                     "damaged, refit it with `pointgt atlas`")
            write_png(args.atlas, img)
            print(f"wrote {args.atlas} {img.shape[1]}x{img.shape[0]}")
        if args.texels:
            save_npy(args.texels, f.read("atlas/texel_points"))
        if args.outlines:
            from core.atlas.outlines import CELL_KEYS, island_mask, outline_overlay

            shape = tuple(f.read("atlas/image").shape[:2])
            keys = [k for k in (*CELL_KEYS, "atlas/islands/offset", "atlas/islands/orient", "atlas/texel_points")
                    if k in names]
            overlay = outline_overlay(island_mask({k: f.read(k) for k in keys}, shape))
            write_png(args.outlines, overlay)
            print(f"wrote {args.outlines} {shape[1]}x{shape[0]} RGBA, {int((overlay[..., 3] > 0).sum())} outline "
                  "pixels")
    return 0
