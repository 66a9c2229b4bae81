"""The render's fast paths against their plain-torch forms, on one frame's real inputs, timed in the same run.

Run: `python -m tools.bench.fast_paths [--model M.pgt] [--size 256] [--reps 5]` (one thread by default).

The inputs come from one deformed + painted frame of the model (built as in `tools.bench.frames`: a 10k-point
sphere, fresh PointModel with the UNet decoder, short-fit atlas; or --model). Each pair runs interleaved
(torch form, fast path, torch form, ...) `--reps` times; the table gives the median seconds of each, their ratio
and the largest difference of their outputs:
- attention: PointModel.attend over the frame's active rays in chunks of 1024 (trace_frame's torch path) vs the
  compiled kernels (core/points/attention_compiled.py);
- point colours: values gathered per neighbour slot [R, K, C] and weighted vs the per-point table blended by
  embedding_bag (PointModel.shade);
- decoder: the UNet over the whole frame vs over the active rays' box pasted into the cached background frame
  (core/points/render.py decode_where_active);
- texture lookup: the anti-aliased lookup (core/frames/edited.py) over the whole frame vs over the textured rays'
  bounding box;
- pixel filter: the separable strided conv2d vs strided per-tap sums (core/images/filter.py filter_down), on the
  frame's 2 × 2 sub-pixel grid.
"""
from __future__ import annotations

import statistics
import time

from tools.bench import parse, parser, write_json
from tools.bench.frames import Case
from tools.bench.render import add_model_args, bend, model_from_args, orbit_cameras, retexture
from tools.machine import machine_line


def _pair(fa, fb, reps: int):
    """Interleaved timings of fa (torch form) and fb (fast path): (median a, median b, output a, output b)."""
    ta, tb = [], []
    oa = ob = None
    for _ in range(reps):
        t = time.perf_counter()
        oa = fa()
        ta.append(time.perf_counter() - t)
        t = time.perf_counter()
        ob = fb()
        tb.append(time.perf_counter() - t)
    return statistics.median(ta), statistics.median(tb), oa, ob


def _maxdiff(a, b) -> float:
    import torch

    if isinstance(a, (tuple, list)):
        return max(_maxdiff(x, y) for x, y in zip(a, b) if x is not None)
    if isinstance(a, dict):
        return max(_maxdiff(a[k], b[k]) for k in b)
    return float((a.float() - b.float()).abs().nan_to_num(0.0).max()) if torch.is_tensor(a) else 0.0


