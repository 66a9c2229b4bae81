"""Neighbour search for rays: the K points each ray attends to (method.md §1), the hot path of PAPR.

Three metrics, all returning `Neighbors(idx [R, K] int64, dist [R, K] float32)`, sorted ascending, where a ray
with fewer than K candidates is padded with idx -1 and dist +inf (`.valid` [R, K] bool says which are real):

- "perpendicular" (paper / PAPR): ‖(p−o) − ((p−o)·d) d‖, only points in front of the origin ((p−o)·d > 0).
- "screen" (reference "knn_frustum"): project with the camera, keep points in front and inside the frame ± 1 px,
  K nearest in pixel space to each query pixel. dist in pixels.
- "screen_depth" (reference "d2r_z"): as "screen" but ranked by pixel distance × depth / focal, which is ≈ the
  perpendicular distance (world units).

Pixel radius cap (screen metrics): a point is a candidate for a query pixel only if its projected distance is
≤ max_radius_px. A ray whose nearest projected point is farther than a few pixels misses the object: the
attention's background slot takes it, and the renderer can skip shading it. "auto" (the default) sets the cap to
2 × the radius of a disc holding K points at the median projected density (at least 1.5 px), so an interior pixel
sees ≈ 4 K candidates; inf means no cap (the reference's behaviour).

Points with a non-finite coordinate are absent; so is any candidate whose distance is not finite.
Indices are not differentiable and `dist` is detached: gather the points with `idx` to get gradients.

Layout: the result type and input checks (`base.py`); one backend per file, all exact w.r.t. the definition
above (tests compare each with a plain-torch brute force): chunked brute force, the reference (`brute.py`,
backend "torch"), a k-d tree with an exact re-rank for uncapped searches on CPU tensors (`kdtree.py`), a pixel-space
cell grid in pure torch for capped screen searches on any device (`grid.py`), the same grid as one compiled loop
(`compiled.py`, numba, CPU); the radius rule (`radius.py`); the indexes that check inputs and pick a backend
("auto": compiled, grid, kdtree, torch in that order of fit; `index.py`); and the model's selector (`select.py`).
The benchmark: `python -m tools.bench.neighbors`.
"""
from __future__ import annotations

from core.points.neighbors.base import BACKENDS, METHODS, Neighbors
from core.points.neighbors.index import PerpendicularIndex, ScreenIndex, rays_knn_perpendicular, screen_knn
from core.points.neighbors.radius import auto_radius_px
from core.points.neighbors.select import select_neighbors

__all__ = ["BACKENDS", "METHODS", "Neighbors", "PerpendicularIndex", "ScreenIndex", "auto_radius_px",
           "rays_knn_perpendicular", "screen_knn", "select_neighbors"]
