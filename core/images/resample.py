"""Resampling a photo onto another pinhole camera (numpy only): how the dataset loader gives a split one camera
when its frames have their own intrinsics, and how it undistorts OpenCV radial-tangential lenses.

For every pixel centre of the target camera the ray's normalised coordinates (x, y) = ((u - cx) / fx,
(v - cy) / fy) are pushed through the source lens (its distortion, then its intrinsics) to the point of the
source image that saw the same ray, which is read by bilinear interpolation. This is the exact inverse mapping:
no iterative undistortion is needed, because the forward distortion model is evaluated at the target's rays.
Pixel (r, c) has its centre at (c + 0.5, r + 0.5), as everywhere in PointGT (and in COLMAP's intrinsics).
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from core.images.intrinsics import Intrinsics
from core.util.errors import InputError


@dataclass(frozen=True)
class Distortion:
    """OpenCV's radial-tangential lens model (COLMAP OPENCV / nerfstudio / instant-ngp `k1, k2, k3, p1, p2`) on
    normalised coordinates (x, y), r² = x² + y²:
        x_d = x (1 + k1 r² + k2 r⁴ + k3 r⁶) + 2 p1 x y + p2 (r² + 2 x²)
        y_d = y (1 + k1 r² + k2 r⁴ + k3 r⁶) + p1 (r² + 2 y²) + 2 p2 x y
    """
    k1: float = 0.0
    k2: float = 0.0
    k3: float = 0.0
    p1: float = 0.0
    p2: float = 0.0

    def __post_init__(self):
        for name in ("k1", "k2", "k3", "p1", "p2"):
            v = getattr(self, name)
            if isinstance(v, bool) or not isinstance(v, (int, float)) or not math.isfinite(v):
                raise InputError(f"lens distortion: {name} must be a finite number, got {v!r}")

    @property
    def is_zero(self) -> bool:
        return self.k1 == self.k2 == self.k3 == self.p1 == self.p2 == 0.0

    def folds(self, reach: float) -> bool:
        """Whether the radial scale r -> r (1 + k1 r² + k2 r⁴ + k3 r⁶) stops growing for some normalised radius
        r <= reach: the lens would then map two rays onto one image point, and no undistortion is correct."""
        r = np.linspace(0.0, float(reach), 2049)
        r2 = r * r
        slope = 1.0 + r2 * (3.0 * self.k1 + r2 * (5.0 * self.k2 + r2 * 7.0 * self.k3))
        return bool((slope <= 0.0).any() or not np.isfinite(slope).all())

    def apply(self, x: np.ndarray, y: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Undistorted normalised coordinates x, y [...] -> distorted (x_d, y_d) [...], float64. Rays far outside
        the lens's calibrated field may overflow to inf; callers treat those as outside the image."""
        x = np.asarray(x, dtype=np.float64)
        y = np.asarray(y, dtype=np.float64)
        with np.errstate(over="ignore", invalid="ignore"):
            r2 = x * x + y * y
            radial = 1.0 + r2 * (self.k1 + r2 * (self.k2 + r2 * self.k3))
            xd = x * radial + 2.0 * self.p1 * x * y + self.p2 * (r2 + 2.0 * x * x)
            yd = y * radial + self.p1 * (r2 + 2.0 * y * y) + 2.0 * self.p2 * x * y
        return xd, yd


def source_pixels(target: Intrinsics, size: tuple[int, int], source: Intrinsics,
                  distortion: Distortion | None = None, rows: tuple[int, int] | None = None
                  ) -> tuple[np.ndarray, np.ndarray]:
    """Where each pixel centre of the `size` = (h, w) target camera lies in the source image: column and row
    coordinates (px, py) [h, w] float64, continuous (pixel (r, c) spans [c, c + 1] x [r, r + 1]); rows = (r0, r1)
    limits it to those target rows ([r1 - r0, w]). Non-finite results (overflowing distortion) become -inf,
    i.e. outside the image."""
    h, w = size
    r0, r1 = rows if rows is not None else (0, h)
    u = (np.arange(w, dtype=np.float64) + 0.5 - target.cx) / target.fx
    v = (np.arange(r0, r1, dtype=np.float64) + 0.5 - target.cy) / target.fy
    x, y = np.meshgrid(u, v)
    if distortion is not None and not distortion.is_zero:
        x, y = distortion.apply(x, y)
    with np.errstate(over="ignore", invalid="ignore"):
        px = source.fx * x + source.cx
        py = source.fy * y + source.cy
    bad = ~(np.isfinite(px) & np.isfinite(py))
    px[bad] = py[bad] = -np.inf
    return px, py


