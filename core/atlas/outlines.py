"""Island outlines of a packed atlas as an RGBA overlay for painting (numpy only: `pointgt export` reads the model
file without torch)."""
from __future__ import annotations

import numpy as np

# the eight symmetries of the texel grid (four turns by 90°, then the same after a mirror): an island with
# orientation q maps its chart texel coordinates t = (col, row) to ORIENT_NP[q] @ t (+ its offset)
ORIENT_NP = np.array([[[1, 0], [0, 1]], [[0, -1], [1, 0]], [[-1, 0], [0, -1]], [[0, 1], [-1, 0]],
                      [[1, 0], [0, -1]], [[-1, 0], [0, 1]], [[0, 1], [1, 0]], [[0, -1], [-1, 0]]], np.int64)


def cell_pixels(cols: np.ndarray, rows: np.ndarray, offset: np.ndarray, orient: np.ndarray
                ) -> tuple[np.ndarray, np.ndarray]:
    """Image pixels (col [K], row [K]) of chart cells (cols, rows [K] int) of islands with offset [K, 2] (col, row)
    and orientation orient [K] (0..7, ORIENT_NP): the pixel holding the cell's centre once placed."""
    m = ORIENT_NP[np.asarray(orient, np.int64)]                                   # [K, 2, 2]
    cx, cy = 2 * np.asarray(cols, np.int64) + 1, 2 * np.asarray(rows, np.int64) + 1  # centres, doubled: exact
    off = np.asarray(offset, np.int64).reshape(-1, 2)
    px = m[:, 0, 0] * cx + m[:, 0, 1] * cy + 2 * off[:, 0]
    py = m[:, 1, 0] * cx + m[:, 1, 1] * cy + 2 * off[:, 1]
    return (px - 1) // 2, (py - 1) // 2


def island_mask(arrays: dict, shape: tuple[int, int]) -> np.ndarray:
    """Pixels [H, W] bool inside an island: from the island arrays of an island atlas (cells [n, G, G] island id or
    -1, offset [I, 2] (col, row), orient [I] when present), else (grid atlases) the texels with a surface point
    ('atlas/texel_points')."""
    H, W = shape
    if "atlas/islands/cells" in arrays and "atlas/islands/offset" in arrays:
        cells = np.asarray(arrays["atlas/islands/cells"]).astype(np.int64)
        off = np.asarray(arrays["atlas/islands/offset"]).astype(np.int64).reshape(-1, 2)
        mask = np.zeros((H, W), bool)
        n, rr, kk = np.nonzero(cells >= 0)
        isl = cells[n, rr, kk]
        orient = np.asarray(arrays.get("atlas/islands/orient", np.zeros(len(off)))).astype(np.int64).reshape(-1)
        c, r = cell_pixels(kk, rr, off[isl], orient[isl])
        ok = (r >= 0) & (r < H) & (c >= 0) & (c < W)
        mask[r[ok], c[ok]] = True
        return mask
    return np.isfinite(np.asarray(arrays["atlas/texel_points"])).all(-1)


def outline_overlay(mask: np.ndarray, colour=(1.0, 0.0, 1.0), width: int = 1) -> np.ndarray:
    """RGBA overlay [H, W, 4] in [0, 1]: `colour`, opaque, on the island pixels within `width` pixels of the
    island's edge (a 4-neighbour outside it); transparent elsewhere. mask [H, W] bool."""
    m = np.asarray(mask, bool)
    edge = np.zeros_like(m)
    inner = m.copy()
    for _ in range(max(int(width), 1)):
        p = np.pad(inner, 1, constant_values=False)
        eroded = inner & p[:-2, 1:-1] & p[2:, 1:-1] & p[1:-1, :-2] & p[1:-1, 2:]
        edge |= inner & ~eroded
        inner = eroded
    out = np.zeros((*m.shape, 4), np.float32)
    out[edge, :3] = np.asarray(colour, np.float32)
    out[edge, 3] = 1.0
    return out
