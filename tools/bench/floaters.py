"""Floaters: what removing a fitted model's floaters (core/points/floaters.py) does to its test views.

    python -m tools.bench.floaters --scene-root DIR --scenes cloth,tube --tag keep --sizes 5,10,20 --radii 2,3

Reads DIR/<scene>/ (a scene made by `pointgt make-scene`, or any NeRF-synthetic folder) and its fit (DIR/<scene>.pgt
or .default.pgt; with --tag T, DIR/<scene>.T.default.pgt: `tools.bench.scenes --tag T --fit-args=...`). A fit made
with its floaters removed (`pointgt fit`'s default) has none left to measure: fit with `--keep-floaters` for this
bench. For each setting (groups of fewer than SIZE points, RADIUS spacings apart) the model's floaters are removed and
its test views rendered (PSNR and object PSNR against the images, the evaluation loop of `pointgt eval`); the first
row per scene is the model as fitted.
"""
from __future__ import annotations

import sys
import time
from pathlib import Path

from tools.bench import parse, parser, write_json


def floater_rows(model_path: Path, data: Path, sizes, radii, views: int = 0, log=print) -> list[dict]:
    """Rows {scene, size, radius, removed, points, psnr, psnr_object, seconds} for the model as fitted (size 0)
    and each (size, radius) setting; views: the first that many test views (0 = all)."""
    import copy

    import torch

    from core.bundle import load_bundle
    from core.images.dataset import load_split
    from core.points.floaters import floater_mask
    from core.points.train import evaluate, resize_points

    test = load_split(data, "test")
    ids = list(range(test.c2w.shape[0]))[: views or None]
    fitted = load_bundle(model_path).model
    xyz = fitted.xyz.detach()
    rows = []
    settings = [(0, 0.0)] + [(s, r) for s in sizes for r in radii]
    for size, radius in settings:
        t0 = time.perf_counter()
        mask = floater_mask(xyz, size, radius) if size else torch.zeros(xyz.shape[0], dtype=torch.bool)
        seconds = time.perf_counter() - t0
        model = copy.deepcopy(fitted)
        resize_points(model, None, torch.nonzero(~mask).squeeze(1))
        sc = evaluate(model, test, ids, (1.0, 1.0, 1.0))
        row = {"scene": data.name, "size": size, "radius": radius, "removed": int(mask.sum()),
               "points": int(xyz.shape[0]), "psnr": sc["psnr"], "psnr_object": sc["psnr_object"],
               "seconds": seconds}
        rows.append(row)
        log(f"[{data.name}] " + ("as fitted" if not size else f"size < {size}, {radius:g} spacings") +
            f": {row['removed']} removed of {row['points']}, PSNR {row['psnr']:.2f} / object "
            f"{row['psnr_object']:.2f} dB ({1000 * seconds:.0f} ms)")
    return rows


def markdown(rows: list[dict]) -> str:
    """One line per scene: the fit's PSNR / object PSNR, then per setting the points removed and the change."""
    settings = sorted({(r["size"], r["radius"]) for r in rows if r["size"]})
    head = ["scene", "fit: PSNR / object"] + [f"< {s} pts, {r:g} sp.: removed, Δ / Δ object" for s, r in settings]
    out = ["| " + " | ".join(head) + " |", "|" + "---|" * len(head)]
    for scene in dict.fromkeys(r["scene"] for r in rows):
        rs = [r for r in rows if r["scene"] == scene]
        fit = next(r for r in rs if not r["size"])
        cells = [scene, f"{fit['psnr']:.2f} / {fit['psnr_object']:.2f}"]
        for s, rad in settings:
            r = next(x for x in rs if (x["size"], x["radius"]) == (s, rad))
            d, d_obj = r["psnr"] - fit["psnr"], r["psnr_object"] - fit["psnr_object"]
            cells.append(f"{r['removed']}, {d:+.2f} / {d_obj:+.2f}")
        out.append("| " + " | ".join(cells) + " |")
    return "\n".join(out)


def main(argv=None) -> int:
    from tools.bench.atlas import scene_model
    from tools.machine import machine_info

    ap = parser(__doc__)
    ap.add_argument("--scene-root", required=True, help="DIR/<scene>/ and its fit DIR/<scene>.pgt (or .default.pgt)")
    ap.add_argument("--scenes", default="cloth", help="scenes (comma-separated)")
    ap.add_argument("--tag", default="", help="read DIR/<scene>.<tag>.default.pgt (`tools.bench.scenes --tag`)")
    ap.add_argument("--sizes", default="5,10,20", help="floater group sizes (fewer points than this; comma-separated)")
    ap.add_argument("--radii", default="2,3", help="gaps in spacings (comma-separated)")
    ap.add_argument("--views", type=int, default=0, help="test views scored (0 = all)")
    args = parse(ap, argv)
    root = Path(args.scene_root)
    rows = []
    for name in [x for x in args.scenes.split(",") if x]:
        model = scene_model(root, name, args.tag)
        if model is None or not (root / name / "transforms_test.json").exists():
            print(f"[{name}] skipped: needs {root / name}/ and its fit")
            continue
        rows += floater_rows(model, root / name, [int(x) for x in args.sizes.split(",") if x],
                             [float(x) for x in args.radii.split(",") if x], args.views)
    machine = machine_info()
    print(markdown(rows))
    print(f"machine: {machine}")
    write_json(args.json, [dict(r, machine=machine) for r in rows])
    return 0


if __name__ == "__main__":
    sys.exit(main())
