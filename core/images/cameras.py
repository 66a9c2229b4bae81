"""Pinhole cameras in the NeRF-synthetic / Blender convention and the rays through pixel centres.

Convention: `c2w` [4, 4] is camera-to-world; the camera looks down its local -Z with +Y up (OpenGL/Blender).
Pixel (row r, col c) has its centre at (c + 0.5, r + 0.5); row 0 is the top row of the image.
focal = 0.5 * W / tan(0.5 * camera_angle_x) in pixels.
"""
from __future__ import annotations

import math

import torch


def focal_from_fov(width: int, camera_angle_x: float) -> float:
    return 0.5 * width / math.tan(0.5 * camera_angle_x)


def pixel_rays(c2w: torch.Tensor, height: int, width: int, focal: float) -> tuple[torch.Tensor, torch.Tensor]:
    """Rays through every pixel centre.

    Args: c2w [4, 4] (or [3, 4]). Returns origins [H, W, 3] and unit directions [H, W, 3], row-major, row 0 = top.
    """
    dev, dt = c2w.device, c2w.dtype
    rows = torch.arange(height, device=dev, dtype=dt) + 0.5
    cols = torch.arange(width, device=dev, dtype=dt) + 0.5
    r, c = torch.meshgrid(rows, cols, indexing="ij")
    d_cam = torch.stack([(c - 0.5 * width) / focal, -(r - 0.5 * height) / focal, -torch.ones_like(r)], dim=-1)
    d = d_cam @ c2w[:3, :3].T
    d = d / d.norm(dim=-1, keepdim=True)
    o = c2w[:3, 3].expand_as(d)
    return o, d


def project_points(points: torch.Tensor, c2w: torch.Tensor, height: int, width: int, focal: float):
    """Project world points into the image.

    Args: points [N, 3], c2w [4, 4]. Returns pixel coords [N, 2] as (col, row) in pixel units (centre of pixel
    (r, c) is (c + 0.5, r + 0.5)) and depth [N] along the viewing axis (> 0 in front of the camera).
    """
    R = c2w[:3, :3]
    t = c2w[:3, 3]
    cam = (points - t) @ R  # world -> camera: R^T (p - t)
    depth = -cam[:, 2]
    safe = torch.where(depth.abs() > 1e-12, depth, torch.full_like(depth, 1e-12))
    col = focal * cam[:, 0] / safe + 0.5 * width
    row = -focal * cam[:, 1] / safe + 0.5 * height
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
                    focal: float) -> tuple[torch.Tensor, torch.Tensor]:
    """Rays through given pixel coordinates px [R, 2] (col, row in pixel units; centres at +0.5).

    Returns origins [R, 3] and unit directions [R, 3].
    """
    c2w = c2w.to(px.dtype)
    d_cam = torch.stack([(px[:, 0] - 0.5 * width) / focal, -(px[:, 1] - 0.5 * height) / focal,
                         -torch.ones_like(px[:, 0])], dim=-1)
    d = d_cam @ c2w[:3, :3].T
    d = d / d.norm(dim=-1, keepdim=True)
    return c2w[:3, 3].expand_as(d), d