def bilinear(image: np.ndarray, px: np.ndarray, py: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Sample image [H, W, C] at continuous pixel coordinates px, py [h, w] (pixel centres at +0.5) by bilinear
    interpolation; outside the image the border pixels are repeated. Returns (samples [h, w, C] float32,
    inside [h, w] bool: the point lies on the image, [0, W] x [0, H])."""
    H, W = image.shape[:2]
    inside = (px >= 0.0) & (px <= W) & (py >= 0.0) & (py <= H)
    sx = np.clip(np.nan_to_num(px, nan=-1.0, posinf=W + 1.0, neginf=-1.0), 0.5, W - 0.5) - 0.5
    sy = np.clip(np.nan_to_num(py, nan=-1.0, posinf=H + 1.0, neginf=-1.0), 0.5, H - 0.5) - 0.5
    x0 = np.minimum(np.floor(sx).astype(np.int64), W - 1)
    y0 = np.minimum(np.floor(sy).astype(np.int64), H - 1)
    x1 = np.minimum(x0 + 1, W - 1)
    y1 = np.minimum(y0 + 1, H - 1)
    fx = (sx - x0)[..., None]
    fy = (sy - y0)[..., None]
    img = np.asarray(image, dtype=np.float32)
    top = img[y0, x0] * (1.0 - fx) + img[y0, x1] * fx
    bottom = img[y1, x0] * (1.0 - fx) + img[y1, x1] * fx
    return (top * (1.0 - fy) + bottom * fy).astype(np.float32), inside


MAX_SUPERSAMPLING = 8  # samples per target pixel side when the source is denser than the target
BAND_SAMPLES = 1 << 20  # source samples computed at once (~60 MB of float64 coordinates and weights)


def resample(image: np.ndarray, source: Intrinsics, target: Intrinsics, size: tuple[int, int],
             distortion: Distortion | None = None) -> tuple[np.ndarray, float]:
    """The picture image [H, W, C] (taken through `source` with `distortion`) would be through the pinhole
    `target` camera of `size` = (h, w) at the same pose: [h, w, C] float32, and the share of target pixels whose
    ray the source saw (the others repeat the source's border). Resample premultiplied colour with its alpha
    as one array, so that edges keep no dark fringes. Where the source has more pixels per angle than the target
    (a longer focal length), each target pixel averages s x s bilinear samples, s = ceil(that ratio) up to
    MAX_SUPERSAMPLING, so that the finer photo is filtered down instead of aliased."""
    h, w = size
    ratio = max(source.fx / target.fx, source.fy / target.fy)
    s = int(min(max(math.ceil(ratio - 1e-9), 1), MAX_SUPERSAMPLING))
    fine = target if s == 1 else Intrinsics(target.fx * s, target.fy * s, target.cx * s, target.cy * s)
    out = np.empty((h, w, image.shape[2]), dtype=np.float32)
    seen = 0
    band = max(1, BAND_SAMPLES // (w * s * s))  # target rows per band: bounded work memory for any image size
    for r0 in range(0, h, band):
        r1 = min(h, r0 + band)
        px, py = source_pixels(fine, (h * s, w * s), source, distortion, rows=(r0 * s, r1 * s))
        part, inside = bilinear(image, px, py)
        if s > 1:
            part = part.reshape(r1 - r0, s, w, s, -1).mean(axis=(1, 3), dtype=np.float32)
            inside = inside.reshape(r1 - r0, s, w, s).all(axis=(1, 3))
        out[r0:r1] = part
        seen += int(inside.sum())
    return out, seen / float(h * w)
