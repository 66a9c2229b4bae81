"""`pointgt render MODEL.pgt --cameras transforms.json --out DIR`: one PNG per camera.

With --points/--ids (a deformed point set, e.g. exported from a Blender rig) and/or --atlas (a painted atlas), the
frames are rendered through the edit path (core.frames.edited): neighbours and attention in deformed space, the
painted texture looked up at each ray's canonical correspondence.
"""
from __future__ import annotations

import json
import sys
import time
from pathlib import Path

NAME = "render"
HELP = ("render a model from the cameras of a transforms JSON (one RGBA PNG per camera, straight alpha), "
        "optionally posed/painted")
ORDER = 40
MAX_RENDER_SIZE = 8192  # --size: pixels per side
EMPTY_ALPHA = 0.5 / 255  # a frame whose largest coverage is at most this is empty (rounds to 0 in the PNG)


def add_arguments(p):
    from core.config import add_to_parser
    from core.edits.correspondence import MODES
    from core.edits.deformation import DeformationConfig
    from core.frames.edited import EditConfig

    p.add_argument("model", help="model file (.pgt)")
    p.add_argument("--cameras", required=True, help="transforms JSON whose cameras to render (transforms_*.json, or "
                                                   "every frame of a nerfstudio / instant-ngp transforms.json)")
    p.add_argument("--out", required=True, help="output folder for the PNGs")
    p.add_argument("--size", type=int, default=None,
                   help="image width, 1-8192; the height keeps the JSON's aspect ratio (square when the JSON "
                        "gives no size) (default: the JSON's 'w'/'h' or its images' size)")
    p.add_argument("--device", default="auto", help="cpu | cuda | auto")
    p.add_argument("--json", default=None, help="write timings and counts to this JSON file")
    p.add_argument("--points", default=None, help="deformed point positions: .npy float [M, 3]")
    p.add_argument("--ids", default=None,
                   help="canonical index of each deformed point: .npy integer [M] (needed when M != model points)")
    p.add_argument("--atlas", default=None, help="painted atlas image (PNG, same size as the model's atlas)")
    p.add_argument("--correspondence", default=EditConfig.correspondence, choices=MODES,
                   help="canonical correspondence for texture lookups of moved points: deform-gradient (undoes "
                        "each neighbour's local rotation and stretch; the default) or deform-aware / naive (the "
                        "paper's)")
    # the F-aware rendering and fold rule: one flag per EditConfig field, help from the field (the other fields
    # have their own flags above and below, or are not offered)
    add_to_parser(p, EditConfig, skip=("correspondence", "blend", "mask_threshold", "temperature", "colour",
                                       "attention", "antialias", "render_mode"))
    add_to_parser(p, DeformationConfig, prefix="deformation")
    p.add_argument("--blend", default="soft", choices=("soft", "threshold"),
                   help="texture-edit blend: soft (m*T' + (1-m)*render) or threshold (paper: m > 0.95)")
    p.add_argument("--temperature", type=float, default=None,
                   help="attention temperature (< 1 sharpens attention; default: 1, plain renders: the model's)")
    from core.points.resolution import DEFAULT_RENDER_MODE, RENDER_MODES

    p.add_argument("--render-mode", default="auto", choices=("auto", *RENDER_MODES),
                   help="frames finer than the training pixels (a larger --size, a closer camera): pixels (as at "
                        "the training size) | filtered (low-passed by a fraction of a training pixel: no point "
                        "discs) | decoder (UNet decoder at the training scale) | decoder+filtered | interior (UNet "
                        "decoder at the training scale inside the object, at the full size at its silhouette) | "
                        "interior+filtered | footprint | footprint+decoder | upsampled (the training-size frame "
                        "upsampled, a painted texture at the full size); auto = upsampled for a single-scale fit; for a "
                        f"multi-scale fit interior+filtered where its fit measured it better, else {DEFAULT_RENDER_MODE}")
    p.add_argument("--antialias", type=int, default=2,
                   help="texture lookups per pixel side, pixel-filtered (1 = one per ray, no filter)")


MAX_FILE_POINTS = 10_000_000  # points per --points/--ids file (a model holds far fewer; 200k is a large one)


