"""Frame render times of the edit path (core.frames.edited) and what each of its skips saves.

Run: `python -m tools.bench.render [--model M.pgt] [--points 10000] [--size 128] [--frames 5]`.

Without --model the bench builds a model in seconds: `--points` points on a noisy sphere of radius 0.8 (a stand-in
for a trained surface; neighbour search and attention cost the same whatever the weights are), a freshly
initialised PointModel with the default ModelConfig (K = 20, 32 features, no decoder), and an atlas from a short
stage-2 fit on those points with a smooth analytic colour (default AtlasConfig networks and texture size, fewer
steps). With --model, a trained .pgt (with an atlas) is used as it is.

Frames: `--frames` cameras on an orbit at distance 3.3 with the NeRF-synthetic field of view; each row is the
median frame time over them (after one warm-up frame). Rows:
- canonical: points not moved, atlas unedited (neighbours + attention + point colours only);
- deformed: a smooth bend of the points, atlas unedited (texture work skipped, so no correspondence either);
- deformed + retextured: the bend plus a baked global retexture (correspondence + atlas lookup on every hit ray);
  the same with lookups through the chart networks instead of the stored samples (EditConfig lookup charts).
Skip savings, each against the same frame with the work forced:
- correspondence: canonical points + retexture (skipped: the ray's own surface point is its canonical point)
  vs points displaced by 1e-6 × spacing (forced: "moved", full deform-aware correspondence);
- texture work: bent points + unedited atlas (skipped) vs an atlas with one changed texel (forced: every hit ray
  does the correspondence and two atlas lookups);
- rays that cannot reach the object: the neighbour pixel-radius cap (`ModelConfig.neighbor_radius_px` 0 = auto,
  core/points/neighbors/radius.py) vs no cap (-1, a copy of the model sharing its weights): without it every ray
  with any projected point in the frame gets K neighbours and is attended and shaded.
The last table splits the deformed + retextured frame into its parts (timed by wrapping the functions).
"""
from __future__ import annotations

import contextlib
import copy
import dataclasses
import functools
import math
import statistics
import time
import types

from tools.bench import parse, parser, write_json
from tools.machine import machine_line


