"""`pointgt make-scene`: render a built-in scene (Blender Cycles, CPU) in the NeRF-synthetic layout — and write it
again in the nerfstudio / instant-ngp / BlenderNeRF layouts with --format — or a posed / retextured variant of an
existing one."""
from __future__ import annotations

NAME = "make-scene"
HELP = "render a built-in scene of the library (--list) with its rig, poses and ground-truth variants"
DESCRIPTION = (
    "Render a built-in scene with Blender (Cycles, CPU) into DIR in the NeRF-synthetic layout "
    "(transforms_{train,val,test}.json + RGBA PNGs, scene.blend, scene.json). With --pose and/or --texture, "
    "render the test cameras of the existing scene in DIR posed/retextured into DIR/poses/<pose>[_m<M>][_<tex>]/. "
    "With --format nerfstudio|instant-ngp|blendernerf, also write the same scene (same cameras and pixels, no "
    "re-render when DIR already holds it) in that tool's layout into DIR/<format>/."
)
ORDER = 10


def add_arguments(parser) -> None:
    parser.add_argument("name", nargs="?", help="scene name (see --list)")
    parser.add_argument("--list", action="store_true", help="print the library, one scene a line (name, base texture, lighting, description), the default first")
    parser.add_argument("--out", help="output directory")
    parser.add_argument("--size", type=int, default=128, help="image width = height in pixels")
    parser.add_argument("--views-train", type=int, default=60, help="training views")
    parser.add_argument("--views-val", type=int, default=8, help="validation views (a third camera set)")
    parser.add_argument("--views-test", type=int, default=20, help="test views (also used by --pose/--texture)")
    parser.add_argument("--seed", type=int, default=0, help="seed of the camera sets")
    parser.add_argument("--lit", action="store_true", help="lit variant: Principled BSDF + sun instead of emission "
                                                            "(scenes marked lit in --list are always lit)")
    parser.add_argument("--samples", type=int, default=None, help="Cycles samples per pixel (default 64: the frames' "
                                                                  "own noise far below a model's error)")
    parser.add_argument("--pose", default=None, help="render the existing scene in DIR in this pose (e.g. bend, rest)")
    parser.add_argument("--magnitude", type=float, default=1.0, help="pose magnitude: 0 = rest, 1 = the named pose")
    parser.add_argument("--texture", default=None,
                        help="render the existing scene with this texture (a name of core/edits/procedural.py's "
                             "TEXTURES, e.g. checker, stripes, decal)")
    parser.add_argument("--force", action="store_true", help="re-render a scene that already exists in --out")
    parser.add_argument("--format", default="nerf-synthetic",
                        choices=("nerf-synthetic", "nerfstudio", "instant-ngp", "blendernerf"),
                        help="layout to write: nerf-synthetic (DIR itself) or another tool's, written into "
                             "DIR/<format>/ from the NeRF-synthetic render in DIR (rendered first if absent)")


def run(args) -> int:
    from tools.scenes.library import SCENES, scene_names

    if args.list:
        for name in scene_names():
            sdef = SCENES[name]
            print(f"{name:8s} {sdef.texture:11s} {'lit' if sdef.lit else 'emission':8s} {sdef.help}")
        return 0
    from core.util.errors import InputError

    if not args.name:
        raise InputError("give a scene name (one of: " + ", ".join(scene_names()) + ") or --list")
    if args.name not in SCENES:
        raise InputError(f"unknown scene '{args.name}'; choose one of {', '.join(scene_names())}")
    if not args.out:
        raise InputError("--out DIR is required")
    from core.config import check_flag
    from core.util.atomic import check_output_dir

    check_output_dir(args.out, "--out")
    check_flag(args.size, "--size", min=8, max=4096)
    for flag in ("views_train", "views_val", "views_test"):
        check_flag(getattr(args, flag), "--" + flag.replace("_", "-"), min=0 if flag == "views_val" else 1,
                   max=10_000)
    check_flag(args.samples, "--samples", min=1)
    check_flag(args.magnitude, "--magnitude")

    from tools.scenes import build  # imports bpy: only now
    from tools.scenes.spec import load_scene_spec

    if args.pose is not None or args.texture is not None:
        spec = load_scene_spec(args.out)
        if spec.get("name") != args.name:
            raise InputError(f"{args.out}/scene.json holds scene '{spec.get('name')}', not '{args.name}'")
        vdir = build.render_variant(args.out, args.pose or "rest", args.magnitude, args.texture,
                                    samples=args.samples, log=lambda m: print(m, flush=True))
        print(f"wrote {vdir}")
        return 0
    from pathlib import Path

    existing = Path(args.out) / "scene.json"
    if args.format == "nerf-synthetic" or args.force or not existing.exists():
        build.make_scene(args.name, args.out, size=args.size, views_train=args.views_train,
                         views_val=args.views_val, views_test=args.views_test, seed=args.seed, lit=args.lit,
                         samples=args.samples, force=args.force, log=lambda m: print(m, flush=True))
    else:
        spec = load_scene_spec(args.out)
        if spec.get("name") != args.name:
            raise InputError(f"{existing} holds scene '{spec.get('name')}', not '{args.name}'; choose another --out")
    if args.format != "nerf-synthetic":
        from tools.scenes.formats import write_layout

        first = write_layout(args.out, Path(args.out) / args.format, args.format,
                             log=lambda m: print(m, flush=True))
        print(f"wrote {first}")
    return 0