def load_npy(path, what: str, kind: str):
    """Read a .npy array without unpickling. kind 'points' -> float32 [M, 3]; 'ids' -> int64 [M].
    The header (shape, dtype) is checked against the file's real size and MAX_FILE_POINTS before anything is
    allocated. Raises InputError naming the file and the problem (missing, corrupt, pickled, wrong shape/dtype)."""
    import numpy as np

    from core.util.errors import InputError

    path = Path(path)
    if not path.is_file():
        raise InputError(f"{path}: {what} file does not exist" if not path.exists() else
                         f"{path}: {what} is not a regular file (a folder or device); give a .npy file")
    with open(path, "rb") as fh:
        magic = fh.read(6)
        if magic != b"\x93NUMPY":
            raise InputError(f"{path}: {what} is not a .npy file (no NumPy header); save the array with numpy.save")
        fh.seek(0)
        try:
            version = np.lib.format.read_magic(fh)
            shape, fortran, dtype = np.lib.format._read_array_header(fh, version)
        except Exception as exc:  # numpy's header parser raises ValueError, SyntaxError, tokenize errors, ...
            raise InputError(f"{path}: {what} has a corrupt .npy header ({exc}); save it again with numpy.save") from exc
        offset = fh.tell()
    if dtype.hasobject:  # object arrays need pickle: refused, loading never runs code
        raise InputError(f"{path}: {what} holds Python objects (pickled data), which is never loaded; "
                         f"save a plain numeric array with numpy.save")
    count = int(np.prod(shape, dtype=object))
    if count > 3 * MAX_FILE_POINTS:
        raise InputError(f"{path}: {what} declares shape {list(shape)}, more than {MAX_FILE_POINTS} points; "
                         "the header is corrupt or the file is not a point set")
    expected, actual = count * dtype.itemsize, path.stat().st_size - offset
    if actual != expected:
        state = "truncated" if actual < expected else "longer than its header says"
        raise InputError(f"{path}: {what} is {state} (header: shape {list(shape)} {dtype} = {expected} bytes, file "
                         f"holds {actual}); save it again with numpy.save")
    try:
        arr = np.load(path, allow_pickle=False)
    except ValueError as exc:
        raise InputError(f"{path}: {what} is truncated or corrupt ({exc}); save it again with numpy.save") from exc
    except (OSError, EOFError) as exc:
        raise InputError(f"{path}: {what} is not a readable .npy file ({exc}); save it with numpy.save") from exc
    if kind == "points":
        if arr.ndim != 2 or arr.shape[1] != 3:
            raise InputError(f"{path}: {what} must have shape [M, 3], got {list(arr.shape)}")
        if arr.dtype.kind != "f":
            raise InputError(f"{path}: {what} must be floating point, got dtype {arr.dtype}")
        return arr.astype(np.float32)
    if arr.ndim != 1:
        raise InputError(f"{path}: {what} must have shape [M], got {list(arr.shape)}")
    if arr.dtype.kind not in "iu":
        raise InputError(f"{path}: {what} must be integers, got dtype {arr.dtype}")
    if arr.dtype.kind == "u" and arr.size and int(arr.max()) > np.iinfo(np.int64).max:
        raise InputError(f"{path}: {what} holds the id {int(arr.max())}, beyond any point index; ids are the "
                         "canonical indices 0..N-1 of the model's points")
    return arr.astype(np.int64)


