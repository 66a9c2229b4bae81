"""Write a NeRF-synthetic scene again in the layouts other tools write: nerfstudio, instant-ngp, BlenderNeRF.

Nothing is re-rendered: the cameras and pixels of `<scene>/transforms_{train,val,test}.json` are rewritten with
each tool's keys, so every layout must load to the same cameras, rays and images (tests/tools/test_scene_formats.py).

    nerfstudio    transforms.json: camera_model OPENCV with k1-k4, p1, p2 = 0, fl_x/fl_y/cx/cy/w/h at the top,
                  applied_transform, train/val/test_filenames; RGB images in images/<split>/ with their masks
                  (alpha) in masks/<split>/ as mask_path, plus downscaled copies images_<d>/ and masks_<d>/
    instant-ngp   transforms.json: camera_angle_x/y and aabb_scale at the top, fl_x/fl_y/cx/cy/w/h in every frame,
                  RGBA images in images/ ('./images/<split>_r_0.png'), the split named by <split>_filenames
    blendernerf   transforms_<split>.json with camera_angle_x/y, fl_x/fl_y, cx/cy, w/h, k1-k4/p1/p2 = 0,
                  aabb_scale, file_path with its extension ('train/r_0.png'), RGBA images

No bpy here: the conversion runs anywhere.
"""
from __future__ import annotations

import io
import json
import math
from pathlib import Path

import numpy as np
from PIL import Image

from core.images.cameras import focal_from_fov
from core.util.atomic import atomic_write_bytes, atomic_write_text
from core.util.errors import DataError, InputError

FORMATS = ("nerfstudio", "instant-ngp", "blendernerf")
SPLITS = ("train", "val", "test")
# what ns-process-data records for COLMAP input: the axis swap already applied to every transform_matrix
NS_APPLIED_TRANSFORM = [[1.0, 0.0, 0.0, 0.0], [0.0, 0.0, 1.0, 0.0], [0.0, -1.0, -0.0, 0.0]]


def _png_bytes(arr: np.ndarray) -> bytes:
    buf = io.BytesIO()
    Image.fromarray(arr).save(buf, format="PNG")
    return buf.getvalue()


def _read_u8(path: Path) -> np.ndarray:
    """An 8-bit RGBA image [H, W, 4] uint8 (a missing alpha becomes 255)."""
    with Image.open(path) as img:
        if img.mode not in ("RGBA", "RGB"):
            raise DataError(f"{path}: expected an 8-bit RGB(A) PNG as make-scene writes, got mode {img.mode}")
        return np.asarray(img.convert("RGBA"))