def build_model(n: int, atlas_steps: int, seed: int = 0, decoder: str = "none"):
    """A Bundle with n points on a noisy sphere (radius 0.8), a fresh PointModel (decoder "none" | "unet") and a
    short-fit atlas."""
    import torch

    from core.atlas.config import AtlasConfig
    from core.atlas.fit import fit_atlas
    from core.atlas.synthetic import surface_colour
    from core.bundle import Bundle
    from core.points.model import ModelConfig, PointModel, mean_spacing

    g = torch.Generator().manual_seed(seed)
    torch.manual_seed(seed)
    v = torch.randn(n, 3, generator=g)
    xyz = 0.8 * v / v.norm(dim=1, keepdim=True) * (1 + 0.01 * torch.randn(n, 1, generator=g))
    model = PointModel(ModelConfig(num_points=n, decoder=decoder), xyz, mean_spacing(xyz)).eval()
    atlas, _ = fit_atlas(xyz, surface_colour(xyz),
                         AtlasConfig(steps=atlas_steps, texture_steps=max(atlas_steps // 5, 1), charts="4",
                                     device="cpu"), quiet=True)
    return Bundle(model=model, atlas=atlas, meta={"scene": {"name": f"bench sphere, {n} points"}})


def add_model_args(ap, atlas_steps: int, model_help: str) -> None:
    """The benches' model flags: --model (a trained .pgt) or --points / --atlas-steps for a built one."""
    ap.add_argument("--model", default=None, help=model_help)
    ap.add_argument("--points", type=int, default=10_000, help="points of the built model")
    ap.add_argument("--atlas-steps", type=int, default=atlas_steps, help="stage-2 steps of the built model's atlas")


def model_from_args(args, decoder: str = "none"):
    """(Bundle, one line saying where it came from): the --model file, which must have an atlas, or a model built
    by `build_model` from --points / --atlas-steps with a fresh `decoder` ("none" | "unet")."""
    from core.bundle import load_bundle

    if args.model:
        bundle = load_bundle(args.model, device="cpu")
        if bundle.atlas is None:
            raise SystemExit(f"{args.model}: this model has no atlas; run `pointgt atlas` on it first")
        return bundle, f"{args.model} ({bundle.model.num_points} points, trained, decoder {bundle.model.cfg.decoder})"
    bundle = build_model(args.points, args.atlas_steps)
    if decoder != "none":
        bundle = with_decoder(bundle, decoder)
    return bundle, (f"built: {args.points} points on a noisy sphere, fresh PointModel (decoder {decoder}), atlas "
                    f"from a {args.atlas_steps}-step stage-2 fit")


def with_decoder(bundle, decoder: str, seed: int = 0):
    """The bundle's points and atlas with a fresh PointModel of the same config but `decoder` ("none" | "unet")."""
    import torch

    from core.bundle import Bundle
    from core.points.model import PointModel

    torch.manual_seed(seed)
    m = bundle.model
    model = PointModel(dataclasses.replace(m.cfg, decoder=decoder), m.xyz.detach(), float(m.spacing)).eval()
    return dataclasses.replace(bundle, model=model)


def orbit_cameras(frames: int, size: int, distance: float = 3.3):
    """frames c2w [4, 4] on a tilted orbit at `distance` (3.3) looking at the origin, and the focal length."""
    from core.images.cameras import focal_from_fov, look_at

    mats = []
    for i in range(frames):
        a = 2 * math.pi * i / frames + 0.3
        eye = (distance * math.cos(a) * 0.85, distance * math.sin(a) * 0.85, distance * 0.527)
        mats.append(look_at(eye).float())
    return mats, focal_from_fov(size, 0.6911)


def bend(points, spacing: float):
    """A smooth non-rigid deformation: points [N, 3] bent about the z axis by up to ~40°, plus a tiny jitter."""
    import torch

    x, y, z = points.unbind(1)
    ang = 0.5 * z
    c, s = torch.cos(ang), torch.sin(ang)
    out = torch.stack([c * x - s * y, s * x + c * y, z * 1.1], dim=1)
    return out + 0.01 * spacing * torch.sin(7 * points)


def retexture(atlas):
    """A global retexture baked through the texel map: checker of the canonical position."""
    import torch

    from core.edits.bake import bake

    def fn(x):
        k = ((torch.floor(x * 4).sum(1)) % 2)[:, None]
        return k * torch.tensor([0.9, 0.2, 0.1]) + (1 - k) * torch.tensor([0.1, 0.3, 0.9]), None

    return bake(atlas, fn)


def one_texel(atlas):
    """The fitted atlas with one texel changed (enough to switch the texture path on)."""
    img = atlas.packed_image().clone()
    h, w, _ = img.shape
    img[h // 2, w // 2] = 1.0 - img[h // 2, w // 2]
    return img


def uncapped(bundle):
    """The bundle with the neighbour pixel-radius cap off (ModelConfig.neighbor_radius_px = -1); the model is a
    shallow copy sharing the original's weights."""
    model = copy.copy(bundle.model)
    model.cfg = dataclasses.replace(bundle.model.cfg, neighbor_radius_px=-1.0)
    return dataclasses.replace(bundle, model=model)


def time_frames(states, cams, size, focal, warmup: int = 1) -> list[dict]:
    """Frame times of several edit states, interleaved per camera (A, B, A, B, ...) so that a drift in machine
    load hits every state alike. Per state: median wall seconds per frame over cams (after `warmup` untimed
    frames), median CPU seconds of this process per frame (all its threads; on a shared machine wall ≈ CPU / the
    share of a core the process gets), and the stats of the last frame."""
    from core.frames.edited import render_edited

    for c in cams[:warmup]:
        for st in states:
            render_edited(st, c, size, size, focal)
    times = [[] for _ in states]
    cpu = [[] for _ in states]
    stats = [None] * len(states)
    for c in cams:
        for i, st in enumerate(states):
            t, tc = time.perf_counter(), time.process_time()
            out = render_edited(st, c, size, size, focal)
            times[i].append(time.perf_counter() - t)
            cpu[i].append(time.process_time() - tc)
            stats[i] = out["stats"]
            assert bool(out["rgb"].isfinite().all()) and 0 <= float(out["rgb"].min()) <= float(out["rgb"].max()) <= 1
    return [{"median_s": statistics.median(t), "min_s": min(t), "max_s": max(t), "cpu_s": statistics.median(c),
             "stats": st} for t, c, st in zip(times, cpu, stats)]


def default_parts(bundle) -> list:
    """What timed_parts wraps by default: (object, attribute, label) of render_edited's parts."""
    import core.frames.edited as edited_mod
    import core.points.render as render_mod

    return [(render_mod, "select_neighbors", "neighbour search"), (bundle.model, "attend", "attention"),
            (render_mod, "attend_compiled", "attention"), (edited_mod, "shade_frame", "point colours (shade)"),
            (edited_mod, "ray_canonical_points", "correspondence"),
            (edited_mod, "_filtered_lookup", "texture lookup (anti-aliased)"), (edited_mod, "_lookup", "texture lookup")]


@contextlib.contextmanager
def timed_parts(bundle, acc: dict, parts: list | None = None, clock=time.perf_counter):
    """Wrap the parts of render_edited (`parts`: (object, attribute, label) triples, default `default_parts`) to
    accumulate their time in acc[label] (clock: wall by default; time.process_time for CPU seconds). Module
    functions are patched in the module; methods of an instance (the model, the atlas) by an instance attribute,
    removed afterwards."""
    patches = []

    def wrap(obj, name, label):
        fn = getattr(obj, name)

        @functools.wraps(fn)
        def timed(*a, **k):
            t = clock()
            try:
                return fn(*a, **k)
            finally:
                acc[label] = acc.get(label, 0.0) + clock() - t

        setattr(obj, name, timed)
        patches.append((obj, name, fn))

    for obj, name, label in (default_parts(bundle) if parts is None else parts):
        wrap(obj, name, label)
    try:
        yield
    finally:
        for obj, name, fn in reversed(patches):
            if not isinstance(obj, types.ModuleType):
                delattr(obj, name)  # drop the instance attribute: the class method shows again
            else:
                setattr(obj, name, fn)


def compare_chunks(bundle, points, atlas_image, cams, size, focal, chunks: str) -> dict:
    """Edited-frame times for several trace_frame chunk sizes, interleaved per camera: {chunk: (wall s, CPU s)}.
    Each frame is traced with the chunk size, then rendered from that trace (render_edited(trace=...))."""
    from core.frames.edited import EditState, render_edited
    from core.points.render import trace_frame

    sizes = [int(c) for c in chunks.split(",") if c.strip()]
    if not sizes:
        return {}
    state = EditState(bundle, points=points, atlas=atlas_image)
    times = {c: ([], []) for c in sizes}
    for i, cam in enumerate([cams[0]] + list(cams)):  # the first is a warm-up
        for c in sizes:
            t, tc = time.perf_counter(), time.process_time()
            tr = trace_frame(state.bundle.model, cam, size, size, focal, points=state.points,
                             influence=state.influence, temperature=state.cfg.temperature, chunk=c)
            render_edited(state, cam, size, size, focal, trace=tr)
            if i:
                times[c][0].append(time.perf_counter() - t)
                times[c][1].append(time.process_time() - tc)
    print("\ntrace_frame chunk (rays per attention call), deformed + retextured frame, interleaved:")
    print("| chunk | median s | CPU s |")
    print("|---|---|---|")
    out = {}
    for c, (w, cp) in times.items():
        out[c] = (statistics.median(w), statistics.median(cp))
        print(f"| {c} | {out[c][0]:.3f} | {out[c][1]:.3f} |")
    return out


def main(argv=None) -> int:
    ap = parser(__doc__)
    add_model_args(ap, 60, "a trained .pgt with an atlas (default: build one, see above)")
    ap.add_argument("--size", type=int, default=128, help="frames are size × size pixels")
    ap.add_argument("--frames", type=int, default=7, help="timed frames per row (median reported)")
    ap.add_argument("--save-model", default=None, help="save the built model here (reuse it with --model)")
    ap.add_argument("--budget", type=float, default=0.25, help="target seconds for a deformed + retextured frame")
    ap.add_argument("--chunks", default="", help="comma-separated trace_frame chunk sizes (rays per attention call) "
                    "to compare on the deformed + retextured frame, e.g. 16384,1024; empty = skip")
    args = parse(ap, argv, threads=0)

    from core.frames.edited import EditState

    t0 = time.perf_counter()
    bundle, source = model_from_args(args)
    if not args.model and args.save_model:
        from core.bundle import save_bundle

        save_bundle(args.save_model, bundle)
    build_s = time.perf_counter() - t0
    model, atlas = bundle.model, bundle.atlas
    spacing = float(model.spacing)
    cams, focal = orbit_cameras(args.frames, args.size)
    xyz = model.xyz.detach()
    bent = bend(xyz, spacing)
    nudged = xyz + 1e-6 * spacing
    painted = retexture(atlas)
    texel = one_texel(atlas)

    print(machine_line())
    cfg = model.cfg
    print(f"model: {source}; K = {cfg.k}, {cfg.neighbors} neighbours, decoder {cfg.decoder}, atlas "
          f"{tuple(atlas.packed_image().shape[:2])} ({atlas.n} charts); ready in {build_s:.1f} s")
    print(f"frames: {args.size}x{args.size}, median of {args.frames} orbit views after 1 warm-up")

    def rows_of(*specs):
        """specs: (label, EditState kwargs, bundle by default) -> one result dict per spec, timed interleaved."""
        states = [EditState(**{"bundle": bundle, **kw}) for _, kw in specs]
        res = time_frames(states, cams, args.size, focal)
        for r, (label, _) in zip(res, specs):
            r["label"] = label
        return res

    from core.frames.edited import EditConfig

    rows = dict(zip(("canonical", "deformed", "edited", "edited_charts"), rows_of(
        ("canonical", {}), ("deformed (bend)", {"points": bent}),
        ("deformed + retextured", {"points": bent, "atlas": painted}),
        ("deformed + retextured, chart lookups", {"points": bent, "atlas": painted,
                                                  "cfg": EditConfig(lookup="charts")}))))
    print("\n| frame | median s | min–max s | CPU s | rays shaded / rays | texture rays | correspondence |")
    print("|---|---|---|---|---|---|---|")
    for r in rows.values():
        s = r["stats"]
        print(f"| {r['label']} | {r['median_s']:.3f} | {r['min_s']:.3f}–{r['max_s']:.3f} | {r['cpu_s']:.3f} | "
              f"{s['rays_shaded']} / {s['rays']} | {s['texture_rays']} | {s['correspondence']} |")
    edited_s = rows["edited"]["median_s"]
    verdict = "within" if edited_s <= args.budget else "ABOVE"
    print(f"\ndeformed + retextured {args.size}² frame of {model.num_points} points: {edited_s:.3f} s wall, "
          f"{rows['edited']['cpu_s']:.3f} s CPU ({verdict} the {args.budget:.2f} s budget)")

    skips = [
        ("correspondence (points did not move)", *rows_of(
            ("skipped", {"atlas": painted}), ("forced: points moved by 1e-6 spacing", {"points": nudged, "atlas": painted}))),
        ("texture work (atlas unedited)", *rows_of(
            ("skipped", {"points": bent, "atlas": atlas.packed_image()}),
            ("forced: one texel changed", {"points": bent, "atlas": texel}))),
    ]
    skips.append(("rays that cannot reach the object (deformed + retextured)", *rows_of(
        ("skipped", {"points": bent, "atlas": painted}),
        ("forced: no radius cap", {"bundle": uncapped(bundle), "points": bent, "atlas": painted}))))
    print("\n| skip | skipped: median s (CPU s) | forced: median s (CPU s) | saving (CPU) "
          "| rays shaded skipped / forced | texture rays skipped / forced |")
    print("|---|---|---|---|---|---|")
    for name, a, b in skips:
        sa, sb = a["stats"], b["stats"]
        saving = 1 - a["median_s"] / b["median_s"] if b["median_s"] > 0 else float("nan")
        saving_cpu = 1 - a["cpu_s"] / b["cpu_s"] if b["cpu_s"] > 0 else float("nan")
        print(f"| {name} | {a['median_s']:.3f} ({a['cpu_s']:.3f}) | {b['median_s']:.3f} ({b['cpu_s']:.3f}) | "
              f"{100 * saving:.0f} % ({100 * saving_cpu:.0f} %) | "
              f"{sa['rays_shaded']} / {sb['rays_shaded']} | {sa['texture_rays']} / {sb['texture_rays']} |")

    acc: dict[str, float] = {}
    state = EditState(bundle, points=bent, atlas=painted)
    time_frames([state], cams[:1], args.size, focal)  # warm-up outside the wrappers
    with timed_parts(bundle, acc):
        parts = time_frames([state], cams, args.size, focal, warmup=0)[0]
    total = parts["median_s"] * len(cams)
    print(f"\nwhere the deformed + retextured frame's time goes (sum over {len(cams)} frames, wrapped calls):")
    print("| part | s per frame | share |")
    print("|---|---|---|")
    for name, s in sorted(acc.items(), key=lambda kv: -kv[1]):
        print(f"| {name} | {s / len(cams):.4f} | {100 * s / max(total, 1e-12):.0f} % |")
    rest = total - sum(acc.values())
    print(f"| rest (rays, blending, bookkeeping) | {rest / len(cams):.4f} | {100 * rest / max(total, 1e-12):.0f} % |")

    chunk_rows = compare_chunks(bundle, bent, painted, cams, args.size, focal, args.chunks)

    write_json(args.json, {"machine": machine_line(), "model": source, "size": args.size, "frames": args.frames,
                           "rows": {k: dict(v) for k, v in rows.items()},
                           "skips": [{"skip": n, "skipped_s": a["median_s"], "forced_s": b["median_s"],
                                      "skipped_cpu_s": a["cpu_s"], "forced_cpu_s": b["cpu_s"],
                                      "skipped_stats": a["stats"], "forced_stats": b["stats"]} for n, a, b in skips],
                           "parts_s_per_frame": {k: v / len(cams) for k, v in acc.items()}, "chunks": chunk_rows})
    return 0 if edited_s <= args.budget else 1


if __name__ == "__main__":
    raise SystemExit(main())
