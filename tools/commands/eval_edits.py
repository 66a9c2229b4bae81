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
    from core.atlas.config import LOOKUPS
    from core.edits.bake import SOURCES
    from tools.eval_edits import renderers_help

    p.add_argument("--renderers", default=None,
                   help="comma-separated renderer variants, each named with the EditConfig switches it sets beyond "
                        "the paper's renderer (what a switch does: `pointgt render --help`; default: paper and the "
                        "default renderer, what `pointgt render` does): " + renderers_help())
    p.add_argument("--correspondences", default="naive,deform-aware,deform-gradient",
                   help="comma-separated correspondences: naive | deform-aware (the paper's two) | deform-gradient "
                        "(also undoes local rotation and stretch; the default of `pointgt render`)")
    p.add_argument("--antialias", type=int, default=2,
                   help="texture lookups per pixel side (1 = one per ray, no pixel filter)")
    p.add_argument("--retexture", default="stripes", help="global procedural texture for the retexture edit (stripes: along x; checker cells are thinner than a thin object's depth error)")
    p.add_argument("--lookup", default=None, choices=LOOKUPS,
                   help="every renderer's atlas lookup (default: each renderer's own: the paper's through the chart "
                        "networks, the default renderer's through the stored surface samples)")
    p.add_argument("--bake-source", default="auto", choices=SOURCES,
                   help="how the retexture and the decal are baked into the atlas (auto: fitted at the stored surface "
                        "samples; samples: splatted from them)")
    p.add_argument("--samples", type=int, default=None, help="Cycles samples for the ground truth (default: scene's)")
    p.add_argument("--downscale", type=int, default=1,
                   help="integer factor (1-64) the ground truth is area-averaged by: the --downscale the model was "
                        "fitted with (`pointgt fit --downscale`), so its frames are scored at its training size")
    p.add_argument("--device", default="cpu", help="cpu | cuda | auto")
    p.add_argument("--json", default=None, help="write all figures to this JSON file")
    p.add_argument("--markdown", default=None, help="write the tables to this markdown file")


def run(args) -> int:
    import json

    from core.util.atomic import atomic_write_text
    from tools.eval_edits import compared_renderers, markdown, parse_floats, run_eval

    from core.util.atomic import check_output_file

    for path, flag in ((args.json, "--json"), (args.markdown, "--markdown")):
        if path:
            check_output_file(path, flag)  # before the (long) evaluation
    poses = [p.strip() for p in args.poses.split(",") if p.strip()] if args.poses else None
    result = run_eval(args.model, args.scene, poses=poses, magnitudes=parse_floats(args.magnitudes, "--magnitudes"),
                      views=args.views, temperatures=parse_floats(args.temperatures, "--temperatures"),
                      antialias=args.antialias,
                      renderers=([r.strip() for r in args.renderers.split(",") if r.strip()] if args.renderers
                                 else list(compared_renderers())),
                      correspondences=[c.strip() for c in args.correspondences.split(",") if c.strip()],
                      retexture=args.retexture, samples=args.samples, device=args.device,
                      log=lambda m: print(m, flush=True), lookup=args.lookup, bake_source=args.bake_source,
                      downscale=args.downscale)
    table = markdown(result)
    print(table)
    if args.json:
        atomic_write_text(args.json, json.dumps(result, indent=1))
    if args.markdown:
        atomic_write_text(args.markdown, table)
    return 0
