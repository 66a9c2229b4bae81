"""Frame cost of the deformation-gradient parts of the edit path, against the paper's renderer (needs bpy).

Run: `python -m tools.bench.deformation MODEL.pgt --scene DIR [--pose stretch] [--views 4] [--repeats 3]
[--size 128] [--variants "A;B"] [--variant "A:FIELD=VALUE,..."]`.

The model's points are posed by the scene's rig (as `pointgt eval-edits` does) and a global retexture is baked
into the atlas; every frame then builds a fresh EditState, as an animation does when the points move each frame,
so the F fit (canonical neighbourhoods cached per model, one O(N·k) least-squares fit per frame) is charged to
every frame. So is the painted atlas's preparation (unpacking it, a few ms a frame for every renderer, and about
1 ms more for the stored samples' reads of the samples lookup), which the add-on and the demo's animation do once
(EditState's paint_from). Variants are interleaved per camera and repeat (the machine's load drifts alike for all), one torch
thread; the table gives the median wall and CPU (process) seconds per frame and the CPU ratio to the paper's.
`--profile`: a second table splits each variant's CPU milliseconds per frame (mean) into stages, by wrapping their
functions (tools.bench.render's timed_parts): the F fit (neighbour gathering and least squares), the fill, the
inverse gradients (the keys' and the occlusion rule's), the neighbour search, the attention, shading and decoder,
the correspondence, the texture lookup; "other" is the rest (ray set-up, compositing, bookkeeping).
"""
from __future__ import annotations

import argparse
import statistics
import time
from pathlib import Path

from tools.bench.regions import parse_variant
from tools.eval_edits import RENDERERS

# the paper's renderer with the deform-aware correspondence and the frame's reach rule (every F switch named, from
# eval-edits' "paper" renderer: the defaults may change)
_OFF = {**RENDERERS["paper"], "correspondence": "deform-aware", "f_radius_rule": "frame"}
# F-aware keys, blended fill, fold rule, canonical depths, compression by thickness; and with the budget reach
_AUTO = {**_OFF, "f_attention": True, "f_fill": True, "fold_radius": 2.0, "f_fill_features": "blend",
         "f_depth": "nearest", "f_compression": "auto"}
