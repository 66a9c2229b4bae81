"""What every neighbour-search backend shares: the result type, the metric and backend names, input checks, and
the padding rule (a ray with fewer than K candidates is padded with idx -1 and dist +inf)."""
from __future__ import annotations

import math
import numbers
from typing import NamedTuple

import numpy as np
import torch

from core.images.intrinsics import Intrinsics
from core.util.errors import InputError

METHODS = ("screen", "screen_depth", "perpendicular")
BACKENDS = ("auto", "compiled", "grid", "kdtree", "torch")
_MAX_COORD = 1e18  # beyond this a point has diverged; squared distances would overflow float32 on the torch path


class Neighbors(NamedTuple):
    """idx [R, K] int64 (-1 = none) and dist [R, K] float32 (+inf = none), sorted ascending per ray."""

    idx: torch.Tensor
    dist: torch.Tensor

    @property
    def valid(self) -> torch.Tensor:
        """[R, K] bool: True where a real neighbour was found."""
        return self.idx >= 0


def check_k(k) -> int:
    if isinstance(k, bool) or not isinstance(k, (int, np.integer)) or k < 1:
        raise InputError(f"neighbour search: k must be a positive integer, got {k!r}")
    return int(k)


def check_matrix(name: str, t, cols: int) -> torch.Tensor:
    if not isinstance(t, torch.Tensor):
        raise InputError(f"neighbour search: {name} must be a torch.Tensor, got {type(t).__name__}")
    if t.dim() != 2 or t.shape[1] != cols:
        raise InputError(f"neighbour search: {name} must have shape [n, {cols}], got {list(t.shape)}")
    if not (t.is_floating_point() or t.dtype in (torch.int32, torch.int64)):
        raise InputError(f"neighbour search: {name} must be a real-valued tensor, got {t.dtype}")
    return t


def check_camera(c2w, height, width, focal) -> None:
    if not isinstance(c2w, torch.Tensor) or tuple(c2w.shape) not in ((4, 4), (3, 4)):
        shape = list(c2w.shape) if isinstance(c2w, torch.Tensor) else type(c2w).__name__
        raise InputError(f"neighbour search: c2w must be a [4, 4] or [3, 4] tensor, got {shape}")
    if not bool(torch.isfinite(c2w).all()):
        raise InputError("neighbour search: c2w has non-finite entries")
    for name, v in (("height", height), ("width", width)):
        if isinstance(v, bool) or not isinstance(v, (int, np.integer)) or v < 1:
            raise InputError(f"neighbour search: {name} must be a positive integer, got {v!r}")
    if isinstance(focal, Intrinsics):
        return  # validated when it was made: finite, positive focal lengths
    if isinstance(focal, bool) or not (isinstance(focal, numbers.Real) and math.isfinite(focal) and focal > 0):
        raise InputError(f"neighbour search: focal must be a finite positive number of pixels (or Intrinsics), "
                         f"got {focal!r}")


def present(points: torch.Tensor) -> torch.Tensor:
    """points [N, 3] -> [N] bool: finite and not diverged (|coord| <= _MAX_COORD); the rest are absent."""
    return (torch.isfinite(points) & (points.abs() <= _MAX_COORD)).all(dim=1)


def empty(r: int, k: int, device) -> Neighbors:
    return Neighbors(torch.full((r, k), -1, dtype=torch.int64, device=device),
                     torch.full((r, k), math.inf, dtype=torch.float32, device=device))


def finalize(idx: torch.Tensor, dist: torch.Tensor, k: int, device) -> Neighbors:
    """Pad to K columns, mark non-finite distances as absent, cast: idx [R, k'] and dist [R, k'] sorted."""
    r = idx.shape[0]
    if idx.shape[1] < k:
        pad = k - idx.shape[1]
        idx = torch.cat([idx, idx.new_full((r, pad), -1)], dim=1)
        dist = torch.cat([dist, dist.new_full((r, pad), math.inf)], dim=1)
    dist = dist.to(torch.float32)
    absent = ~torch.isfinite(dist) | (idx < 0)
    idx = idx.masked_fill(absent, -1)
    dist = dist.masked_fill(absent, math.inf)
    return Neighbors(idx.to(device), dist.to(device))

