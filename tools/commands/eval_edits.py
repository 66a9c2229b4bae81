"""`pointgt eval-edits MODEL.pgt --scene DIR`: geometry + texture edits scored against Blender ground truth."""
from __future__ import annotations

NAME = "eval-edits"
HELP = "score posed + retextured/decal renders of a model against Cycles renders of the posed scene mesh"
DESCRIPTION = (
    "For the rig poses of a built-in scene (pointgt make-scene) at increasing magnitudes: render the posed mesh "
    "with Cycles as ground truth (cached under DIR/poses/), move the model's points with the same rig, render them "
    "with a geometry edit only, + a global procedural retexture, + the scene's decal, each with the chosen "
    "correspondences, renderer variants and attention temperatures; report PSNR (full frame and object "
    "pixels), SSIM, seconds per frame, the blank-frame floor, texture persistence and attention diagnostics."
)
ORDER = 45


def add_arguments(p):
    p.add_argument("model", help="model file (.pgt) with an atlas, trained on the scene in --scene")
    p.add_argument("--scene", required=True, help="scene directory made by `pointgt make-scene` (scene.json, scene.blend)")
    p.add_argument("--poses", default=None, help="comma-separated poses (default: every pose in scene.json but rest)")
    p.add_argument("--magnitudes", default="0.25,0.5,1", help="comma-separated pose magnitudes (1 = the named pose)")
    p.add_argument("--views", type=int, default=4, help="test views per case (evenly spaced over the scene's)")
    p.add_argument("--temperatures", default="1,0.5", help="attention temperatures (< 1 sharpens attention)")
    p.add_argument("--renderers", default="paper,f-attention",
                   help="comma-separated renderer variants: paper (the paper's renderer) | f-attention (attention keys in each "
                        "point's canonical frame, stretch undone) | f-radius (neighbour radius cap scaled by the stretch) | "
                        "f-both | f-keep / f-squash (as f-attention, undoing no / all compression, also in the deform-gradient "
                        "correspondence) | fill / f-fill (paper / f-attention with points added where the pose pulled neighbours "
                        "apart) | fold / fill-fold / f-fold / f-fill-fold (paper / fill / f-attention / f-fill with the "
                        "correspondence's fold rule) | f-fill-fold-occ (f-fill-fold with the occlusion rule: each ray "
                        "keeps its front surface layer) | f-fill-fold-blend (f-fill-fold, each added point's "
                        "features mixed from both ends of its pair) | f-fill-fold-local (f-fill-fold, the fold rule "
                        "comparing each neighbour's local-map estimate of the canonical point, radius 0.5) | "
                        "f-fill-fold-blend-local (both) | f-fill-fold-blend-reach (f-fill-fold-blend, each point "
                        "reaching the neighbour search's cap times the growth the fill left on its pairs) | "
                        "f-fill-fold-blend-undo (f-fill-fold-blend undoing all compression, f_compression undo) | "
                        "f-fill-fold-blend-depth (f-fill-fold-blend, the keys' depths from the ray's nearest "
                        "neighbour in the canonical frames, f_depth nearest) | f-fill-fold-blend-depth-undo (both) | "
                        "f-fill-fold-blend-depth-auto (f-fill-fold-blend-depth, undo on a model whose points form "
                        "a thick shell, f_compression auto) | f-fill-fold-blend-depth-auto-reach (it, with "
                        "f-fill-fold-blend-reach's reach) | f-fill-fold-blend-depth-auto-budget (it, with the reach "
                        "from the pairs the fill budget kept sparse only, f_radius_rule budget) | "
                        "f-fill-fold-blend-depth-auto-budget-gate (that reach only for rays the plain pixel cap gives "
                        "a point, f_reach_gate 1) | f-fill-fold-blend-depth-auto-budget-gate2 (the gate at twice the "
                        "cap) | f-fill-fold-blend-depth-auto-gap (f-fill-fold-blend-depth-auto, the keys undoing at "
                        "most the stretch the fill left between consecutive points, f_key_stretch gap) | "
                        "f-fill-fold-blend-depth-auto-gap-occ (that with the occlusion rule, f_occlusion) | "
                        "f-fill-fold-blend-depth-auto-budget-gate-gap (both -budget-gate and -gap) | "
                        "f-fill-fold-blend-depth-auto-budget-surround (the gate at 1 cap, letting through "
                        "rays their neighbours surround, f_reach_surround) | "
                        "f-fill-fold-blend-depth-auto-budget-gate15 (the gate at 1.5 caps) | "
                        "f-fill-fold-blend-depth-auto-budget-gate15-own (each point's gate at most its own reach, "
                        "f_reach_gate_own) | f-fill-fold-blend-depth-auto-budget-between (the gate at 1.5 caps "
                        "opening beyond the cap only between points more than 120° apart, f_reach_between) | "
                        "f-fill-fold-blend-depth-auto-budget-between2 (that at 2 caps) | "
                        "f-fill-fold-blend-depth-auto-budget-between-gap (both -budget-between and -gap) | "
                        "f-fill-fold-blend-depth-auto-budget-between-gap-tear (it, pairs grown past 13.5× left "
                        "unfilled, f_fill_tear 13.5) | f-fill-fold-blend-depth-auto-budget-gate15-gap-b3 (the gate at "
                        "1.5 caps for any point, -gap, fill budget 3) | "
                        "f-fill-fold-blend-depth-auto-budget-between25-gap-b2 (the gate between points at 2.5 caps, "
                        "-gap, fill budget 2) | f-fill-fold-blend-depth-auto-budget-gate15-gap (the gate at 1.5 caps "
                        "for any point, -gap) | f-fill-fold-blend-depth-auto-budget-gate15-gap-b2 (that, fill budget "
                        "2) | f-fill-fold-blend-depth-auto-budget-between25-gap-b3 (the gate between points at 2.5 "
                        "caps, -gap, fill budget 3)")
    p.add_argument("--correspondences", default="naive,deform-aware",
                   help="comma-separated correspondences: naive | deform-aware (the paper's two) | deform-gradient "
                        "(also undoes local rotation and stretch)")
    p.add_argument("--antialias", type=int, default=2,
                   help="texture lookups per pixel side (1 = one per ray, no pixel filter)")
    p.add_argument("--retexture", default="stripes", help="global procedural texture for the retexture edit (stripes: along x; checker cells are thinner than a thin object's depth error)")
    p.add_argument("--samples", type=int, default=None, help="Cycles samples for the ground truth (default: scene's)")
    p.add_argument("--device", default="cpu", help="cpu | cuda | auto")
    p.add_argument("--json", default=None, help="write all figures to this JSON file")
    p.add_argument("--markdown", default=None, help="write the tables to this markdown file")


def run(args) -> int:
    import json

    from core.util.atomic import atomic_write_text
    from tools.eval_edits import markdown, parse_floats, run_eval

    from core.util.atomic import check_output_file

    for path, flag in ((args.json, "--json"), (args.markdown, "--markdown")):
        if path:
            check_output_file(path, flag)  # before the (long) evaluation
    poses = [p.strip() for p in args.poses.split(",") if p.strip()] if args.poses else None
    result = run_eval(args.model, args.scene, poses=poses, magnitudes=parse_floats(args.magnitudes, "--magnitudes"),
                      views=args.views, temperatures=parse_floats(args.temperatures, "--temperatures"),
                      antialias=args.antialias,
                      renderers=[r.strip() for r in args.renderers.split(",") if r.strip()],
                      correspondences=[c.strip() for c in args.correspondences.split(",") if c.strip()],
                      retexture=args.retexture, samples=args.samples, device=args.device,
                      log=lambda m: print(m, flush=True))
    table = markdown(result)
    print(table)
    if args.json:
        atomic_write_text(args.json, json.dumps(result, indent=1))
    if args.markdown:
        atomic_write_text(args.markdown, table)
    return 0