def _downscale_rgba(arr: np.ndarray, d: int) -> tuple[np.ndarray, np.ndarray]:
    """An RGBA image [H, W, 4] uint8 averaged over d x d blocks with premultiplied alpha (as the loader averages
    when there are no copies), returned as straight RGB [H/d, W/d, 3] and mask [H/d, W/d] uint8."""
    h, w, _ = arr.shape
    x = arr[: h - h % d, : w - w % d].astype(np.float64) / 255.0
    x = x.reshape(h // d, d, w // d, d, 4)
    a = x[..., 3].mean(axis=(1, 3))
    premul = (x[..., :3] * x[..., 3:]).mean(axis=(1, 3))
    straight = np.where(a[..., None] > 0, premul / np.maximum(a[..., None], 1e-12), 0.0)
    to_u8 = lambda v: np.clip(np.round(v * 255.0), 0, 255).astype(np.uint8)  # noqa: E731
    return to_u8(straight), to_u8(a)


def _source(scene: Path) -> tuple[float, dict, int, int]:
    """camera_angle_x, {split: frames} and the image size of a NeRF-synthetic folder."""
    frames, angle = {}, None
    for split in SPLITS:
        path = scene / f"transforms_{split}.json"
        if not path.is_file():
            continue
        doc = json.loads(path.read_text(encoding="utf-8"))
        if angle is not None and doc["camera_angle_x"] != angle:
            raise DataError(f"{path}: camera_angle_x differs from the other splits'; one camera per scene")
        angle = doc["camera_angle_x"]
        frames[split] = doc["frames"]
    if "train" not in frames:
        raise DataError(f"{scene}: no transforms_train.json; convert a scene written by `pointgt make-scene`")
    first = frames["train"][0]["file_path"]
    first = scene / (first if first.endswith(".png") else first + ".png")
    with Image.open(first) as img:
        w, h = img.size
    return float(angle), frames, w, h


def _image_file(scene: Path, file_path: str) -> Path:
    return scene / (file_path if file_path.endswith(".png") else file_path + ".png")


def _intrinsics(angle: float, w: int, h: int) -> dict:
    """The keys every pinhole layout shares, for the centred camera of a NeRF-synthetic scene."""
    fx = focal_from_fov(w, angle)
    return {"fl_x": fx, "fl_y": fx, "cx": 0.5 * w, "cy": 0.5 * h, "w": w, "h": h}


def write_layout(scene, out, fmt: str, downscales=(2,), log=print) -> Path:
    """Write the NeRF-synthetic scene in folder `scene` into folder `out` in layout `fmt` (one of FORMATS);
    `downscales`: factors of the nerfstudio images_<d>/ copies. Returns the JSON a loader reads first."""
    scene, out = Path(scene), Path(out)
    if fmt not in FORMATS:
        raise InputError(f"--format must be one of nerf-synthetic, {', '.join(FORMATS)}; got {fmt!r}")
    angle, frames, w, h = _source(scene)
    k = _intrinsics(angle, w, h)
    angle_y = 2.0 * math.atan(0.5 * h / k["fl_y"])
    zero_distortion = {"k1": 0.0, "k2": 0.0, "k3": 0.0, "k4": 0.0, "p1": 0.0, "p2": 0.0}
    out.mkdir(parents=True, exist_ok=True)
    n = 0
    if fmt == "blendernerf":
        for split, fr in frames.items():
            new = []
            for f in fr:
                name = f"{split}/{Path(f['file_path']).name.removesuffix('.png')}.png"
                atomic_write_bytes(out / name, _png_bytes(_read_u8(_image_file(scene, f["file_path"]))), backup=False)
                new.append({"file_path": name, "transform_matrix": f["transform_matrix"]})
                n += 1
            doc = {"camera_angle_x": angle, "camera_angle_y": angle_y, **k, **zero_distortion,
                   "aabb_scale": 4, "frames": new}
            atomic_write_text(out / f"transforms_{split}.json", json.dumps(doc, indent=2) + "\n", backup=False)
        first = out / "transforms_train.json"
    else:
        doc, all_frames = {}, []
        for split, fr in frames.items():
            names = []
            for f in fr:
                stem = Path(f["file_path"]).name.removesuffix(".png")
                rgba = _read_u8(_image_file(scene, f["file_path"]))
                if fmt == "nerfstudio":
                    name = f"images/{split}/{stem}.png"
                    mask = f"masks/{split}/{stem}.png"
                    atomic_write_bytes(out / name, _png_bytes(np.ascontiguousarray(rgba[..., :3])), backup=False)
                    atomic_write_bytes(out / mask, _png_bytes(np.ascontiguousarray(rgba[..., 3])), backup=False)
                    for d in downscales:
                        rgb_d, mask_d = _downscale_rgba(rgba, d)
                        atomic_write_bytes(out / f"images_{d}/{split}/{stem}.png", _png_bytes(rgb_d), backup=False)
                        atomic_write_bytes(out / f"masks_{d}/{split}/{stem}.png", _png_bytes(mask_d), backup=False)
                    all_frames.append({"file_path": name, "mask_path": mask,
                                       "transform_matrix": f["transform_matrix"]})
                else:  # instant-ngp: one images/ folder, intrinsics per frame
                    name = f"./images/{split}_{stem}.png"
                    atomic_write_bytes(out / name, _png_bytes(rgba), backup=False)
                    all_frames.append({"file_path": name, **k, "transform_matrix": f["transform_matrix"]})
                names.append(name)
                n += 1
            doc[f"{split}_filenames"] = names
        if fmt == "nerfstudio":
            head = {"camera_model": "OPENCV", **k, **zero_distortion, "applied_transform": NS_APPLIED_TRANSFORM}
        else:
            head = {"camera_angle_x": angle, "camera_angle_y": angle_y, "aabb_scale": 4}
        doc = {**head, "frames": all_frames, **doc}
        first = out / "transforms.json"
        atomic_write_text(first, json.dumps(doc, indent=2) + "\n", backup=False)
    log(f"{fmt}: {n} images and {first.name} written to {out}")
    return first
