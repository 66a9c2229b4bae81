"""Chart outlines as line segments (core/atlas/outlines.py): the geometry the add-on draws over the atlas in the
Image Editor, checked against a brute-force list of pixel edges."""
from __future__ import annotations

import numpy as np
import pytest

from core.atlas.outlines import chart_labels, outline_segments, segments_to_uv


def _unit_edges_brute(lab: np.ndarray) -> set:
    """Every unit pixel edge between different labels where at least one side is a chart (-1 and the border are
    outside), as ((x0, y0), (x1, y1))."""
    H, W = lab.shape
    at = lambda r, c: lab[r, c] if 0 <= r < H and 0 <= c < W else -1  # noqa: E731
    out = set()
    for r in range(-1, H + 1):
        for c in range(-1, W + 1):
            a = at(r, c)
            for dr, dc in ((0, 1), (1, 0)):
                b = at(r + dr, c + dc)
                if a != b and max(a, b) >= 0:
                    out.add(((c + 1, r), (c + 1, r + 1)) if dc else ((c, r + 1), (c + 1, r + 1)))
    return out


def _unit_edges(segments: np.ndarray) -> list:
    out = []
    for (x0, y0), (x1, y1) in segments.astype(int).tolist():
        assert x0 == x1 or y0 == y1, "segments are axis-aligned"
        if x0 == x1:
            out += [((x0, y), (x0, y + 1)) for y in range(min(y0, y1), max(y0, y1))]
        else:
            out += [((x, y0), (x + 1, y0)) for x in range(min(x0, x1), max(x0, x1))]
    return out


def test_a_rectangle_is_four_segments_on_its_border():
    m = np.zeros((8, 9), bool)
    m[2:6, 3:8] = True  # rows 2..5, columns 3..7
    seg = outline_segments(m)
    assert seg.shape == (4, 2, 2)
    boxes = {tuple(map(tuple, s)) for s in seg.astype(int).tolist()}
    assert boxes == {((3, 2), (3, 6)), ((8, 2), (8, 6)), ((3, 2), (8, 2)), ((3, 6), (8, 6))}


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_random_charts_match_the_brute_force_edges_each_once(seed):
    rng = np.random.default_rng(seed)
    lab = rng.integers(-1, 3, size=(11, 13))
    lab[rng.random(lab.shape) < 0.3] = -1
    lab[:, 0] = 2  # a chart on the image's border: its outline runs along the border
    seg = outline_segments(lab)
    edges = _unit_edges(seg)
    assert len(edges) == len(set(edges)), "no edge is drawn twice"
    assert set(edges) == _unit_edges_brute(lab)


def test_merged_runs_and_charts_touching_each_other():
    lab = np.full((4, 6), -1)
    lab[1:3, 0:3] = 0
    lab[1:3, 3:6] = 1  # two charts side by side: one shared edge between them, drawn once
    seg = outline_segments(lab)
    assert len(seg) == 2 + 2 + 1  # top and bottom (one run each, over both charts), left, right, the shared edge
    assert ((3, 1), (3, 3)) in {tuple(map(tuple, s)) for s in seg.astype(int).tolist()}
    assert len(outline_segments(np.zeros((5, 5), bool))) == 0 and len(outline_segments(np.ones((3, 3), bool))) == 4


def test_uv_space_has_v_up():
    uv = segments_to_uv(np.array([[[0, 0], [4, 2]]], np.float32), (2, 4))
    np.testing.assert_allclose(uv, [[[0.0, 1.0], [1.0, 0.0]]])


def test_grid_labels_follow_the_cells_and_islands_their_offsets():
    tp = np.full((6, 12, 3), np.nan, np.float32)
    tp[1:5, 1:5] = 0.0
    tp[1:5, 7:11] = 1.0
    lab = chart_labels({"atlas/texel_points": tp}, (6, 12), cell=6)
    assert set(np.unique(lab)) == {-1, 0, 1} and (lab[1:5, 7:11] == 1).all() and (lab[0] == -1).all()
    assert len(outline_segments(lab)) == 8  # two squares
    cells = np.full((2, 2, 2), -1)
    cells[0, 0, :] = 0
    cells[1, :, 0] = 1
    isl = chart_labels({"atlas/islands/cells": cells, "atlas/islands/offset": np.array([[0, 0], [3, 1]])}, (4, 5))
    assert isl[0, 0] == 0 and isl[0, 1] == 0 and isl[1, 3] == 1 and isl[2, 3] == 1 and (isl >= 0).sum() == 4
