"""The atlas's chart outlines for the Image Editor overlay: line segments in UV space read from the model file
(numpy only: the grid layout's charts from the texel map, an island atlas's islands from its island arrays), cached
per model file, and their mapping to the editor's region pixels. `ui.image_panel.draw_chart_outlines` draws them;
the geometry is `core.atlas.outlines.outline_segments`."""
from __future__ import annotations

import os

import numpy as np

from core.atlas.outlines import CELL_KEYS, chart_labels, outline_segments, segments_to_uv
from core.modelfile.pgt import PgtFile
from core.util.errors import ModelFileError

from .state import STATE

KEYS = (*CELL_KEYS, "atlas/islands/offset", "atlas/islands/orient", "atlas/texel_points")


def read_outlines(path: str) -> np.ndarray:
    """Chart outlines [S, 2, 2] float32 in UV space (v = 0 at the bottom) of the atlas of the model at `path`.
    Raises ModelFileError when the model has no atlas."""
    with PgtFile(path) as f:
        meta, names = f.meta, set(f.names)
        if "atlas/texel_points" not in names or not isinstance(meta.get("atlas"), dict):
            raise ModelFileError(f"{path}: the model has no atlas, so it has no charts to outline")
        arrays = {k: f.read(k) for k in KEYS if k in names}
    a = meta["atlas"]
    shape = tuple(arrays["atlas/texel_points"].shape[:2])
    cell = None
    if a.get("layout") != "islands":
        try:
            cell = int(a["R"]) + 2 * int(a["pad"])
        except (KeyError, TypeError, ValueError):
            raise ModelFileError(f"{path}: the atlas description lacks R / pad; re-export the model") from None
    return segments_to_uv(outline_segments(chart_labels(arrays, shape, cell)), shape)


def model_outlines(path: str) -> np.ndarray:
    """read_outlines, cached in memory until the file changes (size or modification time)."""
    st = os.stat(path)
    stamp = (st.st_size, st.st_mtime_ns)
    hit = STATE.outlines.get(path)
    if hit is not None and hit[0] == stamp:
        return hit[1]
    seg = read_outlines(path)
    STATE.outlines[path] = (stamp, seg)
    return seg


def to_region(segments_uv: np.ndarray, origin, corner) -> np.ndarray:
    """Segments in UV space [S, 2, 2] -> line vertices [2 S, 2] float32 in region pixels, given where UV (0, 0)
    (`origin`) and UV (1, 1) (`corner`) land in the region (View2D.view_to_region): the editor's pan and zoom."""
    o = np.asarray(origin, np.float32)
    scale = np.asarray(corner, np.float32) - o
    return (np.asarray(segments_uv, np.float32).reshape(-1, 2) * scale + o).astype(np.float32)