_BUDGET = {**_AUTO, "f_radius": True, "f_radius_rule": "budget"}
_D = "f-attention + blended fill + fold rule, depth from the canonical nearest, auto compression"
# with the budget reach gated between points, the keys' stretch by thickness and the perspective reach (factor 4)
_PERSP = {**_BUDGET, "f_reach_gate": 1.5, "f_reach_between": True, "f_key_stretch": "auto", "f_reach_perspective": 4.0}
_P = _D + ", budget reach gated at 1.5 caps between points, keys' stretch by the model's thickness, perspective reach"
# with the perspective reach's factor at 16, the stretch grid and the squash grid (the chart networks' lookup, as the
# paper's renderer; the default renderer looks up through the stored samples)
_P16 = {**_PERSP, "f_reach_perspective": 16.0, "stretch_grid": 1.5, "squash_grid": 1.5}
VARIANTS = {  # name: EditConfig fields (every F switch named: the defaults may change)
    "paper, deform-aware": _OFF,
    "f-attention, deform-aware": {**_OFF, "f_attention": True},
    "f-attention, deform-gradient": {**_OFF, "f_attention": True, "correspondence": "deform-gradient"},
    "f-attention + f-radius, deform-gradient": {**_OFF, "f_attention": True, "f_radius": True,
                                                "correspondence": "deform-gradient"},
    "f-keep, deform-gradient": {**_OFF, "f_attention": True, "f_compression": "keep",
                                "correspondence": "deform-gradient"},
    "f-squash, deform-gradient": {**_OFF, "f_attention": True, "f_compression": "undo",
                                  "correspondence": "deform-gradient"},
    "f-attention + fold rule, deform-aware": {**_OFF, "f_attention": True, "fold_radius": 2.0},
    "f-attention + fill, deform-aware": {**_OFF, "f_attention": True, "f_fill": True},
    "f-attention + fill + fold rule, deform-aware": {**_OFF, "f_attention": True, "f_fill": True, "fold_radius": 2.0},
    "f-attention + fill + fold rule + occlusion, deform-aware": {**_OFF, "f_attention": True, "f_fill": True,
                                                                 "fold_radius": 2.0, "f_occlusion": True},
    "f-attention + blended fill + fold rule, deform-aware": {**_OFF, "f_attention": True, "f_fill": True,
                                                             "fold_radius": 2.0, "f_fill_features": "blend"},
    "f-attention + fill + local-map fold rule, deform-aware": {**_OFF, "f_attention": True, "f_fill": True,
                                                               "fold_radius": 0.5, "fold_test": "local-map"},
    "f-attention + blended fill + fold rule + gap reach, deform-aware": {
        **_OFF, "f_attention": True, "f_fill": True, "fold_radius": 2.0, "f_fill_features": "blend",
        "f_radius": True, "f_radius_rule": "gap"},
    "f-attention + blended fill + fold rule, depth from the canonical nearest, deform-aware": {
        **_OFF, "f_attention": True, "f_fill": True, "fold_radius": 2.0, "f_fill_features": "blend",
        "f_depth": "nearest"},
    "f-attention + blended fill + fold rule, depth from the canonical nearest, undo, deform-aware": {
        **_OFF, "f_attention": True, "f_fill": True, "fold_radius": 2.0, "f_fill_features": "blend",
        "f_depth": "nearest", "f_compression": "undo"},
    _D + ", deform-aware": _AUTO,
    _D + ", gap reach, deform-aware": {**_AUTO, "f_radius": True, "f_radius_rule": "gap"},
    _D + ", gated gap reach, deform-aware": {**_AUTO, "f_radius": True, "f_radius_rule": "gap", "f_reach_gate": 1.0},
    _D + ", budget reach, deform-aware": _BUDGET,
    _D + ", budget reach gated at 1 cap, deform-aware": {**_BUDGET, "f_reach_gate": 1.0},
    _D + ", budget reach gated at 2 caps, deform-aware": {**_BUDGET, "f_reach_gate": 2.0},
    _D + ", keys' stretch capped at the fill's gap, deform-aware": {**_AUTO, "f_key_stretch": "gap"},
    _D + ", keys' stretch capped at the fill's gap, occlusion, deform-aware":
        {**_AUTO, "f_key_stretch": "gap", "f_occlusion": True},
    _D + ", budget reach gated at 1 cap or surrounded, deform-aware":
        {**_BUDGET, "f_reach_gate": 1.0, "f_reach_surround": True},
    _D + ", budget reach gated at 1.5 caps, deform-aware": {**_BUDGET, "f_reach_gate": 1.5},
    _D + ", budget reach gated at 1.5 caps or its own reach, deform-aware":
        {**_BUDGET, "f_reach_gate": 1.5, "f_reach_gate_own": True},
    _D + ", budget reach gated at 1.5 caps between points, deform-aware":
        {**_BUDGET, "f_reach_gate": 1.5, "f_reach_between": True},
    _D + ", budget reach gated at 2 caps between points, deform-aware":
        {**_BUDGET, "f_reach_gate": 2.0, "f_reach_between": True},
    _D + ", budget reach gated at 1.5 caps between points, keys' stretch capped at the fill's gap, deform-aware":
        {**_BUDGET, "f_reach_gate": 1.5, "f_reach_between": True, "f_key_stretch": "gap"},
    _D + ", budget reach gated at 1 cap, keys' stretch capped at the fill's gap, deform-aware":
        {**_BUDGET, "f_reach_gate": 1.0, "f_key_stretch": "gap"},
    _D + ", budget reach gated at 1.5 caps between points, keys' stretch capped at the fill's gap, occlusion, "
         "deform-aware": {**_BUDGET, "f_reach_gate": 1.5, "f_reach_between": True, "f_key_stretch": "gap",
                          "f_occlusion": True},
    _D + ", budget reach gated at 1.5 caps between points, keys' stretch only where the fill left pairs sparse, "
         "deform-aware": {**_BUDGET, "f_reach_gate": 1.5, "f_reach_between": True, "f_key_stretch": "sparse"},
    _D + ", budget reach gated at 1.5 caps between points, keys' stretch only where the fill left pairs sparse, "
         "occlusion, deform-aware": {**_BUDGET, "f_reach_gate": 1.5, "f_reach_between": True,
                                     "f_key_stretch": "sparse", "f_occlusion": True},
    _D + ", budget reach gated at 1.5 caps between points, keys' stretch by the model's thickness, deform-aware":
        {**_BUDGET, "f_reach_gate": 1.5, "f_reach_between": True, "f_key_stretch": "auto"},
    _P + ", deform-aware": _PERSP,
    _P + ", stretch grid, deform-aware": {**_PERSP, "stretch_grid": 1.5},
    _P + ", stretch grid, squash grid, deform-aware": {**_PERSP, "stretch_grid": 1.5, "squash_grid": 1.5},
    _P + " 16, stretch grid, squash grid, deform-aware": _P16,
    _P + " 16, stretch grid, squash grid, texture on it, deform-aware": {**_P16, "grid_texture": 0.25},
    _P + " 16, stretch grid, squash grid, samples lookup, deform-aware": {**_P16, "lookup": "samples"},
    _P + " 16, stretch grid, squash grid, texture on it, samples lookup, deform-aware":
        {**_P16, "grid_texture": 0.25, "lookup": "samples"},
    _P + " 16, stretch grid, squash grid, texture on it, samples lookup, occlusion, deform-aware (the default "
         "renderer with the paper's correspondence)": {**_P16, "grid_texture": 0.25, "lookup": "samples",
                                                        "f_occlusion": True},
    _P + " 16, stretch grid, squash grid, texture on it, samples lookup, occlusion, deform-gradient undoing no "
         "compression (the default renderer)": {**_P16, "grid_texture": 0.25, "lookup": "samples", "f_occlusion": True,
                                               "correspondence": "deform-gradient",
                                               "f_correspondence_compression": "keep"},
    _P + " 16, stretch grid, squash grid, occlusion, deform-aware": {**_P16, "f_occlusion": True},
    _P + ", stretch grid, occlusion, deform-aware": {**_PERSP, "stretch_grid": 1.5, "f_occlusion": True},
    _D + ", budget reach gated at 1.5 caps between points, keys' stretch by the model's thickness, occlusion, "
         "deform-aware": {**_BUDGET, "f_reach_gate": 1.5, "f_reach_between": True, "f_key_stretch": "auto",
                          "f_occlusion": True},
    _D + ", budget reach gated at 1.5 caps between points, keys' stretch capped at the fill's gap, no fill past "
         "13.5x, deform-aware": {**_BUDGET, "f_reach_gate": 1.5, "f_reach_between": True, "f_key_stretch": "gap",
                                 "f_fill_tear": 13.5},
    _D + ", budget reach gated at 1.5 caps, keys' stretch capped at the fill's gap, fill budget 3, deform-aware":
        {**_BUDGET, "f_reach_gate": 1.5, "f_key_stretch": "gap", "f_fill_budget": 3.0},
    _D + ", budget reach gated at 2.5 caps between points, keys' stretch capped at the fill's gap, fill budget 2, "
         "deform-aware": {**_BUDGET, "f_reach_gate": 2.5, "f_reach_between": True, "f_key_stretch": "gap",
                          "f_fill_budget": 2.0},
    _D + ", budget reach gated at 2.5 caps between points, keys' stretch capped at the fill's gap, fill budget 3, "
         "deform-aware": {**_BUDGET, "f_reach_gate": 2.5, "f_reach_between": True, "f_key_stretch": "gap",
                          "f_fill_budget": 3.0},
    _D + ", budget reach gated at 1.5 caps, keys' stretch capped at the fill's gap, fill budget 2, deform-aware":
        {**_BUDGET, "f_reach_gate": 1.5, "f_key_stretch": "gap", "f_fill_budget": 2.0},
    _D + ", budget reach gated at 1.5 caps, keys' stretch capped at the fill's gap, deform-aware":
        {**_BUDGET, "f_reach_gate": 1.5, "f_key_stretch": "gap"},
}


