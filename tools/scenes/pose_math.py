"""The named pose deformations as plain maps of points (no bpy).

Blender evaluates the poses with Lattice and Armature modifiers (see `poses.py`); these maps place the lattice
points, so inside the lattice the deformation is these maps interpolated (exact at lattice points; bend and
twist are piecewise linear between the 24 slices along their axis; squash/stretch are exact everywhere).

Why not SimpleDeform: its bend/twist angle is spread over the *deformed object's own* extent along the axis, so
a point cloud with one stray point gets a different deformation than the mesh. Lattice and Armature (bone
envelopes) depend only on the rig, so a mesh and a vertex-only point mesh in the same scene move the same way.

Magnitude m scales a pose: bend angle m * angle, twist m * angle, scale factor ** m (m = 1: 5 % thickness /
5x length; geometric, so it is always positive), armature joint angle m * angle; m = 0 is the rest pose.
"""
from __future__ import annotations

import math

import numpy as np

POSE_TYPES = ("rest", "bend", "twist", "scale", "armature")


def bend(points: np.ndarray, center, half, along: int, toward: int, angle_deg: float, m: float) -> np.ndarray:
    """Bend points [N, 3] along axis `along`, curling toward +`toward`, by m * angle over the object's length."""
    c = np.asarray(center, dtype=np.float64)
    k = math.radians(angle_deg) * m / max(2.0 * float(half[along]), 1e-9)  # curvature = angle / length
    p = np.array(points, dtype=np.float64)
    s, t = p[:, along] - c[along], p[:, toward] - c[toward]
    if abs(k) < 1e-9:
        return p
    a = k * s
    p[:, along] = c[along] + np.sin(a) / k - t * np.sin(a)
    p[:, toward] = c[toward] + (1.0 - np.cos(a)) / k + t * np.cos(a)
    return p


def twist(points: np.ndarray, center, half, along: int, angle_deg: float, m: float) -> np.ndarray:
    """Rotate each slice across axis `along` by m * angle * s / length (s from the centre)."""
    c = np.asarray(center, dtype=np.float64)
    p = np.array(points, dtype=np.float64)
    u, v = [i for i in range(3) if i != along]
    phi = math.radians(angle_deg) * m * (p[:, along] - c[along]) / max(2.0 * float(half[along]), 1e-9)
    x, y = p[:, u] - c[u], p[:, v] - c[v]
    p[:, u] = c[u] + np.cos(phi) * x - np.sin(phi) * y
    p[:, v] = c[v] + np.sin(phi) * x + np.cos(phi) * y
    return p


def scale(points: np.ndarray, center, axis: int, factor: float, m: float) -> np.ndarray:
    """Scale along `axis` about the centre by factor ** m."""
    c = np.asarray(center, dtype=np.float64)
    p = np.array(points, dtype=np.float64)
    p[:, axis] = c[axis] + (p[:, axis] - c[axis]) * float(factor) ** m
    return p


def deform(points: np.ndarray, spec: dict, center, half, m: float) -> np.ndarray:
    """Apply a lattice pose spec (type bend/twist/scale/rest) to points [N, 3]; returns [N, 3] float64."""
    kind = spec["type"]
    if kind == "rest" or m == 0:
        return np.array(points, dtype=np.float64)
    if kind == "bend":
        return bend(points, center, half, spec["along"], spec["toward"], spec["angle_deg"], m)
    if kind == "twist":
        return twist(points, center, half, spec["along"], spec["angle_deg"], m)
    if kind == "scale":
        return scale(points, center, spec["axis"], spec["factor"], m)
    raise ValueError(f"pose type '{kind}' is not a lattice pose")


def rotation_matrix(axis: int, angle_rad: float) -> np.ndarray:
    """3x3 right-handed rotation about coordinate axis 0/1/2."""
    c, s = math.cos(angle_rad), math.sin(angle_rad)
    u, v = [i for i in range(3) if i != axis]
    r = np.eye(3)
    r[u, u], r[u, v], r[v, u], r[v, v] = c, -s, s, c
    return r
