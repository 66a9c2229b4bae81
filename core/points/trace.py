"""What a frame's rays know after the neighbour search and the attention (`trace_frame`'s result)."""
from __future__ import annotations

from dataclasses import dataclass
from functools import cached_property

import torch


@dataclass(frozen=True)
class Trace:
    """Flat per-ray tensors of one frame, R = H * W rays in row-major pixel order (row 0 = top).

    origins / dirs [R, 3] the pixel rays (unit dirs); idx [R, K] neighbour indices into the traced points (-1 =
    empty slot); weights [R, K] attention over the neighbours and bg [R] the background's share (weights + bg sum
    to 1); fg_weights [R, K] the weights renormalised over the neighbours alone; x [R, 3] the surface point
    Σ fg_weights · p (the ray origin where no neighbour exists); active [R] bool: rays with at least one
    neighbour (the others are background, no attention evaluated); shape (H, W); non_finite_points: how many
    traced points were non-finite and treated as absent.

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
