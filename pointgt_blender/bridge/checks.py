"""Loud warnings about poses the neural render cannot show well, from plain arrays (no bpy, no torch): the
object moved off-camera, collapsed to a point or blew up (a bone or lattice scaled by 1e-6 or 1e6)."""
from __future__ import annotations

import numpy as np

from core.images.intrinsics import Intrinsics

COLLAPSED = 0.01   # deformed extent / rest extent below this: collapsed
EXPLODED = 100.0   # above this: blown up


def extent(points: np.ndarray) -> float:
    """Bounding-box diagonal of finite points [M, 3] (0 for none)."""
    p = points[np.isfinite(points).all(axis=1)]
    return float(np.linalg.norm(p.max(axis=0) - p.min(axis=0))) if len(p) else 0.0


def in_view(points: np.ndarray, c2w: np.ndarray, focal: float | Intrinsics, width: int, height: int) -> np.ndarray:
    """[M] bool: world points [M, 3] in front of the camera (c2w [4, 4], looks down -Z; focal in pixels or
    Intrinsics) and inside its image."""
    if isinstance(focal, Intrinsics):
        fx, fy, cx, cy = focal.fx, focal.fy, focal.cx, focal.cy
    else:
        fx = fy = float(focal)
        cx, cy = width / 2.0, height / 2.0
    c2w = np.asarray(c2w, dtype=np.float64)
    with np.errstate(divide="ignore", invalid="ignore", over="ignore"):
        cam = (np.asarray(points, dtype=np.float64) - c2w[:3, 3]) @ c2w[:3, :3]
        z = -cam[:, 2]
        front = z > 1e-9
        col = fx * cam[:, 0] / z + cx
        row = -fy * cam[:, 1] / z + cy
    return front & (col >= 0) & (col < width) & (row >= 0) & (row < height)


def pose_warning(name: str, positions: np.ndarray, rest_extent: float, c2w: np.ndarray, focal: float | Intrinsics,
                 width: int, height: int) -> str:
    """'' when the deformed points [M, 3] (world) look renderable from the camera, else one sentence saying what
    is wrong and what to check."""
    if not np.isfinite(positions).all(axis=1).any():
        return f"'{name}' has no finite point left: check its modifiers"
    ext = extent(positions)
    if rest_extent > 0 and ext < COLLAPSED * rest_extent:
        return (f"'{name}' collapsed: its points span {ext / rest_extent:.2g} of their rest size, so it renders "
                f"as (almost) nothing; check for a bone or lattice scaled to zero")
    if rest_extent > 0 and ext > EXPLODED * rest_extent:
        return (f"'{name}' blew up: its points span {ext / rest_extent:.3g} times their rest size, so its "
                f"surface falls apart; check for a bone or lattice scaled up")
    seen = in_view(positions, c2w, focal, width, height)
    if not seen.any():
        return f"'{name}' is off-camera: none of its {len(positions)} points is in the camera's view"
    return ""
