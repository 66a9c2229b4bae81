"""What a frame's rays know after the neighbour search and the attention (`trace_frame`'s result)."""
from __future__ import annotations

from dataclasses import dataclass
from functools import cached_property

import numpy as np
import torch

from core.util.jit import njit


def _held_loop(idx, m, out):
    """Mark out[j] (m bools, given False) for every point index j >= 0 in idx [R, K]; returns how many."""
    n = 0
    for r in range(idx.shape[0]):
        for s in range(idx.shape[1]):
            j = idx[r, s]
            if j >= 0 and not out[j]:
                out[j] = True
                n += 1
    return n


_held_compiled = njit(_held_loop)


def held_rows(idx: torch.Tensor, m: int) -> torch.Tensor:
    """The points [P] long (ascending) that some ray holds as a neighbour: idx [R, K] (-1 = none) of m points.
    Compiled on CPU tensors where numba is installed, else torch."""
    if idx.device.type == "cpu" and _held_compiled is not _held_loop:
        mark = np.zeros(m, dtype=np.bool_)
        _held_compiled(np.ascontiguousarray(idx.numpy()), m, mark)
        return torch.from_numpy(np.flatnonzero(mark))
    mark = torch.zeros(m + 1, dtype=torch.bool, device=idx.device)
    mark[(idx.clamp_min(-1) + 1).reshape(-1)] = True
    return torch.nonzero(mark[1:]).squeeze(1)


@dataclass(frozen=True)
class Trace:
    """Flat per-ray tensors of one frame, R = H * W rays in row-major pixel order (row 0 = top).

    origins / dirs [R, 3] the pixel rays (unit dirs); idx [R, K] neighbour indices into the traced points (-1 =
    empty slot); weights [R, K] attention over the neighbours and bg [R] the background's share (weights + bg sum
    to 1); fg_weights [R, K] the weights renormalised over the neighbours alone; x [R, 3] the surface point
    Σ fg_weights · p (the ray origin where no neighbour exists); active [R] bool: rays with at least one
    neighbour (the others are background, no attention evaluated); shape (H, W); non_finite_points: how many
    traced points were non-finite and treated as absent; held (on demand, once) the traced points some ray holds.

    A variant with other surface points is `dataclasses.replace(trace, x=...)` (its depth then follows the new x).
    coarse: how an `upsampled` frame's trace was interpolated from the training-scale trace
    (`core.points.resolution.interpolate_trace`), else None.
    """

    origins: torch.Tensor
    dirs: torch.Tensor
    idx: torch.Tensor
    weights: torch.Tensor
    fg_weights: torch.Tensor
    bg: torch.Tensor
    x: torch.Tensor
    active: torch.Tensor
    shape: tuple[int, int]
    non_finite_points: int = 0
    coarse: "CoarseLink | None" = None

    @cached_property
    def depth(self) -> torch.Tensor:
        """Distance of the surface point along its ray, (x − origin) · dir: [R] (computed once per trace)."""
        return ((self.x - self.origins) * self.dirs).sum(-1)

    @cached_property
    def held(self) -> torch.Tensor:
        """The traced points [P] long (ascending) that some ray holds as a neighbour (`held_rows` of idx; computed
        once per trace: the keys' inverse gradients, the occlusion rule and the point values all read it)."""
        return held_rows(self.idx, int(self.idx.max()) + 1 if self.idx.numel() else 0)

    @property
    def fg(self) -> torch.Tensor:
        """The attention's foreground weight 1 − bg: [R]."""
        return 1.0 - self.bg


@dataclass(frozen=True)
class CoarseLink:
    """A full-size trace's link to the training-scale trace it was interpolated from: low the Trace (h x w);
    corners [R, 4] each full-size ray's four training-scale rays (flat indices into low), weights [R, 4] their
    blend (bilinear, renormalised over the active ones on one surface; a row of zeros for a background ray)."""

    low: Trace
    corners: torch.Tensor
    weights: torch.Tensor
