"""Frame times an artist sees: the cold first frame after loading a model, then warm frames by size, decoder,
edits and threads, and where a frame's time goes.

Run: `python -m tools.bench.frames [--model M.pgt] [--sizes 128,256,512] [--threads-list 1,0] [--frames 3]`
(add 1024 to --sizes for the largest frames; they take tens of seconds each on a 2-core CPU).
Blender's first frame after opening a .blend: `python -m tools.bench.frames --blend-cold --model M.pgt
[--blend-runs 3] [--threads 1]` (needs the bpy module; see below).

Without --model the bench builds its models in seconds, like `tools.bench.render`: `--points` points on a noisy
sphere, a fresh PointModel with the default ModelConfig and an atlas from a short stage-2 fit; the "UNet" columns
use a second fresh PointModel of the same points with the UNet decoder (fresh weights cost what trained ones do).
With --model, the model is used as it is (its own decoder only).

Frames (`--frames` orbit views, median after one warm-up view, every state interleaved per view):
- plain: canonical points, unedited atlas (the training-time render);
- deformed + painted: the bend of `tools.bench.render` and a baked global retexture; a fresh EditState per frame,
  as the add-on makes one whenever the pose changes, so the local deformation gradients are fitted every frame
  (and, as in the add-on, the painted atlas prepared once is passed on: EditState's paint_from).
Threads: `--threads-list` (0 = all the machine's cores); the profile runs on the first entry.

Cold first frame: a separate process (`--cold` on, the default) imports torch and the renderer, loads the model
file, and renders one deformed + painted frame at the smallest size, then a second, warm one; the parent times the
whole process from outside too (interpreter start-up included).

Blender's first frame (`--blend-cold`, instead of everything above; needs the bpy module): the add-on is packaged
from this checkout and installed into a fresh Blender user folder, and a scene is saved as an artist makes it: the
model (`--model`, a trained one with an atlas) imported with its surface proxy, a disc painted into its atlas, a
two-bone armature on the proxy with one bone turned, the PointGT engine at `--blend-size`² — once with the model
packed into the .blend (the import's default), once read from the .pgt next to it. Each of `--blend-runs` rounds
starts a fresh Blender per .blend that reads the user preferences, opens the .blend (the add-on's load_post handler
may start its background warm-up), presses F12 (`--blend-wait` seconds after opening; default at once) and again
in a new pose; wall and CPU seconds per step (tools/bench/blend_script.py, tools/bench/blend_cold.py). One more
Blender, with the warm-up switched off, gives the CPU seconds of each part of the first image on its own.
`--blend-work DIR` keeps the scene and frames.

Profile: the deformed + painted frame split into stages by wrapping their functions (tools.bench.render's
timed_parts): neighbour search, local deformation gradients, attention, trace interpolation (the `upsampled` mode's
full-size trace from the training-scale one), point colours (values blended by the attention), decoder,
correspondence, texture lookup; the rest is ray set-up, compositing and bookkeeping.
"""
from __future__ import annotations

import json
import os
import statistics
import subprocess
import sys
import tempfile
import time

from tools.bench import parse, parser, write_json
from tools.bench.render import bend, build_model, orbit_cameras, retexture, timed_parts, with_decoder
from tools.machine import machine_line

STAGES = ("neighbour search", "deformation gradients", "attention", "trace interpolation", "point colours", "decoder",
          "correspondence", "texture lookup")


def stage_parts(bundle) -> list:
    """(object, attribute, label) of the stages timed_parts wraps in a frame of `bundle`."""
    import core.frames.edited as edited_mod
    import core.points.render as render_mod

    return [(render_mod, "select_neighbors", "neighbour search"), (bundle.model, "attend", "attention"),
            (render_mod, "attend_compiled", "attention"), (bundle.model, "shade", "point colours"), (bundle.model, "decode_with_alpha", "decoder"),
            (edited_mod, "ray_canonical_points", "correspondence"), (edited_mod, "_filtered_lookup", "texture lookup"),
            (edited_mod, "_lookup", "texture lookup"), (edited_mod, "interpolate_trace", "trace interpolation")]


