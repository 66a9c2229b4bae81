"""Blender camera -> the core's pinhole camera: c2w [4, 4] (camera looks down -Z, +Y up, like Blender), image
size and focal length in pixels (with lens shift: the core's Intrinsics, whose principal point is off-centre).

The maths takes plain numbers (tested without Blender); `scene_camera` reads them from a scene. Only what the
core can render is accepted: a perspective camera (with any lens shift and pixel aspect: non-square pixels give
fx != fy); anything else is reported with what to change instead of rendering a silently wrong picture.
"""
from __future__ import annotations

import numpy as np

from core.images.intrinsics import Intrinsics
from core.util.errors import InputError


def render_size(resolution_x: int, resolution_y: int, percentage: int) -> tuple[int, int]:
    """(width, height) in pixels of a render, as Blender computes it from the resolution and its percentage."""
    w = int(resolution_x * percentage / 100)
    h = int(resolution_y * percentage / 100)
    if w < 1 or h < 1:
        raise InputError(f"render size {w}x{h} px is empty; raise Resolution or its percentage (Output properties)")
    return w, h


def preview_size(long_side: int, resolution_x: int, resolution_y: int) -> tuple[int, int]:
    """(width, height) of a preview whose longer side is `long_side`, with the render's aspect ratio."""
    long_side = max(int(long_side), 1)
    if resolution_x >= resolution_y:
        return long_side, max(1, round(long_side * resolution_y / resolution_x))
    return max(1, round(long_side * resolution_x / resolution_y)), long_side


def _fit(sensor_fit: str, width: int, height: int, aspect_x: float, aspect_y: float) -> str:
    """Blender's sensor fit with AUTO resolved: the larger side of the image as displayed (pixel aspect applied)."""
    if sensor_fit == 'AUTO':
        return 'HORIZONTAL' if aspect_x * width >= aspect_y * height else 'VERTICAL'
    if sensor_fit not in ('HORIZONTAL', 'VERTICAL'):
        raise InputError(f"unknown sensor fit {sensor_fit!r}; use Auto, Horizontal or Vertical")
    return sensor_fit


def _view_factor(fit: str, width: int, height: int, aspect_x: float, aspect_y: float) -> float:
    """The image extent, in horizontal pixels, that the sensor (and the lens shift) is measured against."""
    return width if fit == 'HORIZONTAL' else height * aspect_y / aspect_x


def focal_pixels(lens: float, sensor_width: float, sensor_height: float, sensor_fit: str,
                 width: int, height: int, aspect_x: float = 1.0, aspect_y: float = 1.0) -> float:
    """Horizontal focal length fx in pixels for a `width` x `height` image, following Blender's sensor fit: AUTO
    fits the sensor width to the larger image side, HORIZONTAL to the width, VERTICAL the sensor height to the
    height. With a pixel aspect aspect_x : aspect_y (Output > Format) the vertical focal length is
    fy = fx * aspect_x / aspect_y; with square pixels fx is the one focal length."""
    if not (lens > 0 and sensor_width > 0 and sensor_height > 0):
        raise InputError(f"camera lens {lens} mm / sensor {sensor_width}x{sensor_height} mm must be positive")
    auto = sensor_fit == 'AUTO'
    fit = _fit(sensor_fit, width, height, aspect_x, aspect_y)
    sensor = sensor_width if auto or fit == 'HORIZONTAL' else sensor_height
    return lens / sensor * _view_factor(fit, width, height, aspect_x, aspect_y)


def principal_point(shift_x: float, shift_y: float, sensor_fit: str, width: int, height: int,
                    aspect_x: float = 1.0, aspect_y: float = 1.0) -> tuple[float, float]:
    """(cx, cy) in pixels from the top-left corner for Blender's lens shift, which is measured in units of the
    image side the sensor is fitted to (AUTO: the larger side): +X shifts the view right, so the principal point
    moves left; +Y shifts it up, so the principal point moves down (rows grow downwards)."""
    fit = _fit(sensor_fit, width, height, aspect_x, aspect_y)
    side = _view_factor(fit, width, height, aspect_x, aspect_y)
    return 0.5 * width - shift_x * side, 0.5 * height + shift_y * side * aspect_x / aspect_y


MAX_PIXEL_ASPECT = 200.0  # Blender's limit for Output > Format > Aspect X / Y


