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
    return chart_labels(arrays, shape) >= 0


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


def chart_labels(arrays: dict, shape: tuple[int, int], cell: int | None = None) -> np.ndarray:
    """Chart id of every pixel [H, W] int64, -1 outside every chart: the island of an island atlas (as
    `island_mask`), else the grid cell (`cell` = R + 2 pad texels per chart side) of every texel with a surface
    point; without `cell`, all such texels are chart 0."""
    H, W = shape
    if "atlas/islands/cells" in arrays and "atlas/islands/offset" in arrays:
        cells = np.asarray(arrays["atlas/islands/cells"]).astype(np.int64)
        off = np.asarray(arrays["atlas/islands/offset"]).astype(np.int64).reshape(-1, 2)
        lab = np.full((H, W), -1, np.int64)
        n, rr, kk = np.nonzero(cells >= 0)
        isl = cells[n, rr, kk]
        orient = np.asarray(arrays.get("atlas/islands/orient", np.zeros(len(off)))).astype(np.int64).reshape(-1)
        c, r = cell_pixels(kk, rr, off[isl], orient[isl])
        ok = (r >= 0) & (r < H) & (c >= 0) & (c < W)
        lab[r[ok], c[ok]] = isl[ok]
        return lab
    valid = np.isfinite(np.asarray(arrays["atlas/texel_points"])).all(-1)
    if cell is None or cell < 1:
        return np.where(valid, 0, -1).astype(np.int64)
    rows, cols = np.mgrid[0:H, 0:W]
    return np.where(valid, (rows // cell) * max(W // cell, 1) + cols // cell, -1).astype(np.int64)


def _runs(edge: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Maximal runs of True along axis 1 of edge [A, B]: (row [S], first [S], one past the last [S])."""
    d = np.diff(np.pad(edge, ((0, 0), (1, 1))).astype(np.int8), axis=1)
    r0, s = np.nonzero(d == 1)
    r1, e = np.nonzero(d == -1)  # np.nonzero is row-major, so starts and ends pair up in order
    assert np.array_equal(r0, r1)
    return r0, s, e


def outline_segments(labels: np.ndarray) -> np.ndarray:
    """Chart outlines as line segments [S, 2, 2] float32, each ((x0, y0), (x1, y1)) in pixel-corner units (x to
    the right from the left edge, y down from the top edge; pixel (r, c) spans [c, c+1] x [r, r+1]): the edges
    between two 4-neighbouring pixels of different charts, or of a chart and the outside (-1) or the image's
    border. Collinear unit edges are merged into one segment. labels [H, W] int (-1 = no chart) or bool (True =
    inside)."""
    lab = np.asarray(labels)
    lab = np.where(lab, 0, -1) if lab.dtype == bool else lab.astype(np.int64)
    if lab.ndim != 2:
        raise ValueError(f"labels must be [H, W]; got {list(lab.shape)}")
    p = np.pad(lab, 1, constant_values=-1)
    # vertical edges at x = c (between columns c-1 and c), rows r: [W + 1, H] after transposing
    v = (p[1:-1, :-1] != p[1:-1, 1:]) & ((p[1:-1, :-1] >= 0) | (p[1:-1, 1:] >= 0))
    x, y0, y1 = _runs(v.T)
    vert = np.stack([np.stack([x, y0], -1), np.stack([x, y1], -1)], 1)
    # horizontal edges at y = r (between rows r-1 and r), columns c: [H + 1, W]
    h = (p[:-1, 1:-1] != p[1:, 1:-1]) & ((p[:-1, 1:-1] >= 0) | (p[1:, 1:-1] >= 0))
    y, x0, x1 = _runs(h)
    hor = np.stack([np.stack([x0, y], -1), np.stack([x1, y], -1)], 1)
    return np.concatenate([vert, hor]).astype(np.float32).reshape(-1, 2, 2)


def segments_to_uv(segments: np.ndarray, shape: tuple[int, int]) -> np.ndarray:
    """Pixel-corner segments [S, 2, 2] of an [H, W] image -> UV coordinates [S, 2, 2] float32 (u = x / W,
    v = 1 - y / H: Blender's UV space, v = 0 at the image's bottom)."""
    H, W = shape
    s = np.asarray(segments, np.float32).reshape(-1, 2, 2)
    return np.stack([s[..., 0] / W, 1.0 - s[..., 1] / H], -1).astype(np.float32)
