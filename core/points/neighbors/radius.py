"""The pixel radius cap of the screen metrics: a point is a candidate for a query pixel only within max_radius_px
of it. "auto" (0 in a config) = _AUTO_FACTOR × the radius of a disc holding K points at the median projected
density, at least _AUTO_MIN_PX; inf (a negative number in a config) = no cap."""
from __future__ import annotations

import math
import numbers

import torch

from core.util.errors import InputError

_AUTO_FACTOR = 2.0  # "auto" cap = this × the radius holding K points at the median projected density ...
_AUTO_MIN_PX = 1.5  # ... and at least this many pixels
_DENSITY_CELL_POINTS = 16  # density cells hold this many points on average if spread over the whole frame


def check_radius(value) -> float | str:
    """max_radius_px -> "auto", a positive float, or inf (no cap). 0 also means auto and a negative number no cap
    (the config spelling: JSON has no infinity)."""
    if isinstance(value, str):
        if value != "auto":
            raise InputError(f"neighbour search: max_radius_px must be 'auto' or a number of pixels, got {value!r}")
        return value
    if isinstance(value, bool) or not isinstance(value, numbers.Real) or math.isnan(value):
        raise InputError(f"neighbour search: max_radius_px must be 'auto' or a number of pixels, got {value!r}")
    if value == 0:
        return "auto"
    return math.inf if value < 0 else float(value)


def median_density(px: torch.Tensor, height: int, width: int) -> float:
    """Projected points per square pixel where the object is: px [M, 2] (col, row) -> the median over points of
    the density of the grid cell holding the point. Weighting by points, not cells, lets interior cells outvote
    the partial cells along the silhouette. Cells are sized to hold ~_DENSITY_CELL_POINTS points: first at the
    density of the whole frame, then once more at the density this first pass found (objects smaller than the
    frame)."""
    m = px.shape[0]
    if m == 0:
        return 0.0
    density = m / ((width + 2.0) * (height + 2.0))  # candidates lie inside the frame ± 1 px
    for _ in range(2):
        side = min(math.sqrt(_DENSITY_CELL_POINTS / density), width + 2.0, height + 2.0)
        cols = int((width + 2.0) // side) + 1
        cell = ((px[:, 1] + 1.0) // side).long() * cols + ((px[:, 0] + 1.0) // side).long()
        counts = torch.bincount(cell.clamp(min=0))
        density = float(counts[cell].to(torch.float64).median()) / (side * side)
    return density


def auto_radius_px(density: float, k: int) -> float:
    """The "auto" pixel radius cap: _AUTO_FACTOR × the radius of a disc holding k points at `density` points per
    square pixel, at least _AUTO_MIN_PX. An interior pixel then sees ≈ _AUTO_FACTOR² · k candidates."""
    if not density > 0:
        return _AUTO_MIN_PX
    return max(_AUTO_MIN_PX, _AUTO_FACTOR * math.sqrt(k / (math.pi * density)))
