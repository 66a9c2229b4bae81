"""Pinhole intrinsics (fx, fy, cx, cy) in pixels: plain Python, no torch, so the Blender add-on can build them
before torch is installed. core/images/cameras.py uses them for rays and projection."""
from __future__ import annotations

import math
import numbers
from dataclasses import dataclass

from core.util.errors import InputError


@dataclass(frozen=True)
class Intrinsics:
    """Pinhole intrinsics in pixels: focal lengths fx, fy and principal point (cx, cy) measured from the image's
    top-left corner (so the centre of a W x H image is (W/2, H/2))."""
    fx: float
    fy: float
    cx: float
    cy: float

    def __post_init__(self):
        for name in ("fx", "fy", "cx", "cy"):
            v = getattr(self, name)
            if isinstance(v, bool) or not isinstance(v, numbers.Real) or not math.isfinite(v):
                raise InputError(f"camera intrinsics: {name} must be a finite number of pixels, got {v!r}")
        if self.fx <= 0 or self.fy <= 0:
            raise InputError(f"camera intrinsics: focal lengths must be positive, got fx={self.fx!r}, fy={self.fy!r}")

    def scaled(self, factor: float) -> "Intrinsics":
        """The intrinsics of the image resized by `factor` (0.5 = half the pixels per side)."""
        return Intrinsics(self.fx * factor, self.fy * factor, self.cx * factor, self.cy * factor)

    def is_centred(self, height: int, width: int) -> bool:
        """True when this is the single-focal camera: fx == fy and the principal point is the image centre."""
        return self.fx == self.fy and self.cx == 0.5 * width and self.cy == 0.5 * height

    def as_list(self) -> list[float]:
        return [float(self.fx), float(self.fy), float(self.cx), float(self.cy)]
