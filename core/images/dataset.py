"""Loader for the NeRF-synthetic dataset layout.

    <root>/transforms_train.json   {"camera_angle_x": fov_x_radians,
    <root>/transforms_val.json      "frames": [{"file_path": "./train/r_0", "transform_matrix": 4x4 c2w}, ...]}
    <root>/transforms_test.json
    <root>/train/r_0.png ...        RGBA PNGs (alpha = object mask)

`file_path` is relative to <root>, with or without ".png". `transform_matrix` is camera-to-world in the Blender
convention (camera looks down -Z, +Y up; see core/images/cameras.py). Every problem found on disk raises a
DataError naming the file and saying how to fix it.
"""
from __future__ import annotations

import json
import math
import os
import re
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch

from core.images.cameras import focal_from_fov
from core.images.png import read_png
from core.util.errors import DataError, InputError

SPLITS = ("train", "val", "test")
# NeRF-synthetic ships depth and normal renders next to the test images (r_0_depth_0000.png); they are not frames.
_AUXILIARY = re.compile(r"_(depth|normal)(_\d+)?$", re.IGNORECASE)
RIGID_TOL = 1e-3  # max |R^T R - I| entry and |last row - [0,0,0,1]|; NeRF-synthetic matrices are exact to ~1e-7


@dataclass
class SplitData:
    """One split, ready for training/evaluation.

    images [V, H, W, 3] float32 in [0, 1], composited onto `background`; alphas [V, H, W] float32 (all 1 when the
    PNGs carry no alpha); c2w [V, 4, 4] float32 camera-to-world; focal in pixels at this (downscaled) size.
    """
    split: str
    images: torch.Tensor
    alphas: torch.Tensor
    c2w: torch.Tensor
    focal: float
    height: int
    width: int
    camera_angle_x: float
    files: list[Path]

    def __len__(self) -> int:
        return len(self.files)


def transforms_path(root: str | os.PathLike, split: str) -> Path:
    return Path(root) / f"transforms_{split}.json"


def load_dataset(root: str | os.PathLike, splits=SPLITS, required=("train",), downscale: int = 1,
                 background=(1.0, 1.0, 1.0), check_extra_files: bool = True) -> dict[str, SplitData]:
    """Load several splits. Splits listed in `required` must exist; the others are skipped when their
    transforms_<split>.json is absent (a present but broken one still raises). Returns {split: SplitData}."""
    root = _check_root(root)
    missing_required = [s for s in required if s not in splits]
    if missing_required:
        raise InputError(f"required splits {missing_required} are not among the requested splits {list(splits)}")
    out = {}
    for split in splits:
        if split not in required and not transforms_path(root, split).exists():
            continue
        out[split] = load_split(root, split, downscale=downscale, background=background,
                                check_extra_files=check_extra_files)
    return out


def load_split(root: str | os.PathLike, split: str = "train", downscale: int = 1, background=(1.0, 1.0, 1.0),
               check_extra_files: bool = True) -> SplitData:
    """Load one split: images [V, H, W, 3], alphas [V, H, W], c2w [V, 4, 4] (see SplitData).

    downscale: integer factor; pixels are area-averaged with premultiplied alpha (no dark fringes at edges).
    background: RGB in [0, 1] that transparent pixels are composited onto: rgb * a + bg * (1 - a).
    check_extra_files: reject PNGs in the split folders that no frame references (depth/normal renders excepted).
    """
    root = _check_root(root)
    bg = _check_background(background)
    if isinstance(downscale, bool) or not isinstance(downscale, (int, np.integer)) or downscale < 1:
        raise InputError(f"downscale must be a positive integer, got {downscale!r}")
    json_path = transforms_path(root, split)
    doc = _read_json(json_path, root)
    angle = _camera_angle(doc, json_path)
    files, c2w = _frames(doc, json_path, root)
    if check_extra_files:
        _check_no_extra_files(root, json_path, files)

    rgb, alpha = _read_images(files, json_path)
    height, width = rgb.shape[1:3]
    if height % downscale or width % downscale:
        divisors = [d for d in range(2, 17) if height % d == 0 and width % d == 0]
        raise DataError(f"{json_path}: images are {width}x{height}, which downscale={downscale} does not divide; "
                        f"use one of {divisors or [1]}")
    # In place where possible: a full-size split is V x 800 x 800 x 3 floats.
    images = np.multiply(rgb, alpha[..., None], out=rgb)  # premultiplied colour
    if downscale > 1:
        images = _area_mean(images, downscale)
        alpha = _area_mean(alpha[..., None], downscale)[..., 0]
    images += (1.0 - alpha[..., None]) * bg  # composite: rgb * a + bg * (1 - a)
    np.clip(images, 0.0, 1.0, out=images)
    h, w = height // downscale, width // downscale
    return SplitData(split=split,
                     images=torch.from_numpy(images),
                     alphas=torch.from_numpy(alpha),
                     c2w=torch.from_numpy(c2w.astype(np.float32)),
                     focal=focal_from_fov(w, angle), height=h, width=w, camera_angle_x=angle, files=files)