def pixel_aspect(focal) -> tuple[float, float]:
    """(aspect_x, aspect_y) of the render's pixels (scene.render.pixel_aspect_x / _y) for a dataset camera: fy / fx
    as a ratio whose smaller side is 1 (Blender's values run from 1 to 200). (1, 1) for a single focal length."""
    if not isinstance(focal, Intrinsics) or focal.fx == focal.fy:
        return 1.0, 1.0
    ratio = focal.fy / focal.fx
    if not 1.0 / MAX_PIXEL_ASPECT <= ratio <= MAX_PIXEL_ASPECT:
        raise InputError(f"the camera has fx = {focal.fx:g} and fy = {focal.fy:g} pixels; Blender's pixel aspect "
                         f"reaches at most {MAX_PIXEL_ASPECT:g}:1")
    return (ratio, 1.0) if ratio >= 1.0 else (1.0, 1.0 / ratio)


def camera_settings(focal, width: int, height: int, sensor_width: float = 36.0) -> dict:
    """The Blender camera settings (lens, sensor_width, sensor_fit, shift_x, shift_y) that reproduce a dataset
    camera — a focal length in pixels or Intrinsics — for a `width` x `height` render; the inverse of
    focal_pixels + principal_point. A camera with fx != fy also needs the render's pixel aspect set to
    `pixel_aspect(focal)` (a Blender camera has one focal length; non-square pixels give the other)."""
    if isinstance(focal, Intrinsics):
        f, cx, cy = focal.fx, focal.cx, focal.cy
        fy = focal.fy
    else:
        f = fy = float(focal)
        cx, cy = 0.5 * width, 0.5 * height
    ax, ay = pixel_aspect(focal)
    return {"lens": f * sensor_width / width, "sensor_width": sensor_width, "sensor_fit": 'HORIZONTAL',
            "shift_x": (0.5 * width - cx) / width, "shift_y": (cy - 0.5 * height) / width * ay / ax}


def camera_to_world(matrix) -> np.ndarray:
    """A camera's matrix_world [4, 4] with its scale removed -> c2w [4, 4] float32 (orthonormal rotation)."""
    m = np.asarray(matrix, dtype=np.float64).reshape(4, 4)
    if not np.isfinite(m).all():
        raise InputError("the camera's transform holds NaN or infinite values; reset its location/rotation/scale")
    rot = m[:3, :3]
    scale = np.linalg.norm(rot, axis=0)
    if (scale < 1e-9).any():
        raise InputError("the camera has zero scale on an axis, so it has no viewing direction; set its scale to 1")
    out = np.eye(4)
    out[:3, :3] = rot / scale
    out[:3, 3] = m[:3, 3]
    return out.astype(np.float32)


def scene_camera(scene, width: int, height: int, depsgraph=None) -> tuple[np.ndarray, float | Intrinsics]:
    """(c2w [4, 4] float32, focal in pixels — or Intrinsics when the lens is shifted or the pixels are not square)
    of the scene's active camera for a `width` x `height` image. With a depsgraph the camera's evaluated (animated) transform is used."""
    cam = scene.camera
    if cam is None or cam.type != 'CAMERA':
        raise InputError(f"scene '{scene.name}' has no active camera; add a camera and make it active (Ctrl+Numpad 0)"
                         f", PointGT renders from it")
    if depsgraph is not None:
        cam = cam.evaluated_get(depsgraph)
    data = cam.data
    if data.type != 'PERSP':
        raise InputError(f"camera '{cam.name}' is {data.type.lower()}; PointGT renders perspective cameras only "
                         f"(Camera properties > Lens > Type: Perspective)")
    r = scene.render
    ax, ay = float(r.pixel_aspect_x), float(r.pixel_aspect_y)
    if not (ax > 0 and ay > 0):
        raise InputError(f"scene '{scene.name}' has pixel aspect {ax:g}:{ay:g}; set Output > Format > Aspect X and Y "
                         f"to positive values")
    fx = float(focal_pixels(data.lens, data.sensor_width, data.sensor_height, data.sensor_fit, width, height, ax, ay))
    fy = fx * ax / ay
    if data.shift_x != 0.0 or data.shift_y != 0.0 or ax != ay:
        cx, cy = principal_point(data.shift_x, data.shift_y, data.sensor_fit, width, height, ax, ay)
        return camera_to_world(cam.matrix_world), Intrinsics(fx, fy if ax != ay else fx, cx, cy)
    return camera_to_world(cam.matrix_world), fx
