"""`pointgt export MODEL.pgt [--points P.npy] [--atlas A.png] [--texels T.npy]`."""
from __future__ import annotations

NAME = "export"
HELP = "write a model's canonical points (N, 3), its atlas PNG and its texel->surface map (H, W, 3)"
ORDER = 45


def add_arguments(p):
    p.add_argument("model", help="model file (.pgt)")
    p.add_argument("--points", default=None, help="canonical points, float32 [N, 3] in model order (.npy)")
    p.add_argument("--atlas", default=None, help="packed atlas image (.png), the one to paint")
    p.add_argument("--texels", default=None,
                   help="texel->surface map, float32 [H, W, 3] aligned with the atlas PNG (row 0 = top), NaN = none")


def run(args) -> int:
    import io

    import numpy as np

    from core.images.png import write_png
    from core.modelfile import PgtFile
    from core.util.atomic import atomic_write_bytes
    from core.util.errors import ModelFileError
    from tools.cli import UserError

    from core.util.atomic import check_output_file

    if not (args.points or args.atlas or args.texels):
        raise UserError("nothing to export: give --points, --atlas and/or --texels")
    for path, flag in ((args.points, "--points"), (args.atlas, "--atlas"), (args.texels, "--texels")):
        if path:
            check_output_file(path, flag)
    with PgtFile(args.model) as f:  # numpy only: export needs no torch and never builds the networks
        names = set(f.names)
        if (args.atlas or args.texels) and "atlas/image" not in names:
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
    return 0
