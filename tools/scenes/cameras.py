"""Camera sets on a sphere around the object (no bpy): even coverage of the full sphere, distinct per split."""
from __future__ import annotations

import math

import numpy as np
import torch

from core.images.cameras import look_at

SPLIT_OFFSETS = {"train": 0, "val": 1, "test": 2}  # seed + offset: train/val/test never share a camera set


def _random_rotation(rng: np.random.Generator) -> np.ndarray:
    q = rng.normal(size=4)
    q /= np.linalg.norm(q)
    w, x, y, z = q
    return np.array([[1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)],
                     [2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)],
                     [2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)]])


def sphere_directions(n: int, seed: int) -> np.ndarray:
    """n unit vectors [n, 3]: a Fibonacci sphere (full sphere, near-uniform) under a seeded random rotation."""
    i = np.arange(n) + 0.5
    z = 1.0 - 2.0 * i / n
    r = np.sqrt(np.clip(1.0 - z * z, 0.0, 1.0))
    phi = i * math.pi * (3.0 - math.sqrt(5.0))
    dirs = np.stack([r * np.cos(phi), r * np.sin(phi), z], axis=-1)
    return dirs @ _random_rotation(np.random.default_rng(seed)).T


def split_cameras(split: str, n: int, seed: int, radius: float = 4.0, center=(0.0, 0.0, 0.0)) -> np.ndarray:
    """Camera-to-world matrices [n, 4, 4] (Blender convention) on a sphere of `radius` looking at `center`."""
    dirs = sphere_directions(n, seed * 7919 + SPLIT_OFFSETS[split])
    c = np.asarray(center, dtype=np.float64)
    mats = [look_at(torch.from_numpy(c + radius * d), torch.from_numpy(c)).numpy() for d in dirs]
    return np.stack(mats) if mats else np.zeros((0, 4, 4))
