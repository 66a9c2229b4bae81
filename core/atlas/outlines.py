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


# an island atlas's cell grids as stored: atlas version 7 keeps each layout chart's occupied bounding box only
# (cell_boxes, cell_crops, grid), earlier versions the whole [n, G, G] grid (cells)
CELL_KEYS = ("atlas/islands/cells", "atlas/islands/grid", "atlas/islands/cell_boxes", "atlas/islands/cell_crops")
MAX_GRID_CELLS = 1 << 28  # n x G x G of a stored atlas: far above any atlas PointGT fits (2048² images)


def cells_to_arrays(cells: np.ndarray) -> dict[str, np.ndarray]:
    """The stored form of cell grids cells [n, G, G] int (island id, -1 unused): 'atlas/islands/grid' [1] int32
    (G), 'atlas/islands/cell_boxes' [n, 4] int32 (row, col, height, width of each chart's occupied cells' bounding
    box; 0 x 0 for a chart without cells) and 'atlas/islands/cell_crops' [K] int32 (the boxes' cells, chart by chart,
    row-major). Most of a layout chart's G x G grid is unused when the charts are many pieces of different sizes."""
    cells = np.asarray(cells)
    n, G = cells.shape[0], cells.shape[1]
    boxes, crops = np.zeros((n, 4), np.int32), []
    for c in range(n):
        occ = cells[c] >= 0
        rows, cols = np.flatnonzero(occ.any(1)), np.flatnonzero(occ.any(0))
        if len(rows):
            r0, r1, c0, c1 = rows[0], rows[-1] + 1, cols[0], cols[-1] + 1
            boxes[c] = (r0, c0, r1 - r0, c1 - c0)
            crops.append(cells[c, r0:r1, c0:c1].reshape(-1))
    return {"atlas/islands/grid": np.array([G], np.int32), "atlas/islands/cell_boxes": boxes,
            "atlas/islands/cell_crops": (np.concatenate(crops) if crops else np.zeros(0)).astype(np.int32)}


def cells_from_arrays(arrays: dict) -> np.ndarray | None:
    """Cell grids [n, G, G] int64 from either stored form (`cells_to_arrays`, or the whole 'atlas/islands/cells'
    of atlas versions 2-6); None when the arrays hold neither. Raises ModelFileError on boxes outside the grid, a
    crop of the wrong length or a grid larger than any atlas (so a small damaged file never asks for huge memory)."""
    from core.util.errors import ModelFileError

    if "atlas/islands/cells" in arrays:
        cells = np.asarray(arrays["atlas/islands/cells"])
        if cells.ndim != 3 or cells.shape[1] != cells.shape[2]:
            raise ModelFileError(f"atlas: 'atlas/islands/cells' should be [n, G, G], found {cells.shape}")
        return cells.astype(np.int64)
    if not all(k in arrays for k in CELL_KEYS[1:]):
        return None
    grid, boxes = np.asarray(arrays["atlas/islands/grid"]), np.asarray(arrays["atlas/islands/cell_boxes"])
    crops = np.asarray(arrays["atlas/islands/cell_crops"]).reshape(-1)
    if grid.shape != (1,) or boxes.ndim != 2 or boxes.shape[1] != 4:
        raise ModelFileError(f"atlas: island cell arrays of the wrong shape ('atlas/islands/grid' {grid.shape}, "
                             f"should be [1]; 'atlas/islands/cell_boxes' {boxes.shape}, should be [n, 4])")
    G, n = int(grid[0]), boxes.shape[0]
    if not 1 <= G or n * G * G > MAX_GRID_CELLS:
        raise ModelFileError(f"atlas: an island cell grid of {n} x {G} x {G} cells is not one PointGT writes (at "
                             f"most {MAX_GRID_CELLS}); the file is damaged")
    b = boxes.astype(np.int64)
    if (b < 0).any() or (b[:, 0] + b[:, 2] > G).any() or (b[:, 1] + b[:, 3] > G).any():
        raise ModelFileError(f"atlas: 'atlas/islands/cell_boxes' holds boxes outside the {G} x {G} cell grid; the "
                             "file is damaged")
    sizes = b[:, 2] * b[:, 3]
    if int(sizes.sum()) != len(crops):
        raise ModelFileError(f"atlas: 'atlas/islands/cell_crops' holds {len(crops)} cells, its boxes "
                             f"{int(sizes.sum())}; the file is damaged")
    cells = np.full((n, G, G), -1, np.int64)
    start = np.concatenate([[0], np.cumsum(sizes)])
    for c in range(n):
        r0, c0, h, w = (int(v) for v in b[c])
        cells[c, r0:r0 + h, c0:c0 + w] = crops[start[c]:start[c + 1]].reshape(h, w)
    return cells


def island_mask(arrays: dict, shape: tuple[int, int]) -> np.ndarray:
    """Pixels [H, W] bool inside an island: from the island arrays of an island atlas (its cell grids in either
    stored form, `cells_from_arrays`; offset [I, 2] (col, row), orient [I] when present), else (grid atlases) the
    texels with a surface point ('atlas/texel_points')."""
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
    cells = cells_from_arrays(arrays) if "atlas/islands/offset" in arrays else None
    if cells is not None:
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