class Case:
    """One column of the table: a bundle and an edit (plain | edited)."""

    def __init__(self, label: str, bundle, edited: bool, points=None, painted=None, mode: str = "auto"):
        self.label, self.bundle, self.edited = label, bundle, edited
        self.points, self.painted, self.mode = points, painted, mode

    def state(self, paint_from=None):
        from core.frames.edited import EditConfig, EditState

        cfg = EditConfig(render_mode=self.mode)
        if not self.edited:
            return EditState(self.bundle, cfg=cfg)
        return EditState(self.bundle, points=self.points, atlas=self.painted, cfg=cfg, paint_from=paint_from)


def time_cases(cases: list[Case], cams, size: int, focal, profile: bool = False) -> list[dict]:
    """Per case: median / min / max wall seconds of a frame over cams (one untimed warm-up view first), interleaved
    per view; with profile, the mean seconds per frame of each stage. Plain cases reuse one EditState; edited ones
    make a new one per frame (timed)."""
    from core.frames.edited import render_edited

    plain = {i: c.state() for i, c in enumerate(cases) if not c.edited}
    last = {}  # edited cases: the previous frame's state, whose prepared painted textures the next one reuses
    times = [[] for _ in cases]
    accs = [{} for _ in cases]
    for v, cam in enumerate([cams[0]] + list(cams)):
        for i, c in enumerate(cases):
            acc: dict[str, float] = {}
            t = time.perf_counter()
            if profile:
                with timed_parts(c.bundle, acc, stage_parts(c.bundle)):
                    st = plain.get(i) or c.state(last.get(i))
                    out = render_edited(st, cam, size, size, focal)
            else:
                st = plain.get(i) or c.state(last.get(i))
                out = render_edited(st, cam, size, size, focal)
            if c.edited:
                last[i] = st
            wall = time.perf_counter() - t
            rgb = out["rgb"]
            assert bool(rgb.isfinite().all()) and 0 <= float(rgb.min()) <= float(rgb.max()) <= 1
            if v == 0:
                continue
            times[i].append(wall)
            if profile:
                if c.edited:
                    acc["deformation gradients"] = st.deformation_seconds
                acc["total"] = wall
                for k, s in acc.items():
                    accs[i][k] = accs[i].get(k, 0.0) + s / len(cams)
    return [{"median_s": statistics.median(t), "min_s": min(t), "max_s": max(t), **({"stages": a} if profile else {})}
            for t, a in zip(times, accs)]


def cold_child(path: str, size: int, threads: int) -> dict:
    """The cold process's work, timed from inside: imports, model load, edit inputs, first frame, second frame."""
    t0 = time.perf_counter()
    import torch

    if threads > 0:
        torch.set_num_threads(threads)
    from core.bundle import load_bundle
    from core.frames.edited import EditState, render_edited

    t1 = time.perf_counter()
    bundle = load_bundle(path, device="cpu")
    t2 = time.perf_counter()
    bent = bend(bundle.model.xyz.detach(), float(bundle.model.spacing))
    painted = retexture(bundle.atlas)
    cams, focal = orbit_cameras(2, size)
    t3 = time.perf_counter()
    render_edited(EditState(bundle, points=bent, atlas=painted), cams[0], size, size, focal)
    t4 = time.perf_counter()
    render_edited(EditState(bundle, points=bent + 1e-3 * float(bundle.model.spacing), atlas=painted), cams[1],
                  size, size, focal)
    t5 = time.perf_counter()
    return {"imports_s": t1 - t0, "load_s": t2 - t1, "edit_inputs_s": t3 - t2, "first_frame_s": t4 - t3,
            "second_frame_s": t5 - t4}


def run_cold(path: str, size: int, threads: int) -> dict:
    """Run cold_child in a new Python process; adds its whole wall time as seen from here (process_s)."""
    env = {**os.environ, "PYTHONPATH": os.pathsep.join([os.getcwd(), os.environ.get("PYTHONPATH", "")])}
    t = time.perf_counter()
    out = subprocess.run([sys.executable, "-m", "tools.bench.frames", "--cold-child", path, str(size), str(threads)],
                         capture_output=True, text=True, env=env, check=False)
    wall = time.perf_counter() - t
    if out.returncode:
        raise RuntimeError(f"cold first frame process failed:\n{out.stderr[-2000:]}")
    res = json.loads(out.stdout.strip().splitlines()[-1])
    res["process_s"] = wall
    return res


def _fmt(r: dict) -> str:
    return f"{r['median_s']:.3f} ({r['min_s']:.2f}–{r['max_s']:.2f})"


