"""The proxy mesh from a texel map (no Blender): vertices on their texels' points, UVs at the texel centres, the
face budget kept, holes and chart borders never bridged."""
from __future__ import annotations

import numpy as np
import pytest

from core.util.errors import InputError
from pointgt_blender.scene.proxy_mesh import proxy_arrays


def _texel_map(R=16, pad=2, charts=(0, 1)):
    """Two charts side by side (cells of R + 2 pad): chart 0 a plane z = 0, chart 1 a plane z = 5 (far away),
    padding NaN, with a hole of 4 x 4 texels in chart 0."""
    cell = R + 2 * pad
    tp = np.full((cell, 2 * cell, 3), np.nan, np.float32)
    i, j = np.mgrid[0:R, 0:R]
    for c in charts:
        tp[pad:pad + R, c * cell + pad:c * cell + pad + R] = np.stack([j * 0.1, i * 0.1, np.full_like(i, 5.0 * c)],
                                                                        -1)
    tp[pad + 6:pad + 10, pad + 6:pad + 10] = np.nan
    return tp, R, pad


def test_vertices_sit_on_their_texels_and_uvs_are_texel_centres():
    tp, R, pad = _texel_map()
    verts, tris, uv = proxy_arrays(tp, R, pad, target_faces=100000, stitch=0.0)
    H, W = tp.shape[:2]
    col = np.floor(uv[..., 0] * W).astype(int)
    row = np.floor((1.0 - uv[..., 1]) * H).astype(int)  # v = 0 at the bottom row
    np.testing.assert_allclose(uv[..., 0] * W - col, 0.5, atol=1e-4)
    np.testing.assert_array_equal(verts[tris], tp[row, col])  # every corner on the texel its uv names
    assert tris.min() >= 0 and tris.max() < len(verts) and uv.shape == (len(tris), 3, 2)
    # full resolution: (R - 1)^2 squares per chart minus those touching the hole, two triangles each
    assert len(tris) == 2 * (2 * (R - 1) ** 2 - 5 * 5)


def _boundary_edges(tris):
    e = np.sort(np.concatenate([tris[:, [0, 1]], tris[:, [1, 2]], tris[:, [2, 0]]]), axis=1)
    _, counts = np.unique(e, axis=0, return_counts=True)
    return int((counts == 1).sum()), int(counts.max())


def test_charts_of_one_surface_are_stitched_along_their_seam():
    """Two charts holding the left and right half of one plane (a seam 1.4 texel spacings wide between them):
    stitched, the seam's boundary edges disappear and no edge gets more than two triangles; corner UVs stay."""
    R, pad = 8, 1
    cell = R + 2 * pad
    tp = np.full((cell, 2 * cell, 3), np.nan, np.float32)
    i, j = np.mgrid[0:R, 0:R].astype(np.float32)
    tp[pad:pad + R, pad:pad + R] = np.stack([j * 0.1, i * 0.1, 0 * i], -1)
    tp[pad:pad + R, cell + pad:cell + pad + R] = np.stack([(R - 1) * 0.1 + 0.14 + j * 0.1, i * 0.1, 0 * i], -1)
    v0, t0, uv0 = proxy_arrays(tp, R, pad, target_faces=100000, stitch=0.0)
    v1, t1, uv1 = proxy_arrays(tp, R, pad, target_faces=100000)
    open0, _ = _boundary_edges(t0)
    open1, most = _boundary_edges(t1)
    assert len(v1) == len(v0) - R and open1 == open0 - 2 * (R - 1) and most == 2
    np.testing.assert_array_equal(uv1, uv0)
    assert np.isfinite(v1).all()


def test_face_budget_and_no_bridges_across_holes_or_charts():
    tp, R, pad = _texel_map()
    verts, tris, uv = proxy_arrays(tp, R, pad, target_faces=120)
    assert 0 < len(tris) <= 120
    edges = np.linalg.norm(verts[tris] - verts[np.roll(tris, 1, axis=1)], axis=-1)
    assert edges.max() < 1.5  # no triangle spans the two charts (5 apart) or the hole
    z = verts[tris][..., 2]
    assert ((z == 0) | (z == 5)).all() and (z.min(1) == z.max(1)).all()


def test_empty_or_non_finite_maps_say_so():
    tp, R, pad = _texel_map()
    with pytest.raises(InputError, match="too few"):
        proxy_arrays(np.full_like(tp, np.nan), R, pad)
    bad = tp.copy()
    bad[np.isfinite(bad).all(-1)] = np.inf
    with pytest.raises(InputError):
        proxy_arrays(bad, R, pad)