PROFILE_STAGES = ("F fit", "fill", "inverse gradients", "neighbour search", "attention", "shading + decoder",
                  "correspondence", "texture lookup")


def _stage_parts(bundle) -> list:
    """(object, attribute, label) of the parts --profile times (the model's cached DeformationField included)."""
    import core.frames.edited as edited_mod
    import core.points.render as render_mod
    from core.edits.deformation import field_for

    fld = field_for(bundle.model)
    return [(fld, "_gather_deformed", "F fit"), (fld, "_fit", "F fit"), (fld, "_fill", "fill"),
            (edited_mod, "inverse", "inverse gradients"), (edited_mod, "key_inverse", "inverse gradients"),
            (edited_mod, "expansion_inverse", "inverse gradients"), (edited_mod, "bound_above", "inverse gradients"),
            (render_mod, "select_neighbors", "neighbour search"), (render_mod, "attend_compiled", "attention"),
            (bundle.model, "attend", "attention"), (edited_mod, "shade_frame", "shading + decoder"),
            (edited_mod, "ray_canonical_points", "correspondence"), (edited_mod, "_filtered_lookup", "texture lookup")]


def run(model_path, scene_dir, pose: str, magnitude: float, views: int, repeats: int, size: int | None = None,
        log=print, variants: list[str] | None = None, profile: bool = False,
        changed: list[str] | None = None) -> dict:
    """variants: names of VARIANTS to time (default: all); the paper's renderer is always the first. changed:
    "VARIANT:FIELD=VALUE,..." strings, a variant with some EditConfig fields changed (timed after the named ones).
    profile: also the mean CPU seconds per frame of each stage (PROFILE_STAGES, and "other")."""
    import contextlib

    import torch

    from tools.bench.render import timed_parts

    from core.bundle import load_bundle
    from core.edits.bake import bake
    from core.edits.procedural import evaluate
    from core.frames.edited import EditConfig, EditState, render_edited
    from core.images.dataset import load_split
    from tools.machine import machine_info
    from tools.eval_edits import deform_points
    from tools.scenes.spec import load_scene_spec

    torch.set_num_threads(1)
    scene_dir = Path(scene_dir)
    spec = load_scene_spec(scene_dir)
    bundle = load_bundle(model_path)
    c, h = spec["bbox"]["center"], spec["bbox"]["half_size"]
    atlas = bake(bundle.atlas, lambda p: (evaluate("stripes", p, c, h, spec["texture"]["params"].get("stripes"))[0],
                                          None))
    points = torch.from_numpy(deform_points(bundle.model.xyz.detach().numpy(), scene_dir, pose, magnitude))
    test = load_split(scene_dir, "test")
    cams = [round(i * (len(test) - 1) / max(views - 1, 1)) for i in range(views)]
    hw = size or test.width
    focal = test.focal * hw / test.width  # the same field of view at another resolution
    names = list(VARIANTS)[:1] + [v for v in (variants or list(VARIANTS)[1:]) if v != list(VARIANTS)[0]]
    for v in names:
        if v not in VARIANTS:
            raise SystemExit(f"--variants: unknown variant {v!r}; choose from {'; '.join(VARIANTS)}")
    chosen = {v: VARIANTS[v] for v in names}
    chosen.update(parse_variant(v, VARIANTS) for v in changed or ())
    wall = {v: [] for v in chosen}
    cpu = {v: [] for v in chosen}
    fit = {v: [] for v in chosen}
    stages = {v: {} for v in chosen}
    for rep in range(repeats + 1):  # the first round warms up (caches the canonical neighbourhoods)
        for i in cams:
            for name, over in chosen.items():
                acc = {}
                timing = timed_parts(bundle, acc, _stage_parts(bundle), clock=time.process_time) if profile and rep \
                    else contextlib.nullcontext()
                t, tc = time.perf_counter(), time.process_time()
                with timing:
                    state = EditState(bundle, points=points, atlas=atlas, cfg=EditConfig(**over))
                    render_edited(state, test.c2w[i], hw, hw, focal)
                if rep:
                    wall[name].append(time.perf_counter() - t)
                    cpu[name].append(time.process_time() - tc)
                    fit[name].append(state.deformation_seconds)
                    acc["other"] = cpu[name][-1] - sum(acc.values())
                    for key, sec in acc.items():
                        stages[name][key] = stages[name].get(key, 0.0) + sec
    base = statistics.median(cpu[next(iter(VARIANTS))])
    rows = [{"variant": v, "wall": statistics.median(wall[v]), "cpu": statistics.median(cpu[v]),
             "cpu_ratio": statistics.median(cpu[v]) / base, "f_seconds": statistics.median(fit[v])}
            for v in chosen]
    if profile:
        frames = len(cams) * repeats
        for r in rows:
            r["stages_ms"] = {key: 1000 * stages[r["variant"]].get(key, 0.0) / frames
                              for key in (*PROFILE_STAGES, "other")}
    return {"model": str(model_path), "scene": spec.get("name"), "pose": pose, "magnitude": magnitude,
            "size": f"{hw}x{hw}", "points": bundle.model.num_points, "frames": len(cams) * repeats,
            "machine": machine_info(), "rows": rows}


