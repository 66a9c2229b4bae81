"""Dataset loader: the transforms-JSON layouts that NeRF tools write.

Four layouts, told apart by their files and keys (docs/formats.md lists every key):

    NeRF-synthetic   <root>/transforms_{train,val,test}.json  {"camera_angle_x", "frames": [{"file_path":
                     "./train/r_0", "transform_matrix": 4x4 c2w}]}, RGBA PNGs (alpha = object mask)
    BlenderNeRF      the same split files, plus fl_x/fl_y/cx/cy/w/h/camera_angle_y, and file_path with its extension
    nerfstudio       <root>/transforms.json (one file, no split): fl_x, fl_y, cx, cy, w, h, camera_model,
                     distortion k1-k3/p1/p2 (undistorted on load) — at the top or per frame —, mask_path,
                     applied_transform, images/ with downscaled copies images_2/, images_4/, ...
    instant-ngp      <root>/transforms.json or split files: camera_angle_x/y or fl_x/fl_y, cx, cy, w, h,
                     aabb_scale, intrinsics per frame allowed

`transform_matrix` is camera-to-world in the Blender/OpenGL convention (camera looks down -Z, +Y up; see
core/images/cameras.py) in all four. A single transforms.json is split deterministically into train and test:
explicit `train_filenames` / `test_filenames` lists when present, else every `test_every`-th frame (in file_path
order) is a test view. A split has one pinhole camera: frames with their own intrinsics, size or lens distortion
are resampled onto the camera most frames of the file share (core/images/resample.py). Every problem found on
disk raises a DataError naming the file (and frame, and key) and saying how to fix it.
"""
from __future__ import annotations

import json
import math
import os
import re
import sys
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import torch

from core.config import opt
from core.images.cameras import Intrinsics, focal_from_fov, simplest
from core.images.png import read_png
from core.util.errors import DataError, InputError

SPLITS = ("train", "val", "test")
SINGLE_FILE = "transforms.json"
# NeRF-synthetic ships depth and normal renders next to the test images (r_0_depth_0000.png); they are not frames.
_AUXILIARY = re.compile(r"_(depth|normal)(_\d+)?$", re.IGNORECASE)
RIGID_TOL = 1e-3  # max |R^T R - I| entry and |last row - [0,0,0,1]|; NeRF-synthetic matrices are exact to ~1e-7
MAX_CAMERA_DISTANCE = 1e15  # |camera position| per axis: float32 cameras (and their products) stay finite
DISTORTION_KEYS = ("k1", "k2", "k3", "k4", "p1", "p2")
CAMERA_MODELS = ("PINHOLE", "SIMPLE_PINHOLE", "OPENCV")  # OPENCV's k1, k2, k3, p1, p2: undistorted on load
INTRINSIC_KEYS = ("fl_x", "fl_y", "cx", "cy", "w", "h", "camera_angle_x", "camera_angle_y", "camera_model",
                  "is_fisheye") + DISTORTION_KEYS
KEY_TOLERANCE = 0.04  # --background-colour: a pixel within this (max over channels) of the key is background
MIN_COVERAGE = 0.5  # a frame resampled onto the split's camera must see at least this share of its view


@dataclass
class LoadConfig:
    """Reading a dataset: the train/test split of a single transforms.json and images without alpha."""
    test_every: int = opt(8, "a single transforms.json (nerfstudio, instant-ngp) without train_filenames/"
                             "test_filenames: every N-th frame in file_path order is a test view", min=2, max=10_000)
    background_colour: str = opt("", "R,G,B of a studio backdrop (0-1 or 0-255): images without alpha or "
                                     "mask_path are keyed on it; empty = such images are refused")

    def loader_kwargs(self) -> dict:
        """Keyword arguments of load_split / load_dataset."""
        key = parse_colour(self.background_colour) if self.background_colour.strip() else None
        return {"test_every": self.test_every, "background_colour": key}


@dataclass
class SplitData:
    """One split, ready for training/evaluation.

    images [V, H, W, 3] float32 in [0, 1], composited onto `background`; alphas [V, H, W] float32 (the PNG's alpha,
    the frames' masks, or the keyed background colour); c2w [V, 4, 4] float32 camera-to-world; focal: what the
    pipeline takes — a float (pixels, at this downscaled size) for the centred square-pixel camera, else the
    `Intrinsics` (fx, fy, cx, cy); `intrinsics` always holds the Intrinsics. layout: which layout was read.
    """
    split: str
    images: torch.Tensor
    alphas: torch.Tensor
    c2w: torch.Tensor
    focal: float | Intrinsics
    height: int
    width: int
    camera_angle_x: float
    files: list[Path]
    intrinsics: Intrinsics | None = None
    layout: str = "nerf-synthetic"
    meta: dict = field(default_factory=dict)

    def __post_init__(self):
        if self.intrinsics is None:
            f = self.focal
            self.intrinsics = f if isinstance(f, Intrinsics) else \
                Intrinsics(float(f), float(f), 0.5 * self.width, 0.5 * self.height)

    def __len__(self) -> int:
        return len(self.files)


def transforms_path(root: str | os.PathLike, split: str) -> Path:
    """The JSON holding `split`: transforms_<split>.json, or the single transforms.json when the folder has no
    split files (nerfstudio, instant-ngp)."""
    root = Path(root)
    own = root / f"transforms_{split}.json"
    if not own.exists() and (root / SINGLE_FILE).is_file() and not any(root.glob("transforms_*.json")):
        return root / SINGLE_FILE
    return own


def load_dataset(root: str | os.PathLike, splits=SPLITS, required=("train",), downscale: int = 1,
                 background=(1.0, 1.0, 1.0), check_extra_files: bool = True, test_every: int = 8,
                 background_colour=None, progress: bool = False) -> dict[str, SplitData]:
    """Load several splits. Splits listed in `required` must exist; the others are skipped when their JSON is
    absent (a present but broken one still raises). A single transforms.json holds train and test (no val).
    Returns {split: SplitData}; the other arguments as load_split."""
    root = _check_root(root)
    missing_required = [s for s in required if s not in splits]
    if missing_required:
        raise InputError(f"required splits {missing_required} are not among the requested splits {list(splits)}")
    out = {}
    for split in splits:
        path = transforms_path(root, split)
        if split not in required and (not path.exists() or (path.name == SINGLE_FILE and split not in
                                                            ("train", "test") and not _names_split(path, split))):
            continue
        out[split] = load_split(root, split, downscale=downscale, background=background,
                                check_extra_files=check_extra_files, test_every=test_every,
                                background_colour=background_colour, progress=progress)
    return out


