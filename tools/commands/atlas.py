"""`pointgt atlas MODEL.pgt DATA`: refit stage 2 (UV atlas + texture) of an existing model."""
from __future__ import annotations

NAME = "atlas"
HELP = "refit the UV atlas and texture (stage 2) of a model from its training images"
ORDER = 25


def add_arguments(p):
    from core.atlas.config import AtlasConfig
    from core.config import add_to_parser
    from tools.commands import add_model_and_data

    add_model_and_data(p, "model file (.pgt); rewritten in place, the previous version kept as .bak",
                       "the dataset the model was trained on (any layout of docs/formats.md)")
    p.add_argument("--no-progress", action="store_true", help="no progress bar")
    p.add_argument("--texel-map-only", action="store_true",
                   help="keep charts and texture; only recompute the texel->surface map with the current rules "
                        "(seconds; for models made before the forward-splat texel map)")
    from core.images.dataset import LoadConfig

    add_to_parser(p, LoadConfig)
    add_to_parser(p, AtlasConfig, prefix="atlas")


def run(args) -> int:
    from pathlib import Path

    from core.atlas.config import AtlasConfig
    from core.bundle import load_bundle, save_bundle
    from core.config import from_args, to_dict
    from core.frames.report import write_history
    from core.images.dataset import load_split
    from core.pipeline import fit_atlas_stage, refresh_texel_map, stage_time_text

    from core.config import check_flag
    from core.util.atomic import check_output_file
    from core.util.device import check_device

    check_output_file(args.model, "MODEL")  # rewritten in place at the end: checked before the work
    check_output_file(Path(args.model).with_suffix(".atlas_history.json"), "MODEL (atlas history)")
    check_flag(args.downscale, "--downscale", min=1, max=64)
    cfg = from_args(AtlasConfig, args, prefix="atlas")
    from core.images.dataset import LoadConfig

    load_kw = from_args(LoadConfig, args).loader_kwargs()
    check_device(cfg.device, "--atlas-device")
    bundle = load_bundle(args.model, device=cfg.device)
    train = load_split(args.data, "train", downscale=args.downscale, progress=not args.no_progress, **load_kw)
    if args.texel_map_only:
        info = refresh_texel_map(bundle, train, cfg)
        save_bundle(args.model, bundle)
        miss = (f"; t_c sends a texel's point {info['miss_median']:.2f} texels from the texel (median), "
                f"{info['miss_p90']:.2f} (p90)") if "miss_median" in info else ""
        print(f"texel map ({cfg.texel_map}): {info['valid_texels']} texels with a surface point, from "
              f"{info['samples']} samples in {info['seconds']:.1f} s{miss}; {len(bundle.atlas.bake_samples)} samples "
              f"kept for baking -> {args.model} (previous version: .bak)")
        return 0
    try:
        hist = fit_atlas_stage(bundle, train, cfg, show_progress=not args.no_progress)
    except KeyboardInterrupt:
        raise KeyboardInterrupt(f"nothing was saved; {args.model} is unchanged") from None
    save_bundle(args.model, bundle)
    write_history(Path(args.model).with_suffix(".atlas_history.json"), [], {"atlas": hist, "config": to_dict(cfg)})
    print(f"stage 2: {hist['n']} charts from {hist['samples']} samples in {stage_time_text(hist)} "
          f"(fitting PSNR {hist['psnr'][-1]:.2f} dB) -> {args.model}")
    return 0
