"""The Image Editor's chart outlines, without Blender: UV segments mapped through the editor's pan and zoom."""
from __future__ import annotations

import numpy as np

from pointgt_blender.scene.chart_outlines import to_region


def test_uv_segments_map_through_the_editors_pan_and_zoom():
    seg = np.array([[[0.0, 0.0], [1.0, 1.0]], [[0.25, 0.5], [0.25, 0.75]]], np.float32)
    # UV (0, 0) at region pixel (100, 40), UV (1, 1) at (612, 296): a 512 x 256 image at zoom 1
    v = to_region(seg, (100, 40), (612, 296))
    assert v.shape == (4, 2) and v.dtype == np.float32
    np.testing.assert_allclose(v, [[100, 40], [612, 296], [228, 168], [228, 232]])


def test_island_outlines_follow_each_islands_orientation(tmp_path):
    """The overlay of an island atlas outlines its islands as they are placed, turned or mirrored ones included
    (the island arrays' orientations): the same segments as `core.atlas.outlines` from every island array."""
    from core.atlas.outlines import cells_from_arrays, chart_labels, outline_segments, segments_to_uv
    from core.modelfile import load_pgt, save_pgt
    from pointgt_blender.scene.chart_outlines import read_outlines
    from tests.helpers.tiny import save_tiny

    arrays, meta = load_pgt(save_tiny(tmp_path / "m.pgt", "fast"))
    assert meta["atlas"]["layout"] == "islands"
    orient = np.asarray(arrays["atlas/islands/orient"]).copy()
    cells = cells_from_arrays(arrays)
    big = int(np.bincount(cells[cells >= 0]).argmax())  # the largest island, turned by a quarter
    orient[big] = (orient[big] + 1) % 4 + (orient[big] // 4) * 4
    arrays["atlas/islands/orient"] = orient.astype(np.asarray(arrays["atlas/islands/orient"]).dtype)
    path = save_pgt(tmp_path / "turned.pgt", arrays, meta, backup=False,
                    allow_nonfinite=[n for n in arrays if n.startswith("atlas/texel")])
    shape = tuple(arrays["atlas/texel_points"].shape[:2])
    want = segments_to_uv(outline_segments(chart_labels(arrays, shape)), shape)
    upright = dict(arrays, **{"atlas/islands/orient": np.zeros_like(orient)})
    assert not np.array_equal(want, segments_to_uv(outline_segments(chart_labels(upright, shape)), shape))
    np.testing.assert_array_equal(read_outlines(str(path)), want)