def run(args) -> int:
    import numpy as np
    import torch

    from core.bundle import load_bundle
    from core.config import check_flag, from_args
    from core.frames.edited import EditConfig
    from core.points.render import straight_colour
    from core.images.dataset import load_cameras
    from core.images.png import read_png, write_png
    from core.util.atomic import atomic_write_text, check_output_dir, check_output_file
    from core.util.device import check_device
    from core.util.errors import InputError
    from core.util.progress import Progress

    # Flags and output paths first: a typo is reported before the model is read or a frame rendered.
    out = check_output_dir(args.out, "--out")
    if args.json:
        check_output_file(args.json, "--json")
    check_flag(args.size, "--size", min=1, max=MAX_RENDER_SIZE)
    cfg = from_args(EditConfig, args)  # every flag set (the temperature only when given) over the defaults
    check_device(args.device, "--device")
    bundle = load_bundle(args.model, device=args.device)
    cams = load_cameras(args.cameras, size=args.size)
    edited = args.points is not None or args.ids is not None or args.atlas is not None
    state = None
    if edited:
        from core.frames.edited import EditState

        points = load_npy(args.points, "--points", "points") if args.points else None
        ids = load_npy(args.ids, "--ids", "ids") if args.ids else None
        atlas = read_png(args.atlas) if args.atlas else None
        try:
            from core.config import from_args
            from core.edits.deformation import DeformationConfig

            state = EditState(bundle, points=points, ids=ids, atlas=atlas, cfg=cfg,
                              deformation=from_args(DeformationConfig, args, prefix="deformation"))
        except InputError as exc:  # name the files the arrays came from
            files = ", ".join(f for f in (args.points, args.ids, args.atlas) if f)
            raise InputError(f"{files}: {exc}") from exc
        given = 0 if points is None else int(points.shape[0])
        if given and state.non_finite_points >= given:
            raise InputError(f"{args.points}: every one of the {given} positions is NaN or infinite: there is "
                             "nothing to render; export the deformed points again (a broken rig or driver?)")
        if state.non_finite_points:
            print(f"warning: {state.non_finite_points} of {given} points in {args.points} are NaN or infinite; "
                  "they are left out of every frame", file=sys.stderr)
    out.mkdir(parents=True, exist_ok=True)
    times, totals, empty = [], {}, []
    with Progress(len(cams.names), "render") as bar:
        for i, name in enumerate(cams.names):
            t0 = time.perf_counter()
            if state is None:
                from core.points.render import render_frame

                res = render_frame(bundle.model, cams.c2w[i], cams.height, cams.width, cams.focal,
                                   background=(0.0, 0.0, 0.0), temperature=args.temperature,
                                   mode=args.render_mode)
            else:
                from core.frames.edited import render_edited

                res = render_edited(state, cams.c2w[i], cams.height, cams.width, cams.focal,
                                    background=(0.0, 0.0, 0.0))
                for k, v in res["stats"].items():
                    if isinstance(v, (int, float)) and k not in ("seconds", "scale"):
                        totals[k] = totals.get(k, 0) + v
            times.append(time.perf_counter() - t0)
            # Rendered over black, stored straight: viewers composite the PNG over any background themselves.
            rgba = torch.cat([straight_colour(res["rgb"], res["alpha"]), res["alpha"][..., None]], dim=-1)
            rgba = rgba.cpu().numpy()
            write_png(out / f"{name}.png", rgba)
            if not float(rgba[..., 3].max()) > EMPTY_ALPHA:
                empty.append(name)
            bar.update(1)
    summary = {"frames": len(times), "seconds_per_frame": float(np.mean(times)), "out": str(out)}
    if state is not None:
        summary.update(edited=True, correspondence=args.correspondence if state.moved else "skipped",
                       blend=args.blend, temperature=cfg.temperature, textured=state.textured,
                       points=int(state.points.shape[0]), non_finite_points=state.non_finite_points,
                       non_finite_lookups_repaired=int(totals.get("non_finite_lookups_repaired", 0)),
                       rays=int(totals.get("rays", 0)), rays_shaded=int(totals.get("rays_shaded", 0)),
                       texture_rays=int(totals.get("texture_rays", 0)))
    summary["empty_frames"] = len(empty)
    print(f"rendered {len(times)} frames to {out} ({summary['seconds_per_frame']:.3f} s/frame)")
    if args.json:
        atomic_write_text(args.json, json.dumps(summary, indent=1))
    if empty and len(empty) == len(times):
        causes = [f"the cameras of {args.cameras} do not see the object (check that they belong to this model's "
                  "scene: its units and orientation)"]
        if args.points:
            causes.append(f"the points of {args.points} are not in the model's space")
        if args.temperature is not None:
            causes.append(f"--temperature {args.temperature} hands every ray to the background")
        raise InputError(f"every frame in {out} is empty (no pixel covers the object): " + "; or ".join(causes)
                         + ". A model that renders nothing from its own training cameras did not fit: run "
                         "`pointgt fit` again")
    if empty:
        shown = ", ".join(empty[:5]) + (", ..." if len(empty) > 5 else "")
        print(f"warning: {len(empty)} of {len(times)} frames are empty (no pixel covers the object): {shown}",
              file=sys.stderr)
    return 0
