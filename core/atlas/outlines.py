"""Island outlines of a packed atlas as an RGBA overlay for painting (numpy only: `pointgt export` reads the model
file without torch)."""
from __future__ import annotations

import numpy as np


def island_mask(arrays: dict, shape: tuple[int, int]) -> np.ndarray:
    """Pixels [H, W] bool inside an island: from the island arrays of an island atlas (cells [n, G, G] island id or
    -1, offset [I, 2] (col, row)), else (grid atlases) the texels with a surface point ('atlas/texel_points')."""
    H, W = shape
    if "atlas/islands/cells" in arrays and "atlas/islands/offset" in arrays:
        cells = np.asarray(arrays["atlas/islands/cells"]).astype(np.int64)
        off = np.asarray(arrays["atlas/islands/offset"]).astype(np.int64).reshape(-1, 2)
        mask = np.zeros((H, W), bool)
        n, rr, kk = np.nonzero(cells >= 0)
        isl = cells[n, rr, kk]
        r, c = rr + off[isl, 1], kk + off[isl, 0]
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