def _names_split(json_path: Path, split: str) -> bool:
    """Whether a single transforms.json names the images of `split` (<split>_filenames); False when unreadable
    (the error is reported when a required split is loaded)."""
    try:
        return f"{split}_filenames" in json.loads(json_path.read_text(encoding="utf-8"))
    except (OSError, ValueError, TypeError, RecursionError):
        return False


def load_split(root: str | os.PathLike, split: str = "train", downscale: int = 1, background=(1.0, 1.0, 1.0),
               check_extra_files: bool = True, test_every: int = 8, background_colour=None,
               progress: bool = False) -> SplitData:
    """Load one split: images [V, H, W, 3], alphas [V, H, W], c2w [V, 4, 4] (see SplitData).

    downscale: integer factor. Downscaled copies (images_<d>/, masks_<d>/ next to images/, masks/) are used when
    every frame has one; otherwise pixels are area-averaged with premultiplied alpha (no dark fringes at edges).
    Intrinsics are scaled to match.
    background: RGB in [0, 1] that transparent pixels are composited onto: rgb * a + bg * (1 - a).
    check_extra_files: reject PNGs in the split folders that no frame references (depth/normal renders excepted;
    split-file layouts only: a capture's images/ folder may hold photos the camera solver dropped).
    test_every: a single transforms.json without train_filenames/test_filenames puts every N-th frame (sorted by
    file_path, starting with the first) into test and the rest into train.
    background_colour: RGB in [0, 1] of a studio backdrop; images without alpha or masks are keyed on it
    (pixels within KEY_TOLERANCE of it become transparent). Without it such images are refused.
    progress: print the memory estimate and a progress bar while loading (stderr).
    """
    root = _check_root(root)
    bg = _check_background(background)
    key = None if background_colour is None else _check_background(background_colour, "--background-colour")
    if isinstance(downscale, bool) or not isinstance(downscale, (int, np.integer)) or downscale < 1:
        raise InputError(f"downscale must be a positive integer, got {downscale!r}")
    if isinstance(test_every, bool) or not isinstance(test_every, (int, np.integer)) or test_every < 2:
        raise InputError(f"--test-every must be an integer of at least 2, got {test_every!r}")
    json_path = transforms_path(root, split)
    doc = _read_json(json_path, root)
    frames = _split_frames(doc, json_path, split, int(test_every))
    files, c2w = _frames(frames, json_path, root)
    layout = _layout(doc, json_path)
    if check_extra_files and json_path.name != SINGLE_FILE:
        _check_no_extra_files(root, json_path, files)
    masks = _mask_files(frames, json_path, root)
    _check_applied_transform(doc, json_path)
    _check_aabb_scale(doc, json_path)

    # Downscaled copies: used when every frame (and mask) has one.
    factor = int(downscale)
    copies = _downscaled(files, "images", factor) if factor > 1 else None
    mask_copies = _downscaled(masks, "masks", factor) if factor > 1 and masks is not None else None
    use_copies = copies is not None and (masks is None or mask_copies is not None)
    read_files = copies if use_copies else files
    read_masks = (mask_copies if use_copies else masks)
    sizes = [_image_size(f) for f in files]  # (h, w) at full size: the keys describe it
    _check_key_presence(frames, doc, json_path)
    specs = [_frame_camera(doc, fr, json_path, i, files[i], sizes[i][1], sizes[i][0]) for i, fr in enumerate(frames)]
    for spec, (fh, fw) in zip(specs, sizes):
        _check_plausible(spec, json_path, fw, fh)
    spec, height, width = _reference_camera(doc, json_path, root, {id(fr): (sp, sz) for fr, sp, sz in
                                                                   zip(frames, specs, sizes)})
    full_k = _intrinsics(spec, width, height, 1)
    for i, (fr, sp, sz) in enumerate(zip(frames, specs, sizes)):  # another size needs the frame's keys to say so
        if sz != (height, width) and sp == spec and not ("w" in fr or "h" in fr):
            j = next((j for j, z in enumerate(sizes) if z == (height, width)), None)
            other = f"{files[j].name} is" if j is not None else "the split's camera is"
            raise DataError(f"{files[i]}: image is {sz[1]}x{sz[0]} but {other} {width}x{height}; all images of "
                            f"{json_path.name} must have one size, unless a frame gives its own 'w', 'h' (and "
                            "intrinsics): resize the image or add those keys to its frame")
    # Frames with their own camera are resampled onto the reference camera (core/images/resample.py).
    own = [sp != spec or sz != (height, width) or sp["distortion"] is not None for sp, sz in zip(specs, sizes)]
    if use_copies:
        read_sizes = [_image_size(f) for f in read_files]
        kept = [sz for sz, o in zip(read_sizes, own) if not o]
        h, w = kept[0] if kept else (height // factor, width // factor)
        for i, ((ch, cw), (fh, fw)) in enumerate(zip(read_sizes, sizes)):
            if abs(cw * factor - fw) >= factor or abs(ch * factor - fh) >= factor or (not own[i] and (ch, cw) != (h, w)):
                raise DataError(f"{read_files[i]}: downscaled copy is {cw}x{ch}, but {files[i].name} is {fw}x{fh} "
                                f"(expected about {fw / factor:g}x{fh / factor:g} for --downscale {factor}); "
                                f"regenerate the {read_files[i].parent.name}/ folder")
        block = 1
        scale = 1.0 / factor
    else:
        if height % factor or width % factor:
            divisors = [d for d in range(2, 17) if height % d == 0 and width % d == 0]
            raise DataError(f"{json_path}: images are {width}x{height}, which downscale={factor} does not divide; "
                            f"use one of {divisors or [1]}")
        h, w, block = height // factor, width // factor, factor
        read_sizes, scale = sizes, 1.0
    k = _intrinsics(spec, width, height, factor)
    warps = [(_intrinsics(sp, sz[1], sz[0], 1).scaled(scale), full_k.scaled(scale), (h * block, w * block),
              _distortion(sp)) if o else None for sp, sz, o in zip(specs, sizes, own)]

    coverage = [1.0] * len(files)
    images, alpha = _read_images(read_files, json_path, read_masks, key, block, (h, w), progress,
                                 read_sizes=read_sizes, warps=warps, coverage=coverage)
    images += (1.0 - alpha[..., None]) * bg  # composite: rgb * a + bg * (1 - a)
    np.clip(images, 0.0, 1.0, out=images)
    meta = {"json": str(json_path), "downscaled_copies": bool(use_copies)}
    if any(own):
        meta["resampled"] = {"frames": int(sum(own)), "min_coverage": round(min(coverage), 4),
                             "undistorted": sum(sp["distortion"] is not None for sp in specs)}
    if "aabb_scale" in doc:
        meta["aabb_scale"] = doc["aabb_scale"]
    return SplitData(split=split,
                     images=torch.from_numpy(images),
                     alphas=torch.from_numpy(alpha),
                     c2w=torch.from_numpy(c2w.astype(np.float32)),
                     focal=simplest(k, h, w), height=h, width=w,
                     camera_angle_x=spec["camera_angle_x"] or 2.0 * math.atan(0.5 * (width / factor) / k.fx),
                     files=files, intrinsics=k, layout=layout,
                     meta=meta)


def _area_mean(x: np.ndarray, d: int) -> np.ndarray:
    """Average d x d blocks: x [V, H, W, C] -> [V, H/d, W/d, C]."""
    v, h, w, c = x.shape
    return x.reshape(v, h // d, d, w // d, d, c).mean(axis=(2, 4), dtype=np.float32)


def _check_root(root) -> Path:
    root = Path(root)
    if not root.is_dir():
        raise DataError(f"{root}: dataset folder not found; pass the folder that holds transforms_train.json")
    return root


def _check_background(background, flag: str = "background") -> np.ndarray:
    bg = np.asarray(background, dtype=np.float32)
    if bg.shape != (3,) or not np.all(np.isfinite(bg)) or bg.min() < 0 or bg.max() > 1:
        raise InputError(f"{flag} must be three numbers in [0, 1] (RGB), got {background!r}")
    return bg


def parse_colour(text: str, flag: str = "--background-colour") -> tuple[float, float, float]:
    """'R,G,B' with components in [0, 1] (or 0-255 integers when any exceeds 1) -> (r, g, b) in [0, 1]."""
    try:
        vals = [float(v) for v in str(text).split(",")]
    except ValueError as exc:
        raise InputError(f"{flag} must be R,G,B (e.g. 1,1,1 or 255,255,255), got {text!r}") from exc
    if len(vals) != 3 or not all(math.isfinite(v) and v >= 0 for v in vals):
        raise InputError(f"{flag} must be three non-negative numbers R,G,B, got {text!r}")
    if max(vals) > 1:
        if max(vals) > 255:
            raise InputError(f"{flag}: components are in [0, 1] or 0-255, got {text!r}")
        vals = [v / 255.0 for v in vals]
    return tuple(vals)


def _read_json(json_path: Path, root: Path) -> dict:
    if not json_path.is_file():
        present = sorted(p.name for p in root.glob("transforms*.json"))
        hint = f"the folder has {present}" if present else "the folder has no transforms*.json at all"
        raise DataError(f"{json_path}: split file not found ({hint}); point to a dataset folder with "
                        "transforms_train.json (NeRF-synthetic, BlenderNeRF) or transforms.json (nerfstudio, "
                        "instant-ngp)")
    try:
        doc = json.loads(json_path.read_text(encoding="utf-8"))
    except UnicodeDecodeError as exc:
        raise DataError(f"{json_path}: not UTF-8 text ({exc}); is this really a transforms JSON file?") from exc
    except json.JSONDecodeError as exc:
        raise DataError(f"{json_path}: invalid JSON at line {exc.lineno}, column {exc.colno}: {exc.msg}; "
                        "fix the syntax (a JSON validator shows the spot)") from exc
    except RecursionError as exc:
        raise DataError(f"{json_path}: JSON nested too deeply to be a transforms file") from exc
    except OSError as exc:
        raise DataError(f"{json_path}: cannot be read ({exc})") from exc
    if not isinstance(doc, dict):
        raise DataError(f"{json_path}: expected a JSON object with 'camera_angle_x' and 'frames', "
                        f"got a {type(doc).__name__}")
    return doc


def _layout(doc: dict, json_path: Path) -> str:
    """Which tool's layout this is (reported, and used in messages; the keys decide how frames are read)."""
    if json_path.name == SINGLE_FILE:
        if "camera_model" in doc or "applied_transform" in doc:
            return "nerfstudio"
        masked = any(isinstance(f, dict) and "mask_path" in f for f in doc.get("frames") or [])
        return "nerfstudio" if masked and "aabb_scale" not in doc else "instant-ngp"
    if "aabb_scale" in doc and "fl_x" not in doc:
        return "instant-ngp"
    return "blendernerf" if "fl_x" in doc or "w" in doc else "nerf-synthetic"


def _split_frames(doc: dict, json_path: Path, split: str, test_every: int) -> list:
    """The frames of `split`: all of a transforms_<split>.json; for a single transforms.json the frames named by
    `<split>_filenames`, else every `test_every`-th frame in file_path order (test) or the others (train)."""
    frames = doc.get("frames")
    if not isinstance(frames, list):
        raise DataError(f"{json_path}: missing 'frames' list; add one entry per image "
                        "({'file_path': ..., 'transform_matrix': ...})")
    if not frames:
        raise DataError(f"{json_path}: 'frames' is empty; a split needs at least one image")
    if json_path.name != SINGLE_FILE:
        return frames
    for i, frame in enumerate(frames):
        if not isinstance(frame, dict) or not isinstance(frame.get("file_path"), str):
            raise DataError(f"{json_path}: frame {i} needs a 'file_path' string (and a 'transform_matrix')")
    names_key = f"{split}_filenames"
    if names_key in doc:
        wanted = doc[names_key]
        if not isinstance(wanted, list) or not all(isinstance(n, str) for n in wanted):
            raise DataError(f"{json_path}: '{names_key}' must be a list of file_path strings")
        by_path = {os.path.normpath(f["file_path"]): f for f in frames}
        missing = [n for n in wanted if os.path.normpath(n) not in by_path]
        if missing:
            raise DataError(f"{json_path}: '{names_key}' names {len(missing)} image(s) no frame has, e.g. "
                            f"{missing[0]!r}; list file_path values of 'frames'")
        out = [by_path[os.path.normpath(n)] for n in wanted]
    elif any(f"{s}_filenames" in doc for s in SPLITS):
        raise DataError(f"{json_path}: has {[f'{s}_filenames' for s in SPLITS if f'{s}_filenames' in doc]} but "
                        f"no '{names_key}'; list the {split} images too, or remove the lists to split every "
                        f"--test-every frames")
    elif split in ("train", "test"):
        ordered = sorted(frames, key=lambda f: f["file_path"])
        out = [f for i, f in enumerate(ordered) if (i % test_every == 0) == (split == "test")]
    else:
        raise DataError(f"{json_path}: a single transforms.json splits into 'train' and 'test' only, not "
                        f"'{split}' (add '{names_key}' to name its images)")
    if not out:
        raise DataError(f"{json_path}: the {split} split is empty ({len(frames)} frames, --test-every "
                        f"{test_every}); add frames or lower --test-every")
    return out


def _frames(frames: list, json_path: Path, root: Path) -> tuple[list[Path], np.ndarray]:
    """Image paths and c2w [V, 4, 4] float64 of the frames, validated."""
    files, mats, seen = [], [], {}
    for i, frame in enumerate(frames):
        where = f"{json_path}: frame {i}"
        if not isinstance(frame, dict):
            raise DataError(f"{where} is a {type(frame).__name__}, expected an object with 'file_path' and "
                            "'transform_matrix'")
        for key in ("file_path", "transform_matrix"):
            if key not in frame:
                raise DataError(f"{where} has no '{key}'; every frame needs 'file_path' and 'transform_matrix'")
        if not isinstance(frame["file_path"], str) or not frame["file_path"].strip():
            raise DataError(f"{where}: 'file_path' must be a non-empty string, got {frame['file_path']!r}")
        path = _image_path(root, frame["file_path"], where)
        key = os.path.normcase(os.path.abspath(path))
        if key in seen:
            raise DataError(f"{where} uses the same image as frame {seen[key]} ({path}); remove the duplicate frame")
        seen[key] = i
        files.append(path)
        mats.append(_frame_matrix(frame, f"{where} ({path.name})"))
    c2w = np.stack(mats)
    _check_rigid(c2w, files, json_path)
    return files, c2w


def _number(value, json_path: Path, where: str, key: str, positive: bool = False) -> float:
    if isinstance(value, bool) or not isinstance(value, (int, float)) or not math.isfinite(value) \
            or (positive and value <= 0):
        need = "a finite positive number" if positive else "a finite number"
        raise DataError(f"{json_path}: {where}'{key}' must be {need}, got {value!r}")
    return float(value)


def _frame_camera(doc: dict, frame: dict, json_path: Path, i: int, file: Path, width: int, height: int) -> dict:
    """The camera keys of frame i (its own, else the file's), checked: {fl_x, fl_y, cx, cy, camera_angle_x,
    camera_angle_y} (None when absent) and distortion ((k1, k2, k3, p1, p2), None when all are zero) for a
    `width` x `height` image. Fisheye and other non-pinhole models, and k4, are refused."""
    def get(key):
        if key in frame:
            return frame[key], f"frame {i} ({file.name}): "
        return doc.get(key), ""

    model, where = get("camera_model")
    if model is not None and model not in CAMERA_MODELS:
        kind = "a fisheye lens" if isinstance(model, str) and "FISHEYE" in model.upper() else "not a model PointGT reads"
        raise DataError(f"{json_path}: {where}'camera_model' is {model!r}, {kind}; PointGT reads pinhole cameras "
                        f"({', '.join(CAMERA_MODELS)}; OPENCV's k1, k2, k3, p1, p2 are undistorted as the images "
                        "are read): undistort the images to a pinhole camera first (e.g. COLMAP's "
                        "image_undistorter, then ns-process-data with --camera-type perspective)")
    fisheye, where = get("is_fisheye")
    if fisheye:
        raise DataError(f"{json_path}: {where}'is_fisheye' is true; PointGT does not undistort fisheye lenses: "
                        "undistort the images to a pinhole camera first (e.g. COLMAP's image_undistorter)")
    coefficients = []
    for key in DISTORTION_KEYS:
        value, where = get(key)
        value = 0.0 if value is None else _number(value, json_path, where, key)
        if key == "k4" and value != 0.0:
            raise DataError(f"{json_path}: {where}'k4' = {value!r}: k4 belongs to the fisheye (OPENCV_FISHEYE) and "
                            "rational (FULL_OPENCV) lens models, which PointGT does not undistort; undistort the "
                            "images first (COLMAP image_undistorter) and write pinhole intrinsics")
        if key != "k4":
            coefficients.append(value)
    out = {"distortion": tuple(coefficients) if any(coefficients) else None}
    for key in ("w", "h"):
        value, where = get(key)
        if value is not None:
            size = width if key == "w" else height
            if _number(value, json_path, where, key, positive=True) != size:
                raise DataError(f"{json_path}: {where}'{key}' is {value!r} but {file.name} is {width}x{height}; "
                                f"fix '{key}' or the image")
    for key in ("fl_x", "fl_y", "cx", "cy", "camera_angle_x", "camera_angle_y"):
        value, where = get(key)
        if value is None:
            out[key] = None
        elif key.startswith("camera_angle"):
            if isinstance(value, bool) or not isinstance(value, (int, float)) or not math.isfinite(value) \
                    or not 0.0 < value < math.pi:
                raise DataError(f"{json_path}: {where}'{key}' must be a finite field of view in radians strictly "
                                f"between 0 and pi, got {value!r} (degrees? convert with math.radians)")
            out[key] = float(value)
        else:
            out[key] = _number(value, json_path, where, key, positive=key.startswith("fl_"))
    if out["fl_x"] is None and out["camera_angle_x"] is None:
        raise DataError(f"{json_path}: frame {i} ({file.name}) has no horizontal intrinsics: missing "
                        "'camera_angle_x' (field of view in radians) and 'fl_x' (focal length in pixels); add "
                        "one at the top of the file or in every frame")
    if out["distortion"] is not None and width > 0 and height > 0:
        from core.images.resample import Distortion

        k = _intrinsics(out, width, height, 1)
        reach = max(math.hypot((x - k.cx) / k.fx, (y - k.cy) / k.fy) for x in (0, width) for y in (0, height))
        if Distortion(*out["distortion"]).folds(reach):
            raise DataError(f"{json_path}: frame {i} ({file.name}): the distortion k1, k2, k3, p1, p2 = "
                            f"{list(out['distortion'])} folds the image over inside the frame (the radial scale "
                            "stops growing before the corners), so it cannot be undone; check the coefficients "
                            "(they act on normalised coordinates, as COLMAP's OPENCV model writes them)")
    return out


def _check_key_presence(frames: list, doc: dict, json_path: Path, keys=INTRINSIC_KEYS + ("mask_path",)) -> None:
    """A key that is absent at the top of the file must be in every frame or in none."""
    for key in keys:
        if key in doc or key == "mask_path":
            continue
        has = [isinstance(f, dict) and key in f for f in frames]
        if any(has) and not all(has):
            i = has.index(False)
            raise DataError(f"{json_path}: frame {i} has no '{key}', but other frames do and the file has none at "
                            f"the top; give '{key}' in every frame or once at the top of the file")


FOCAL_RANGE = (1e-3, 1e5)  # focal lengths in units of the larger image side: fields of view ~180° to ~0.0006°
CENTRE_RANGE = 10.0  # the principal point may lie this many image sizes outside the image


def _check_plausible(spec: dict, json_path: Path, width: int, height: int) -> None:
    """Intrinsics in pixels far outside any real camera (a unit mix-up: metres, millimetres, normalised) are
    refused before they turn into rays of overflowing size."""
    side = max(width, height)
    for key in ("fl_x", "fl_y"):
        v = spec[key]
        if v is not None and not FOCAL_RANGE[0] * side <= v <= FOCAL_RANGE[1] * side:
            raise DataError(f"{json_path}: '{key}' = {v:g} pixels is implausible for {width}x{height} images "
                            f"(expected {FOCAL_RANGE[0] * side:g} to {FOCAL_RANGE[1] * side:g}); focal lengths "
                            "are in pixels (fl_x = 0.5 * w / tan(0.5 * camera_angle_x)), not mm or normalised")
    for key, size in (("cx", width), ("cy", height)):
        v = spec[key]
        if v is not None and not -CENTRE_RANGE * size <= v <= (1 + CENTRE_RANGE) * size:
            raise DataError(f"{json_path}: '{key}' = {v:g} pixels lies far outside the {width}x{height} image; the "
                            "principal point is in pixels from the top-left corner (about w/2, h/2)")


def _reference_camera(doc: dict, json_path: Path, root: Path, known: dict) -> tuple[dict, int, int]:
    """The split's one camera: (spec, height, width) that most frames of the file share (ties: the earliest frame).
    Frames with other intrinsics or another image size are resampled onto it by the loader. known maps id(frame)
    -> (spec, (h, w)) for frames already read; the file's other frames (other splits of a single transforms.json)
    are sized from their 'w'/'h' keys or image header, and skipped when neither is readable."""
    specs, sizes = [], []
    for i, frame in enumerate(doc["frames"]):
        if id(frame) in known:
            spec, size = known[id(frame)]
        else:
            try:
                size = _key_size(doc, frame)
                if size is None:
                    size = _image_size(_image_path(root, frame["file_path"], f"{json_path}: frame {i}"))
            except (DataError, KeyError, TypeError):
                continue
            spec = _frame_camera(doc, frame, json_path, i, Path(str(frame.get("file_path"))), size[1], size[0])
        specs.append(spec)
        sizes.append(tuple(size))
    return _majority(specs, sizes)


def _majority(specs: list[dict], sizes: list[tuple]) -> tuple[dict, int, int]:
    """(spec, h, w) of the camera most frames share (ties: the earliest frame)."""
    votes: dict = {}
    for i, (spec, size) in enumerate(zip(specs, sizes)):
        key = (tuple(sorted(spec.items())), size)
        count, first, item = votes.get(key, (0, i, (spec, *size)))
        votes[key] = (count + 1, first, item)
    return max(votes.values(), key=lambda v: (v[0], -v[1]))[2]


def _distortion(spec: dict):
    """The frame's lens distortion (core.images.resample.Distortion) or None."""
    if spec["distortion"] is None:
        return None
    from core.images.resample import Distortion

    return Distortion(*spec["distortion"])


def _key_size(doc: dict, frame: dict) -> tuple[int, int] | None:
    """(h, w) from a frame's 'w'/'h' keys (its own, else the file's), or None when they are absent or invalid."""
    w, h = frame.get("w", doc.get("w")), frame.get("h", doc.get("h"))
    if all(isinstance(v, (int, float)) and not isinstance(v, bool) and math.isfinite(v) and v >= 1
           and float(v).is_integer() for v in (w, h)):
        return int(h), int(w)
    return None


def _intrinsics(spec: dict, width: int, height: int, factor: int) -> Intrinsics:
    """Intrinsics at 1/factor of the `width` x `height` images the keys describe. Fields of view are turned into
    focal lengths at the final size (so NeRF-synthetic gives exactly focal_from_fov(W / factor, angle))."""
    w, h = width / factor, height / factor
    fx = spec["fl_x"] / factor if spec["fl_x"] is not None else focal_from_fov(w, spec["camera_angle_x"])
    if spec["fl_y"] is not None:
        fy = spec["fl_y"] / factor
    elif spec["camera_angle_y"] is not None:
        fy = focal_from_fov(h, spec["camera_angle_y"])
    else:
        fy = fx
    cx = spec["cx"] / factor if spec["cx"] is not None else 0.5 * w
    cy = spec["cy"] / factor if spec["cy"] is not None else 0.5 * h
    return Intrinsics(fx, fy, cx, cy)


def _mask_files(frames: list, json_path: Path, root: Path) -> list[Path] | None:
    """The frames' mask_path files (all frames or none), or None."""
    has = [isinstance(f, dict) and "mask_path" in f for f in frames]
    if not any(has):
        return None
    if not all(has):
        i, j = has.index(False), has.index(True)
        raise DataError(f"{json_path}: frame {j} has a 'mask_path' but frame {i} has none; give every frame a "
                        "'mask_path' or remove them all")
    out = []
    for i, frame in enumerate(frames):
        mp = frame["mask_path"]
        if not isinstance(mp, str) or not mp.strip():
            raise DataError(f"{json_path}: frame {i}: 'mask_path' must be a non-empty string, got {mp!r}")
        out.append(_image_path(root, mp, f"{json_path}: frame {i} ('mask_path')"))
    return out


def _check_applied_transform(doc: dict, json_path: Path) -> None:
    """nerfstudio's applied_transform (3x4 or 4x4) records the world change already applied to every
    transform_matrix (COLMAP -> nerfstudio axes); the frames are used as they are, so it only has to be valid."""
    if "applied_transform" not in doc:
        return
    try:
        m = np.asarray(doc["applied_transform"], dtype=np.float64)
    except (TypeError, ValueError) as exc:
        raise DataError(f"{json_path}: 'applied_transform' must be a 3x4 or 4x4 list of numbers ({exc})") from exc
    if m.shape not in ((3, 4), (4, 4)) or not np.isfinite(m).all():
        raise DataError(f"{json_path}: 'applied_transform' must be a finite 3x4 or 4x4 matrix, got shape "
                        f"{m.shape}")


def _check_aabb_scale(doc: dict, json_path: Path) -> None:
    """instant-ngp's aabb_scale: a power of two from 1 to 128 (the size of its scene box; PointGT's points find
    their own extent, so it is only checked and reported)."""
    if "aabb_scale" not in doc:
        return
    v = doc["aabb_scale"]
    if isinstance(v, bool) or not isinstance(v, (int, float)) or v not in (1, 2, 4, 8, 16, 32, 64, 128):
        raise DataError(f"{json_path}: 'aabb_scale' must be a power of two from 1 to 128, got {v!r}")


def _downscaled(files: list[Path], folder: str, factor: int) -> list[Path] | None:
    """The `<folder>_<factor>/` copies of `files` (nerfstudio: images/x.png -> images_2/x.png, the innermost
    path component named `folder` replaced), or None unless every one exists."""
    out = []
    for f in files:
        parts = list(f.parts)
        idx = [j for j, p in enumerate(parts[:-1]) if p == folder]
        if not idx:
            return None
        parts[idx[-1]] = f"{folder}_{factor}"
        copy = Path(*parts)
        if not copy.is_file():
            return None
        out.append(copy)
    return out


def _image_size(path: Path) -> tuple[int, int]:
    """(height, width) from the image header, without decoding the pixels."""
    from PIL import Image, UnidentifiedImageError

    try:
        with Image.open(path) as img:
            w, h = img.size
    except FileNotFoundError as exc:
        raise DataError(f"{path}: image does not exist; check the frame's file_path") from exc
    except (UnidentifiedImageError, OSError, SyntaxError, ValueError) as exc:
        raise DataError(f"{path}: not a readable image ({exc}); re-export it as PNG or JPEG") from exc
    return h, w


def _frame_matrix(frame: dict, where: str) -> np.ndarray:
    """A frame's 'transform_matrix' as float64 [4, 4]; `where` names the frame in the error."""
    try:
        mat = np.asarray(frame["transform_matrix"], dtype=np.float64)
    except (TypeError, ValueError) as exc:
        raise DataError(f"{where}: 'transform_matrix' must be a 4x4 list of numbers ({exc})") from exc
    if mat.shape != (4, 4):
        raise DataError(f"{where}: 'transform_matrix' must be 4x4, got shape {mat.shape}")
    return mat


def _image_path(root: Path, file_path: str, where: str) -> Path:
    """'./train/r_0' -> <root>/train/r_0.png; an explicit extension is kept. Paths must stay inside the dataset
    folder (no absolute paths, no '..' out of it): a dataset never reads files elsewhere on the system."""
    inside = os.path.normpath(os.path.join(os.path.abspath(root), file_path))
    if os.path.isabs(file_path) or os.path.commonpath([inside, os.path.abspath(root)]) != os.path.abspath(root):
        raise DataError(f"{where}: 'file_path' {file_path!r} points outside the dataset folder {root}; file paths "
                        "must be relative to the dataset folder (e.g. './train/r_0')")
    base = root / file_path
    with_png = base.with_name(base.name + ".png")
    if base.suffix.lower() != ".png" and with_png.is_file():
        return with_png
    if base.is_file():
        return base
    tried = [base] if base.suffix.lower() == ".png" else [with_png, base]
    raise DataError(f"{where}: image not found (looked for {', '.join(str(p) for p in tried)}); "
                    "fix 'file_path' (relative to the dataset folder) or restore the file")


def _check_rigid(c2w: np.ndarray, files: list[Path], json_path: Path) -> None:
    """c2w [V, 4, 4] must be finite rigid transforms: R^T R = I, det R = +1, last row [0, 0, 0, 1], camera positions
    within MAX_CAMERA_DISTANCE of the origin (a larger one turns to inf in the float32 cameras)."""
    finite = np.isfinite(c2w).all(axis=(1, 2))
    if not finite.all():
        i = int(np.argmin(finite))
        raise DataError(f"{json_path}: frame {i} ({files[i].name}): 'transform_matrix' has NaN/inf entries")
    far = np.nonzero(np.abs(c2w[:, :3, 3]).max(axis=1) > MAX_CAMERA_DISTANCE)[0]
    if far.size:
        i = int(far[0])
        raise DataError(f"{json_path}: frame {i} ({files[i].name}): 'transform_matrix' puts the camera at "
                        f"{c2w[i, :3, 3].tolist()}, farther than {MAX_CAMERA_DISTANCE:g} units from the origin; "
                        f"{far.size} frame(s) affected. Fix the camera positions (or the scene's units).")
    rot = c2w[:, :3, :3]
    ortho_err = np.abs(np.swapaxes(rot, 1, 2) @ rot - np.eye(3)).max(axis=(1, 2))
    row_err = np.abs(c2w[:, 3, :] - np.array([0.0, 0.0, 0.0, 1.0])).max(axis=1)
    det = np.linalg.det(rot)
    for errs, problem in ((row_err, "last row is not [0, 0, 0, 1]"),
                          (ortho_err, "rotation part is not orthonormal (scaled or sheared camera)")):
        bad = np.nonzero(errs > RIGID_TOL)[0]
        if bad.size:
            i = int(bad[0])
            raise DataError(f"{json_path}: frame {i} ({files[i].name}): 'transform_matrix' is not a rigid "
                            f"camera-to-world transform: {problem} (error {errs[i]:.3g} > {RIGID_TOL}); "
                            f"{bad.size} frame(s) affected. Export cameras without scale.")
    bad = np.nonzero(det < 0)[0]
    if bad.size:
        i = int(bad[0])
        raise DataError(f"{json_path}: frame {i} ({files[i].name}): 'transform_matrix' is a reflection "
                        f"(det {det[i]:.3g}, must be +1); {bad.size} frame(s) affected. Remove negative scales.")


def _check_no_extra_files(root: Path, json_path: Path, files: list[Path]) -> None:
    """Every PNG in the split's folders must be a frame of some transforms_*.json (or a depth/normal render)."""
    referenced = {os.path.normcase(os.path.abspath(p)) for p in files}
    for other in root.glob("transforms_*.json"):
        if other != json_path:
            referenced |= _referenced_quietly(other, root)
    for folder in sorted({p.parent for p in files}):
        extra = sorted(p.name for p in folder.glob("*.png")
                       if not _AUXILIARY.search(p.stem) and os.path.normcase(os.path.abspath(p)) not in referenced)
        if extra:
            shown = ", ".join(extra[:5]) + (f" and {len(extra) - 5} more" if len(extra) > 5 else "")
            raise DataError(f"{json_path}: {len(extra)} PNG(s) in {folder} are not referenced by any frame: {shown}. "
                            "Add frames for them, move them out of the folder, or pass check_extra_files=False")


def _referenced_quietly(json_path: Path, root: Path) -> set[str]:
    """Image paths another split references; a broken file is reported when that split itself is loaded."""
    try:
        frames = json.loads(json_path.read_text(encoding="utf-8")).get("frames", [])
        out = set()
        for frame in frames:
            base = root / frame["file_path"]
            for p in (base.with_name(base.name + ".png"), base):
                out.add(os.path.normcase(os.path.abspath(p)))
        return out
    except (OSError, ValueError, TypeError, AttributeError, KeyError, RecursionError):
        return set()


def _read_images(files: list[Path], json_path: Path, masks: list[Path] | None = None, key=None, block: int = 1,
                 size: tuple[int, int] | None = None, progress: bool = False, read_sizes: list | None = None,
                 warps: list | None = None, coverage: list | None = None) -> tuple[np.ndarray, np.ndarray]:
    """Premultiplied colour [V, h, w, 3] and alpha [V, h, w] float32 of the frames, each image area-averaged over
    `block` x `block` pixels as it is read (so only one full-size image is in memory at a time).

    Coverage: the image's alpha, times the frame's mask when `masks` are given; images without either are keyed
    on the RGB `key` (background colour) or refused. size: (h, w) after the block average (default: from the
    first image). read_sizes: each file's expected (h, w) (default: the first image's). warps: per frame None, or
    (source Intrinsics, target Intrinsics, target (h, w), source Distortion or None) at the file's resolution: the
    frame is resampled (undistorted) onto the target pinhole camera before the block average; coverage[i] receives
    the share of its pixels the frame saw."""
    v = len(files)
    full_h, full_w = _image_size(files[0])
    read_sizes = read_sizes or [(full_h, full_w)] * v
    warps = warps or [None] * v
    if warps[0] is not None:
        full_h, full_w = warps[0][2]
    h, w = size if size is not None else (full_h // block, full_w // block)
    need = v * h * w * 4 * 4 + full_h * full_w * 4 * 4 * min(4, os.cpu_count() or 1)  # outputs + decode buffers
    if progress:
        print(f"[data] {json_path.name}: {v} images of {full_w}x{full_h}"
              + (f" -> {w}x{h}" if (w, h) != (full_w, full_h) else "")
              + f", about {need / 2**20:.0f} MiB as float32", file=sys.stderr, flush=True)
    if need > _memory_limit():
        raise DataError(f"{json_path}: {v} images of {w}x{h} need {need / 2**30:.1f} GiB as float32, more than this "
                        f"machine's memory ({_memory_limit() / 2**30:.1f} GiB); use fewer frames or --downscale")
    try:
        rgb = np.empty((v, h, w, 3), dtype=np.float32)
        alpha = np.ones((v, h, w), dtype=np.float32)
    except MemoryError as exc:
        raise DataError(f"{json_path}: not enough memory for {v} images of {w}x{h} "
                        f"({need / 2**30:.1f} GiB); use fewer frames or --downscale") from exc

    def fill(i: int) -> None:  # each call writes only its own slot, so threads never overlap
        img = read_png(files[i])
        ref = tuple(read_sizes[i])
        if img.shape[:2] != ref:
            raise DataError(f"{files[i]}: image is {img.shape[1]}x{img.shape[0]} but {json_path.name} describes it "
                            f"as {ref[1]}x{ref[0]} ('w'/'h', or the image header); re-export the image")
        a = img[..., 3] if img.shape[2] == 4 else None
        if masks is not None:
            m = read_png(masks[i])
            if m.shape[:2] != ref:
                raise DataError(f"{masks[i]}: mask is {m.shape[1]}x{m.shape[0]} but its image {files[i].name} is "
                                f"{ref[1]}x{ref[0]}; a mask must match its image")
            a = m[..., 0] if a is None else a * m[..., 0]
        if a is None:
            if key is None:
                raise DataError(f"{files[i]}: the image has no alpha channel and {json_path.name} gives no "
                                "'mask_path', so PointGT cannot tell the object from the background. Provide "
                                "masks (a 'mask_path' per frame: white = object, black = background; e.g. from "
                                "rembg or SAM), save the images as RGBA PNGs with the object in alpha, or, for a "
                                "plain studio backdrop, pass --background-colour R,G,B to key it out")
            a = (np.abs(img[..., :3] - key).max(axis=-1) > KEY_TOLERANCE).astype(np.float32)
        premul = img[..., :3] * a[..., None]
        if warps[i] is not None:
            from core.images.resample import resample

            source, target, out_size, lens = warps[i]
            both, seen = resample(np.concatenate([premul, a[..., None]], axis=-1), source, target, out_size, lens)
            if seen < MIN_COVERAGE:
                raise DataError(f"{json_path}: frame {files[i].name} sees only {seen:.0%} of the split's camera view "
                                f"(its intrinsics, size or lens distortion differ: fx, fy, cx, cy = "
                                f"{source.as_list()} vs {target.as_list()}); PointGT resamples frames with their own "
                                "camera onto the pinhole camera most frames share, which needs most of that view: "
                                "crop or remove the frame")
            premul, a = both[..., :3], np.clip(both[..., 3], 0.0, 1.0)
            if coverage is not None:
                coverage[i] = seen
        if block > 1:
            premul = _area_mean(premul[None], block)[0]
            a = _area_mean(a[None, ..., None], block)[0, ..., 0]
        rgb[i], alpha[i] = premul, a

    # zlib and Pillow's decoder release the GIL, so a few threads overlap decoding with file reads.
    from core.util.progress import Progress

    with ThreadPoolExecutor(max_workers=min(4, os.cpu_count() or 1)) as pool, \
            Progress(v, f"[data] {json_path.name}", enabled=progress) as bar:
        for _ in pool.map(fill, range(v)):  # re-raises the first error in frame order
            bar.update(1)
    return rgb, alpha


def _memory_limit() -> int:
    """Bytes of physical memory (a dataset larger than this cannot be loaded); 1 TiB when unknown."""
    try:
        return int(os.sysconf("SC_PAGE_SIZE")) * int(os.sysconf("SC_PHYS_PAGES"))
    except (ValueError, OSError, AttributeError):
        return 1 << 40


@dataclass
class Cameras:
    """Cameras of a transforms JSON without requiring its images: c2w [V, 4, 4] float32, names per frame; focal as
    in SplitData (a float for the centred square-pixel camera, else Intrinsics)."""
    c2w: torch.Tensor
    camera_angle_x: float
    names: list[str]
    height: int
    width: int
    focal: float | Intrinsics


def load_cameras(json_path: str | os.PathLike, size: int | None = None) -> Cameras:
    """Read the cameras of a transforms JSON (any layout; all frames of a single transforms.json) for rendering.
    The image size comes from `size` (the width; the height keeps the images' aspect ratio, square when it is
    unknown) or, when not given, from the 'w'/'h' keys or the first frame's image. Frame names are the file_path
    stems. Frames with their own intrinsics all get the camera most frames share, the one load_split resamples
    their images onto."""
    json_path = Path(json_path)
    doc = _read_json(json_path, json_path.parent)
    frames = doc.get("frames")
    if not isinstance(frames, list) or not frames:
        raise DataError(f"{json_path}: needs a non-empty 'frames' list with 'transform_matrix' entries")
    names, mats = [], []
    for i, frame in enumerate(frames):
        if not isinstance(frame, dict) or "transform_matrix" not in frame:
            raise DataError(f"{json_path}: frame {i} has no 'transform_matrix'")
        mats.append(_frame_matrix(frame, f"{json_path}: frame {i}"))
        fp = frame.get("file_path")
        names.append(Path(fp).stem if isinstance(fp, str) and fp.strip() else f"frame_{i:04d}")
    c2w = np.stack(mats)
    _check_rigid(c2w, [Path(n) for n in names], json_path)
    _check_key_presence(frames, doc, json_path)
    w_key, h_key = frames[0].get("w", doc.get("w")), frames[0].get("h", doc.get("h"))
    if isinstance(w_key, (int, float)) and isinstance(h_key, (int, float)) and not isinstance(w_key, bool) \
            and w_key > 0 and h_key > 0 and float(w_key).is_integer() and float(h_key).is_integer():
        full_h, full_w = int(h_key), int(w_key)
    else:
        try:
            full_h, full_w = _image_size(_image_path(json_path.parent, frames[0].get("file_path"),
                                                     f"{json_path}: frame 0"))
        except (DataError, TypeError, AttributeError) as exc:
            if size is None:
                raise DataError(f"{json_path}: cannot tell the image size (no 'w'/'h' and frame 0 has no readable "
                                "image); pass the size explicitly (--size)") from exc
            full_h = full_w = None
    if full_w:
        sizes = [_key_size(doc, fr) or (full_h, full_w) for fr in frames]
        specs = [_frame_camera(doc, fr, json_path, i, Path(names[i]), sizes[i][1], sizes[i][0])
                 for i, fr in enumerate(frames)]
    else:
        sizes = [(None, None)] * len(frames)
        specs = [_frame_camera({k: v for k, v in doc.items() if k not in ("w", "h")},
                               {k: v for k, v in fr.items() if k not in ("w", "h")}, json_path, i, Path(names[i]), 0, 0)
                 for i, fr in enumerate(frames)]
    spec, full_h, full_w = _majority(specs, sizes)  # the camera load_split resamples every frame onto
    if size is None:
        height, width, scale = full_h, full_w, 1.0
    else:
        if int(size) < 1:
            raise InputError(f"image size must be positive, got {size}")
        width = int(size)
        if full_w is None:
            height, scale = width, None
        else:
            scale = width / full_w
            height = max(1, round(full_h * scale))
    if scale is None:  # size only: the keys must be fields of view or be given for this size
        if spec["fl_x"] is not None or spec["cx"] is not None or spec["cy"] is not None:
            raise DataError(f"{json_path}: intrinsics in pixels ('fl_x', 'cx', 'cy') need the image size the file "
                            "describes; add 'w' and 'h' or the images")
        k = _intrinsics(spec, width, height, 1)
    else:
        k = _intrinsics(spec, full_w, full_h, 1) if scale == 1.0 else _intrinsics(spec, full_w, full_h, 1).scaled(scale)
        if spec["fl_x"] is None and spec["fl_y"] is None and spec["cx"] is None and spec["cy"] is None \
                and spec["camera_angle_y"] is None:
            k = _intrinsics(spec, width, height, 1)  # a field of view: the focal at this size, as load_split
    angle = spec["camera_angle_x"] or 2.0 * math.atan(0.5 * width / k.fx)
    return Cameras(c2w=torch.from_numpy(c2w.astype(np.float32)), camera_angle_x=angle, names=names,
                   height=height, width=width, focal=simplest(k, height, width))