def blend_main(args) -> int:
    """--blend-cold: set up the scene, time the fresh Blenders, print the table (and --json)."""
    from pathlib import Path

    from tools.bench.blend_cold import blend_cold, table

    if args.blend_runs < 1 or args.blend_size < 8:
        raise SystemExit("--blend-runs must be at least 1 and --blend-size at least 8")
    if args.model is None:
        raise SystemExit("--blend-cold needs --model: a trained .pgt with an atlas (a built sphere's surface proxy "
                         "does not bind its points)")
    threads = args.threads if args.threads > 0 else 0
    with tempfile.TemporaryDirectory() as tmp:
        work = Path(args.blend_work or tmp).resolve()
        model = args.model
        print(machine_line())
        res = blend_cold(model, work, args.blend_size, args.blend_runs, threads, args.blend_wait)
        print(f"Blender's first frame after opening a .blend ({args.blend_size}², {threads or 'default'} thread(s), "
              f"F12 {args.blend_wait:g} s after opening; median (min–max) of {args.blend_runs} fresh Blenders per "
              f"row; load average {res['load'][0]:.1f} before, {res['load'][1]:.1f} after):")
        print("\n".join(table(res)))
        print(f"where the first image's CPU time goes ({next(iter(res['runs']))} model, one run, warm-up off): " +
              ", ".join(f"{k} {v:.2f} s" for k, v in res["parts"].items()))
        write_json(args.json, {"machine": machine_line(), "model": str(model), **res})
    return 0