def main(argv=None) -> int:
    ap = parser(__doc__)
    add_model_args(ap, 20, "a trained .pgt with an atlas and the UNet decoder")
    ap.add_argument("--size", type=int, default=256, help="frame size (size × size pixels)")
    ap.add_argument("--reps", type=int, default=5, help="timed runs of each form (median reported)")
    ap.add_argument("--distance", type=float, default=3.3, help="camera distance (the sphere has radius 0.8; at "
                    "3.3 it fills most of the frame, farther it covers less)")
    args = parse(ap, argv, threads=1)

    import torch
    import torch.nn.functional as F

    from core.frames.edited import render_edited
    from core.images.filter import blackman_harris_taps, filter_down
    from core.points import attention_compiled
    from core.points.render import decode_where_active

    bundle, source = model_from_args(args, decoder="unet")
    model = bundle.model
    bent = bend(model.xyz.detach(), float(model.spacing))
    case = Case("deformed + painted", bundle, True, bent, retexture(bundle.atlas))
    cams, focal = orbit_cameras(2, args.size, args.distance)
    state = case.state()
    out = render_edited(state, cams[1], args.size, args.size, focal)
    tr = out["trace"]
    act = torch.nonzero(tr.active).squeeze(1)
    pts = torch.nan_to_num(state.points, nan=0.0)
    fi = state.inv_f_attention
    o, d, idx = tr.origins[act], tr.dirs[act], tr.idx[act]
    rows = []

    print(machine_line())
    print(f"model: {source}; frame {args.size}² at distance {args.distance:g}, deformed + painted, {act.numel()} "
          f"active rays of "
          f"{tr.idx.shape[0]}, K = {model.cfg.k}; median of {args.reps} interleaved runs each")

    if attention_compiled.supported(model, torch.device("cpu")):
        def attn_torch():
            with torch.no_grad():
                parts = [model.attend(pts, state.influence, o[s:s + 1024], d[s:s + 1024], idx[s:s + 1024], inv_f=fi,
                                      rebase_depth=state.rebase_depth)
                         for s in range(0, act.numel(), 1024)]
            return {k: torch.cat([p[k] for p in parts]) for k in ("weights", "fg_weights", "bg", "x")}

        attention_compiled.attend_compiled(model, pts, state.influence, o[:8], d[:8], idx[:8], inv_f=fi)  # compile
        rows.append(("attention", *_pair(attn_torch, lambda: attention_compiled.attend_compiled(
            model, pts, state.influence, o, d, idx, inv_f=fi, rebase_depth=state.rebase_depth), args.reps)))

    att = {"weights": tr.weights, "bg": tr.bg}
    bgc = torch.ones(3)

    def shade_gather():
        with torch.no_grad():
            v = model.point_values(tr.dirs, tr.idx)
            return (att["weights"][..., None] * v).sum(1)

    def shade_table():
        with torch.no_grad():
            table = model.point_table()
            return F.embedding_bag(tr.idx.clamp_min(0), table, per_sample_weights=att["weights"], mode="sum")

    rows.append(("point colours", *_pair(shade_gather, shade_table, args.reps)))

    if model.decoder is not None:
        with torch.no_grad():
            feat = model.shade(att, tr.dirs, tr.idx, bgc)["feature"]
        h = w = args.size
        fimg = feat.reshape(h, w, -1).permute(2, 0, 1)[None].contiguous()
        active = tr.active.reshape(h, w)
        decode_where_active(model, fimg, active)  # fills the background cache, as the first frame of a size does
        with torch.no_grad():
            rows.append(("decoder", *_pair(lambda: model.decode_with_alpha(fimg),
                                           lambda: decode_where_active(model, fimg, active), args.reps)))

    import core.frames.edited as edited_mod

    hit = tr.active & ((1.0 - tr.bg) > 1e-4)
    sel = torch.nonzero(hit).squeeze(1)
    xc = state.canonical_surface(tr, sel)  # the frame's own correspondence (the default's, with its inverses)

    def lookup(crop):
        with torch.no_grad():
            return edited_mod._filtered_lookup(state, tr, sel, xc, args.size, args.size, focal, state.cfg.antialias,
                                               crop=crop)

    rows.append(("texture lookup (anti-aliased)", *_pair(lambda: lookup(False), lambda: lookup(True), args.reps)))

    sub = 2
    on = tr.active.reshape(args.size, args.size).repeat_interleave(sub, 0).repeat_interleave(sub, 1)
    vals = torch.rand(4, *on.shape, generator=torch.Generator().manual_seed(0))
    k = blackman_harris_taps(sub)
    pad = (k.numel() - sub) // 2

    def filter_conv():
        wgt = on.float()[None]
        stack = F.pad(torch.cat([vals * wgt, wgt], 0)[:, None], (pad, pad, pad, pad))
        y = F.conv2d(F.conv2d(stack, k.view(1, 1, 1, -1), stride=(1, sub)), k.view(1, 1, -1, 1), stride=(sub, 1))[:, 0]
        return torch.where(y[-1] > 1e-8, y[:-1] / y[-1].clamp_min(1e-12), torch.full_like(y[:-1], float("nan")))

    rows.append(("pixel filter", *_pair(filter_conv, lambda: filter_down(vals, on, sub), args.reps)))

    print("\n| path | torch form s | fast path s | speed-up | max abs difference |")
    print("|---|---|---|---|---|")
    for name, ta, tb, oa, ob in rows:
        print(f"| {name} | {ta:.4f} | {tb:.4f} | {ta / max(tb, 1e-12):.1f}× | {_maxdiff(oa, ob):.1e} |")
    write_json(args.json, {"machine": machine_line(), "model": source, "size": args.size,
                           "rows": [{"path": n, "torch_s": a, "fast_s": b, "max_abs_diff": _maxdiff(x, y)}
                                    for n, a, b, x, y in rows]})
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