def _area_mean(x: np.ndarray, d: int) -> np.ndarray:
    """Average d x d blocks: x [V, H, W, C] -> [V, H/d, W/d, C]."""
    v, h, w, c = x.shape
    return x.reshape(v, h // d, d, w // d, d, c).mean(axis=(2, 4), dtype=np.float32)


def _check_root(root) -> Path:
    root = Path(root)
    if not root.is_dir():
        raise DataError(f"{root}: dataset folder not found; pass the folder that holds transforms_train.json")
    return root


def _check_background(background) -> np.ndarray:
    bg = np.asarray(background, dtype=np.float32)
    if bg.shape != (3,) or not np.all(np.isfinite(bg)) or bg.min() < 0 or bg.max() > 1:
        raise InputError(f"background must be three numbers in [0, 1] (RGB), got {background!r}")
    return bg


def _read_json(json_path: Path, root: Path) -> dict:
    if not json_path.is_file():
        present = sorted(p.name for p in root.glob("transforms_*.json"))
        hint = f"the folder has {present}" if present else "the folder has no transforms_*.json at all"
        raise DataError(f"{json_path}: split file not found ({hint}); point to a NeRF-synthetic style dataset folder")
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


def _camera_angle(doc: dict, json_path: Path) -> float:
    if "camera_angle_x" not in doc:
        raise DataError(f"{json_path}: missing 'camera_angle_x' (horizontal field of view in radians); add it")
    angle = doc["camera_angle_x"]
    if isinstance(angle, bool) or not isinstance(angle, (int, float)) or not math.isfinite(angle) \
            or not 0.0 < angle < math.pi:
        raise DataError(f"{json_path}: 'camera_angle_x' must be a finite field of view in radians strictly "
                        f"between 0 and pi, got {angle!r} (degrees? convert with math.radians)")
    return float(angle)


def _frames(doc: dict, json_path: Path, root: Path) -> tuple[list[Path], np.ndarray]:
    """Image paths and c2w [V, 4, 4] float64 of the frames, validated."""
    frames = doc.get("frames")
    if not isinstance(frames, list):
        raise DataError(f"{json_path}: missing 'frames' list; add one entry per image "
                        "({'file_path': ..., 'transform_matrix': ...})")
    if not frames:
        raise DataError(f"{json_path}: 'frames' is empty; a split needs at least one image")
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
    """c2w [V, 4, 4] must be finite rigid transforms: R^T R = I, det R = +1, last row [0, 0, 0, 1]."""
    finite = np.isfinite(c2w).all(axis=(1, 2))
    if not finite.all():
        i = int(np.argmin(finite))
        raise DataError(f"{json_path}: frame {i} ({files[i].name}): 'transform_matrix' has NaN/inf entries")
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


def _read_images(files: list[Path], json_path: Path) -> tuple[np.ndarray, np.ndarray]:
    """rgb [V, H, W, 3] and alpha [V, H, W] float32 from the frames' PNGs, all of one size."""
    first = read_png(files[0])
    v, (h, w) = len(files), first.shape[:2]
    need = v * h * w * 4 * 4  # rgb + alpha, float32
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
        img = first if i == 0 else read_png(files[i])
        if img.shape[:2] != (h, w):
            raise DataError(f"{files[i]}: image is {img.shape[1]}x{img.shape[0]} but {files[0].name} is {w}x{h}; "
                            f"all images of {json_path.name} must have one size")
        rgb[i] = img[..., :3]
        if img.shape[2] == 4:
            alpha[i] = img[..., 3]

    # zlib and Pillow's decoder release the GIL, so a few threads overlap decoding with file reads.
    with ThreadPoolExecutor(max_workers=min(4, os.cpu_count() or 1)) as pool:
        for _ in pool.map(fill, range(v)):  # re-raises the first error in frame order
            pass
    return rgb, alpha


def _memory_limit() -> int:
    """Bytes of physical memory (a dataset larger than this cannot be loaded); 1 TiB when unknown."""
    try:
        return int(os.sysconf("SC_PAGE_SIZE")) * int(os.sysconf("SC_PHYS_PAGES"))
    except (ValueError, OSError, AttributeError):
        return 1 << 40


@dataclass
class Cameras:
    """Cameras of a transforms JSON without requiring its images: c2w [V, 4, 4] float32, names per frame."""
    c2w: torch.Tensor
    camera_angle_x: float
    names: list[str]
    height: int
    width: int
    focal: float


def load_cameras(json_path: str | os.PathLike, size: int | None = None) -> Cameras:
    """Read the cameras of a transforms_*.json for rendering. The image size comes from `size` (square) or,
    when not given, from the first frame's image if it exists. Frame names are the file_path stems."""
    json_path = Path(json_path)
    doc = _read_json(json_path, json_path.parent)
    angle = _camera_angle(doc, json_path)
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
    if size is None:
        first = frames[0].get("file_path")
        try:
            img = read_png(_image_path(json_path.parent, first, f"{json_path}: frame 0"))
        except (DataError, TypeError, AttributeError) as exc:
            raise DataError(f"{json_path}: cannot tell the image size (frame 0 has no readable image); "
                            "pass the size explicitly (--size)") from exc
        height, width = img.shape[:2]
    else:
        if int(size) < 1:
            raise InputError(f"image size must be positive, got {size}")
        height = width = int(size)
    return Cameras(c2w=torch.from_numpy(c2w.astype(np.float32)), camera_angle_x=angle, names=names,
                   height=height, width=width, focal=focal_from_fov(width, angle))