def main(argv=None) -> int:
    argv = sys.argv[1:] if argv is None else list(argv)
    if argv[:1] == ["--cold-child"]:
        print(json.dumps(cold_child(argv[1], int(argv[2]), int(argv[3]))))
        return 0
    ap = parser(__doc__)
    ap.add_argument("--model", default=None, help="a trained .pgt with an atlas (default: build one, see above)")
    ap.add_argument("--points", type=int, default=10_000, help="points of the built models")
    ap.add_argument("--atlas-steps", type=int, default=60, help="stage-2 steps of the built models' atlas")
    ap.add_argument("--sizes", default="128,256,512", help="comma-separated frame sizes (size × size pixels)")
    ap.add_argument("--threads-list", default="1,0", help="comma-separated torch thread counts (0 = all cores)")
    ap.add_argument("--frames", type=int, default=3, help="timed views per cell (median reported)")
    ap.add_argument("--decoders", default="none,unet", help="built models: decoders to time (none, unet)")
    ap.add_argument("--render-modes", default="auto",
                    help="comma-separated render modes to time, each its own columns (auto = the model's; "
                         "core/points/resolution.py: frames finer than the training pixels)")
    ap.add_argument("--no-cold", action="store_true", help="skip the cold first-frame process")
    ap.add_argument("--no-profile", action="store_true", help="skip the per-stage profile")
    ap.add_argument("--blend-cold", action="store_true", help="time Blender's first frame after opening a .blend "
                    "instead of the frames (this file's docstring says how)")
    ap.add_argument("--blend-size", type=int, default=128, help="--blend-cold: render size (size × size pixels)")
    ap.add_argument("--blend-runs", type=int, default=3, help="--blend-cold: fresh Blenders per .blend")
    ap.add_argument("--blend-wait", type=float, default=0.0, help="--blend-cold: seconds between opening and F12")
    ap.add_argument("--blend-work", default=None, help="--blend-cold: folder for the scene (default: a temporary one)")
    args = parse(ap, argv, threads=0)
    if args.blend_cold:
        return blend_main(args)

    import torch

    from core.bundle import load_bundle, save_bundle

    sizes = [int(s) for s in args.sizes.split(",") if s.strip()]
    threads = [int(s) or (os.cpu_count() or 1) for s in args.threads_list.split(",") if s.strip()]
    t0 = time.perf_counter()
    if args.model:
        bundle = load_bundle(args.model, device="cpu")
        if bundle.atlas is None:
            raise SystemExit(f"{args.model}: this model has no atlas; run `pointgt atlas` on it first")
        bundles = {bundle.model.cfg.decoder: bundle}
        source = f"{args.model} ({bundle.model.num_points} points, trained, decoder {bundle.model.cfg.decoder})"
    else:
        decs = [d.strip() for d in args.decoders.split(",") if d.strip()]
        base = build_model(args.points, args.atlas_steps)
        bundles = {d: (base if d == "none" else with_decoder(base, d)) for d in decs}
        source = (f"built: {args.points} points on a noisy sphere, fresh PointModels (default ModelConfig; decoders "
                  f"{', '.join(decs)}), atlas from a {args.atlas_steps}-step stage-2 fit")
    build_s = time.perf_counter() - t0
    any_bundle = next(iter(bundles.values()))
    cfg = any_bundle.model.cfg
    xyz = any_bundle.model.xyz.detach()
    bent = bend(xyz, float(any_bundle.model.spacing))
    painted = retexture(any_bundle.atlas)
    names = {"none": "no decoder", "unet": "UNet"}
    cases = []
    modes = [m.strip() for m in args.render_modes.split(",") if m.strip()]
    for d, b in bundles.items():
        for mode in modes:
            tag = "" if modes == ["auto"] else f" ({mode})"
            cases.append(Case(f"{names.get(d, d)}: plain{tag}", b, False, mode=mode))
            cases.append(Case(f"{names.get(d, d)}: deformed + painted{tag}", b, True, bent, painted, mode=mode))

    print(machine_line())
    print(f"model: {source}; K = {cfg.k}, {cfg.neighbors} neighbours, atlas "
          f"{tuple(any_bundle.atlas.packed_image().shape[:2])}; ready in {build_s:.1f} s")
    print(f"frames: median (min–max) wall s of {args.frames} orbit views after 1 warm-up, states interleaved")

    cold = None
    if not args.no_cold:
        with tempfile.TemporaryDirectory() as tmp:
            path = args.model
            if path is None:
                path = os.path.join(tmp, "model.pgt")
                save_bundle(path, bundles[next(iter(bundles))], backup=False)
            cold = run_cold(path, min(sizes), threads[0])
        print(f"\ncold first frame (new process, {threads[0]} thread(s), deformed + painted {min(sizes)}², model "
              f"{'--model' if args.model else 'built, decoder ' + next(iter(bundles))}):")
        print("| process wall s | imports s | model load s | edit inputs s | first frame s | second frame s |")
        print("|---|---|---|---|---|---|")
        print(f"| {cold['process_s']:.2f} | {cold['imports_s']:.2f} | {cold['load_s']:.2f} | "
              f"{cold['edit_inputs_s']:.2f} | {cold['first_frame_s']:.2f} | {cold['second_frame_s']:.2f} |")

    rows = []
    profiles = {}
    for nt in threads:
        torch.set_num_threads(nt)
        for size in sizes:
            cams, focal = orbit_cameras(args.frames, size)
            prof = not args.no_profile and nt == threads[0]
            res = time_cases(cases, cams, size, focal, profile=prof)
            rows.append({"threads": nt, "size": size, "cells": {c.label: r for c, r in zip(cases, res)}})
            if prof:
                for c, r in zip(cases, res):
                    if c.edited:
                        profiles[(size, c.label)] = r["stages"]
    print("\n| size | threads | " + " | ".join(c.label for c in cases) + " |")
    print("|---|---|" + "---|" * len(cases))
    for r in rows:
        print(f"| {r['size']}² | {r['threads']} | " + " | ".join(_fmt(r["cells"][c.label]) for c in cases) + " |")

    if profiles:
        print(f"\nwhere a deformed + painted frame's time goes ({threads[0]} thread(s); s per frame, share):")
        print("| size | model | total s | " + " | ".join(STAGES) + " | rest |")
        print("|---|---|---|" + "---|" * (len(STAGES) + 1))
        for (size, label), st in profiles.items():
            tot = st["total"]
            cells = [f"{st.get(s, 0.0):.3f} ({100 * st.get(s, 0.0) / tot:.0f} %)" for s in STAGES]
            rest = tot - sum(st.get(s, 0.0) for s in STAGES)
            print(f"| {size}² | {label.split(':')[0]} | {tot:.3f} | " + " | ".join(cells) +
                  f" | {rest:.3f} ({100 * rest / tot:.0f} %) |")

    write_json(args.json, {"machine": machine_line(), "model": source, "frames": args.frames, "cold": cold,
                           "rows": rows,
                           "profile": [{"size": s, "case": c, "stages": st} for (s, c), st in profiles.items()]})
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
