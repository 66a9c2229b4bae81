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
