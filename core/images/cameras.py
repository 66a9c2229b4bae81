"""Pinhole cameras in the NeRF-synthetic / Blender convention and the rays through pixel centres.

Convention: `c2w` [4, 4] is camera-to-world; the camera looks down its local -Z with +Y up (OpenGL/Blender).
Pixel (row r, col c) has its centre at (c + 0.5, r + 0.5); row 0 is the top row of the image.
focal = 0.5 * W / tan(0.5 * camera_angle_x) in pixels.

Intrinsics: every function taking `focal` accepts either one focal length in pixels (square pixels, principal point
at the image centre (W/2, H/2) — the NeRF-synthetic camera) or an `Intrinsics` (fx, fy, cx, cy) for non-square
pixels and off-centre principal points (real captures: COLMAP / nerfstudio / instant-ngp). A plain focal gives
bit-identical results to the single-focal camera. Pixel (col x, row y) of a camera-space point (X, Y, Z), Z < 0:
x = fx * X / -Z + cx, y = -fy * Y / -Z + cy (image y grows downwards, camera +Y is up).
"""
from __future__ import annotations

import math

import torch

from core.images.intrinsics import Intrinsics  # noqa: F401  (torch-free, so the Blender add-on can use it)


def intrinsics(focal, height: int, width: int) -> Intrinsics:
    """`focal` (a number of pixels or an Intrinsics) as Intrinsics of a `width` x `height` image."""
    if isinstance(focal, Intrinsics):
        return focal
    return Intrinsics(focal, focal, 0.5 * width, 0.5 * height)


def simplest(k: Intrinsics, height: int, width: int):
    """A plain focal (float) when `k` is the single-focal centred camera, else `k` itself: what datasets hand to
    the pipeline, so that centred square-pixel captures take exactly the single-focal code path."""
    return float(k.fx) if k.is_centred(height, width) else k


def _k(focal, height: int, width: int) -> tuple:
    """(fx, fy, cx, cy) of `focal` (a number — float, numpy or 0-d tensor, passed through untouched — or
    Intrinsics)."""
    if isinstance(focal, Intrinsics):
        return focal.fx, focal.fy, focal.cx, focal.cy
    return focal, focal, 0.5 * width, 0.5 * height


def focal_scale(focal) -> float:
    """One focal length in pixels for footprint estimates (pixel size at depth d ≈ d / focal_scale):
    the focal itself, or sqrt(fx * fy) for Intrinsics."""
    if isinstance(focal, Intrinsics):
        return math.sqrt(focal.fx * focal.fy)
    return focal


def scaled_focal(focal, factor: float):
    """The focal (pixels or Intrinsics) of the same camera's frame resized by `factor` (2 = twice the pixels per
    side)."""
    return focal.scaled(factor) if isinstance(focal, Intrinsics) else focal * factor


def focal_from_fov(width: int, camera_angle_x: float) -> float:
    return 0.5 * width / math.tan(0.5 * camera_angle_x)


def pixel_rays(c2w: torch.Tensor, height: int, width: int, focal) -> tuple[torch.Tensor, torch.Tensor]:
    """Rays through every pixel centre.

    Args: c2w [4, 4] (or [3, 4]); focal in pixels or Intrinsics. Returns origins [H, W, 3] and unit directions
    [H, W, 3], row-major, row 0 = top.
    """
    dev, dt = c2w.device, c2w.dtype
    rows = torch.arange(height, device=dev, dtype=dt) + 0.5
    cols = torch.arange(width, device=dev, dtype=dt) + 0.5
    r, c = torch.meshgrid(rows, cols, indexing="ij")
    fx, fy, cx, cy = _k(focal, height, width)
    d_cam = torch.stack([(c - cx) / fx, -(r - cy) / fy, -torch.ones_like(r)], dim=-1)
    d = d_cam @ c2w[:3, :3].T
    d = d / d.norm(dim=-1, keepdim=True)
    o = c2w[:3, 3].expand_as(d)
    return o, d


def project_points(points: torch.Tensor, c2w: torch.Tensor, height: int, width: int, focal):
    """Project world points into the image.

    Args: points [N, 3], c2w [4, 4], focal in pixels or Intrinsics. Returns pixel coords [N, 2] as (col, row) in
    pixel units (centre of pixel (r, c) is (c + 0.5, r + 0.5)) and depth [N] along the viewing axis (> 0 in front
    of the camera).
    """
    R = c2w[:3, :3]
    t = c2w[:3, 3]
    cam = (points - t) @ R  # world -> camera: R^T (p - t)
    depth = -cam[:, 2]
    safe = torch.where(depth.abs() > 1e-12, depth, torch.full_like(depth, 1e-12))
    fx, fy, cx, cy = _k(focal, height, width)
    col = fx * cam[:, 0] / safe + cx
    row = -fy * cam[:, 1] / safe + cy
    return torch.stack([col, row], dim=-1), depth


def look_at(eye, target=(0.0, 0.0, 0.0), up=(0.0, 0.0, 1.0)) -> torch.Tensor:
    """Camera-to-world [4, 4] for a camera at `eye` looking at `target` (Blender convention, Z up in world)."""
    eye = torch.as_tensor(eye, dtype=torch.float64)
    target = torch.as_tensor(target, dtype=torch.float64)
    up = torch.as_tensor(up, dtype=torch.float64)
    fwd = target - eye
    fwd = fwd / fwd.norm()
    right = torch.linalg.cross(fwd, up)
    if right.norm() < 1e-9:  # looking straight up/down: pick another up
        right = torch.linalg.cross(fwd, torch.tensor([0.0, 1.0, 0.0], dtype=torch.float64))
    right = right / right.norm()
    cam_up = torch.linalg.cross(right, fwd)
    m = torch.eye(4, dtype=torch.float64)
    m[:3, 0], m[:3, 1], m[:3, 2], m[:3, 3] = right, cam_up, -fwd, eye
    return m


def rays_for_pixels(c2w: torch.Tensor, px: torch.Tensor, height: int, width: int,
                    focal) -> tuple[torch.Tensor, torch.Tensor]:
    """Rays through given pixel coordinates px [R, 2] (col, row in pixel units; centres at +0.5); focal in pixels
    or Intrinsics.

    Returns origins [R, 3] and unit directions [R, 3].
    """
    c2w = c2w.to(px.dtype)
    fx, fy, cx, cy = _k(focal, height, width)
    d_cam = torch.stack([(px[:, 0] - cx) / fx, -(px[:, 1] - cy) / fy,
                         -torch.ones_like(px[:, 0])], dim=-1)
    d = d_cam @ c2w[:3, :3].T
    d = d / d.norm(dim=-1, keepdim=True)
    return c2w[:3, 3].expand_as(d), d
