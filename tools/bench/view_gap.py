"""Where a stage-1 model's object error is, on its training and its test views, grazing views apart.

`python -m tools.bench.view_gap --model M.pgt --data DIR [--splits train,test] [--grazing 17]`: every view of each
split is rendered as `pointgt eval` renders it and its object PSNR (the same object pixels: true ∪ rendered
foreground) is split by where the squared error lies — pixels that are foreground in both the truth and the render
("both"), in the truth only ("missed") or in the render only ("spurious") — with the mask IoU, the object's pixel
count and, for a residual UNet, the object PSNR of the decoder-free render it corrects ("base"). Views are grouped
by their camera's elevation above the world's XY plane (the scenes of `pointgt make-scene` are centred at the
origin, Z up): "grazing" below --grazing degrees, where a flat object such as the cloth is seen nearly edge-on.
The gap between a split's groups and between the splits tells a silhouette problem (missed / spurious, IoU) from a
colour problem inside the object (both).
"""
from __future__ import annotations

import math

import torch

from tools.bench import parse, parser, write_json

REGIONS = ("both", "missed", "spurious")


def elevation_deg(c2w: torch.Tensor) -> float:
    """The camera position's elevation in degrees above the world XY plane, seen from the origin. c2w [4, 4]."""
    p = c2w[:3, 3].double()
    n = float(p.norm())
    return 0.0 if n == 0 else math.degrees(math.asin(max(-1.0, min(1.0, float(p[2]) / n))))


def view_row(rgb: torch.Tensor, alpha: torch.Tensor, gt: torch.Tensor, gt_alpha: torch.Tensor,
             base: torch.Tensor | None = None) -> dict:
    """One view's figures. rgb [H, W, 3] and alpha [H, W] the render, gt [H, W, 3] and gt_alpha [H, W] the truth,
    base [H, W, 3] the decoder-free render (or None). Returns psnr_object, base_psnr_object (NaN without base),
    iou, pixels (object pixels) and share_<region> of the object's squared error (0 each for a perfect render)."""
    from core.images.metrics import object_mask, psnr

    g, p = gt_alpha > 0.5, alpha > 0.5
    obj = object_mask(gt_alpha, alpha)
    err = ((rgb - gt) ** 2).sum(-1)
    total = float(err[obj].sum())
    masks = {"both": g & p, "missed": g & ~p, "spurious": ~g & p}
    union = int((g | p).sum())
    row = {"psnr_object": psnr(rgb, gt, obj) if bool(obj.any()) else float("nan"),
           "base_psnr_object": psnr(base, gt, obj) if base is not None and bool(obj.any()) else float("nan"),
           "iou": float((g & p).sum()) / union if union else float("nan"), "pixels": int(obj.sum())}
    for name, m in masks.items():
        row["share_" + name] = float(err[m].sum()) / total if total > 0 else 0.0
    return row


@torch.no_grad()
def split_rows(model, split, grazing_deg: float) -> list[dict]:
    """view_row of every view of a split (SplitData) for a PointModel, with its elevation and group."""
    from core.points.render import render_frame

    rows = []
    for i in range(split.images.shape[0]):
        out = render_frame(model, split.c2w[i], split.height, split.width, split.focal)
        base = None
        if model.decoder is not None and model.cfg.decoder_residual:
            tr = out["trace"]
            sh = model.shade({"weights": tr.weights, "bg": tr.bg}, tr.dirs, tr.idx, torch.ones(3))
            base = sh["feature"][:, :3].reshape(split.height, split.width, 3).clamp(0, 1)
        row = view_row(out["rgb"], out["alpha"], split.images[i].to(out["rgb"].device),
                       split.alphas[i].to(out["rgb"].device), base)
        elev = elevation_deg(split.c2w[i])
        rows.append({"view": split.files[i].name if hasattr(split.files[i], "name") else str(split.files[i]),
                     "elevation": elev, "group": "grazing" if abs(elev) < grazing_deg else "other", **row})
    return rows


def summarise(rows: list[dict]) -> dict:
    """Means per group ("grazing", "other", "all") of the figures of split_rows (NaN figures left out)."""
    out = {}
    for group in ("grazing", "other", "all"):
        sel = [r for r in rows if group == "all" or r["group"] == group]
        if not sel:
            continue
        keys = ["psnr_object", "base_psnr_object", "iou", "pixels"] + ["share_" + r for r in REGIONS]
        mean = {}
        for k in keys:
            vals = [r[k] for r in sel if not (isinstance(r[k], float) and math.isnan(r[k]))]
            mean[k] = sum(vals) / len(vals) if vals else float("nan")
        out[group] = {"views": len(sel), **mean}
    return out


def markdown(result: dict) -> str:
    """The summary as a markdown table, one row per split and group."""
    lines = ["| split | views | object PSNR | base object PSNR | mask IoU | error share both / missed / spurious "
             "| object pixels |", "|---|---|---|---|---|---|---|"]
    for split, groups in result["splits"].items():
        for group, s in groups["summary"].items():
            lines.append(f"| {split}, {group} | {s['views']} | {s['psnr_object']:.2f} | {s['base_psnr_object']:.2f} "
                         f"| {s['iou']:.3f} | {s['share_both']:.2f} / {s['share_missed']:.2f} / "
                         f"{s['share_spurious']:.2f} | {s['pixels']:.0f} |")
    return "\n".join(lines)


def main(argv=None) -> int:
    ap = parser(__doc__)
    ap.add_argument("--model", required=True, help="stage-1 model file (.pgt)")
    ap.add_argument("--data", required=True, help="dataset folder (any layout of docs/formats.md)")
    ap.add_argument("--splits", default="train,test", help="comma-separated splits to evaluate")
    ap.add_argument("--grazing", type=float, default=17.0,
                    help="views whose camera elevation is below this many degrees (absolute) are grazing")
    args = parse(ap, argv)
    from core.bundle import load_bundle
    from core.images.dataset import load_split
    from core.util.atomic import check_output_file
    from core.util.errors import InputError

    if args.json:
        check_output_file(args.json, "--json")
    if not 0.0 < args.grazing <= 90.0:
        raise InputError(f"--grazing {args.grazing}: an elevation in degrees in (0, 90]")
    model = load_bundle(args.model, device="cpu").model
    result = {"model": str(args.model), "data": str(args.data), "grazing_deg": args.grazing, "splits": {}}
    for name in [s for s in args.splits.split(",") if s]:
        rows = split_rows(model, load_split(args.data, name), args.grazing)
        result["splits"][name] = {"summary": summarise(rows), "per_view": rows}
    print(markdown(result))
    write_json(args.json, result)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