def markdown(res: dict) -> str:
    lines = [f"Scene `{res['scene']}`, pose {res['pose']} m={res['magnitude']:g}, {res['size']}, "
             f"{res['points']} points, {res['frames']} frames per variant; machine: {res['machine'].get('cpu')}, "
             f"{res['machine'].get('cores')} cores, 1 torch thread", "",
             "| variant | median wall s/frame | median CPU s/frame | CPU vs paper | of which F (wall s) |",
             "|---|---|---|---|---|"]
    for r in res["rows"]:
        lines.append(f"| {r['variant']} | {r['wall']:.3f} | {r['cpu']:.3f} | {100 * (r['cpu_ratio'] - 1):+.0f} % | "
                     f"{r['f_seconds']:.3f} |")
    if res["rows"] and "stages_ms" in res["rows"][0]:
        keys = list(res["rows"][0]["stages_ms"])
        lines += ["", "CPU ms per frame (mean) by stage:", "",
                  "| variant | " + " | ".join(keys) + " |", "|---|" + "---|" * len(keys)]
        for r in res["rows"]:
            lines.append(f"| {r['variant']} | " + " | ".join(f"{r['stages_ms'][k]:.1f}" for k in keys) + " |")
    return "\n".join(lines) + "\n"


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("model", help="model file (.pgt) with an atlas")
    ap.add_argument("--scene", required=True, help="the scene directory the model was trained on (make-scene)")
    ap.add_argument("--pose", default="stretch", help="rig pose of the scene")
    ap.add_argument("--magnitude", type=float, default=1.0, help="pose magnitude")
    ap.add_argument("--views", type=int, default=4, help="test cameras")
    ap.add_argument("--size", type=int, default=None, help="frame size in pixels (default: the scene's)")
    ap.add_argument("--repeats", type=int, default=3, help="timed rounds over the cameras (after one warm-up)")
    ap.add_argument("--profile", action="store_true", help="also split each variant's CPU time into stages")
    ap.add_argument("--variants", default=None,
                    help="semicolon-separated variant names to time (default: all; the paper's is always timed first)")
    ap.add_argument("--variant", action="append", default=[],
                    help="VARIANT:FIELD=VALUE,... a variant with EditConfig fields changed, timed as well (repeatable)")
    args = ap.parse_args(argv)
    variants = [v.strip() for v in args.variants.split(";") if v.strip()] if args.variants else None
    res = run(args.model, args.scene, args.pose, args.magnitude, args.views, args.repeats, args.size,
              variants=variants, profile=args.profile, changed=args.variant)
    print(markdown(res))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
