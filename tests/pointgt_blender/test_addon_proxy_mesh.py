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
    verts, tris, uv = proxy_arrays(tp, R, pad, target_faces=100000, stitch=0.0, close=0, fill=0)
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
    v0, t0, uv0 = proxy_arrays(tp, R, pad, target_faces=100000, stitch=0.0, fill=0)
    v1, t1, uv1 = proxy_arrays(tp, R, pad, target_faces=100000, fill=0)
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


def _open_edges(tris):
    """Undirected edges used by one triangle [B, 2], and whether every edge of two triangles runs opposite ways in
    them (consistent orientation)."""
    d = np.concatenate([tris[:, [0, 1]], tris[:, [1, 2]], tris[:, [2, 0]]])
    e = np.sort(d, axis=1)
    u, inv, counts = np.unique(e, axis=0, return_inverse=True, return_counts=True)
    forward = (d[:, 0] < d[:, 1]).astype(int)
    fw = np.bincount(inv.reshape(-1), weights=forward, minlength=len(u))
    consistent = bool(((counts != 2) | (fw == 1)).all())
    return u[counts == 1], consistent


def _seam_map(R=12, pad=2, mirror=False, jag=True):
    """One plane (x in [0, 2.4), y in [0, 1.2)) cut into two charts at x = 1.2: chart 0 the left half, chart 1 the
    right half sampled on its own grid (offset by a third of a texel, optionally mirrored in the atlas), each
    half's texel mask jagged along the seam (every other row two texels short), as atlas charts are."""
    cell = R + 2 * pad
    h = 1.2 / R
    tp = np.full((cell, 2 * cell, 3), np.nan, np.float32)
    i, j = np.mgrid[0:R, 0:R].astype(np.float32)
    left = np.stack([j * h, i * h, 0 * i], -1)
    right = np.stack([1.2 + h / 3 + j * h, i * h + h / 3, 0 * i], -1)
    if jag:
        left[1::2, -2:] = np.nan       # notches along the seam, on both sides
        right[::2, :2] = np.nan
    if mirror:
        right = right[:, ::-1]
    tp[pad:pad + R, pad:pad + R] = left
    tp[pad:pad + R, cell + pad:cell + pad + R] = right
    return tp, R, pad


@pytest.mark.parametrize("mirror", [False, True])
def test_jagged_seams_between_charts_close_into_one_piece(mirror):
    """Cracks measured as open edges: without closing, the two halves are two pieces with a jagged crack between
    them; with the defaults they are one piece whose only open edges are the plane's outer border, consistently
    oriented (also when one chart is mirrored in the atlas), manifold, with finite vertices."""
    from pointgt_blender.scene.proxy_mesh import boundary_loops, mesh_components

    tp, R, pad = _seam_map(mirror=mirror)
    v0, t0, _ = proxy_arrays(tp, R, pad, target_faces=100000, stitch=0.0, close=0, fill=0)
    v1, t1, uv1 = proxy_arrays(tp, R, pad, target_faces=100000)
    comp0, comp1 = mesh_components(len(v0), t0), mesh_components(len(v1), t1)
    assert len(np.unique(comp0)) == 2 and len(np.unique(comp1[np.unique(t1)])) == 1
    open0, _ = _open_edges(t0)
    open1, consistent = _open_edges(t1)
    _, most = _boundary_edges(t1)
    assert consistent and most == 2 and np.isfinite(v1).all() and np.isfinite(uv1).all()
    # the crack is gone: one loop of open edges (the plane's outline) holds them all, and the mesh covers the
    # strip between the halves and their notches (0.5 of the plane's 2.88) without overlapping (no more than 2.88)
    loops = boundary_loops(t1)
    assert len(loops) == 1 and len(loops[0]) == len(open1) < len(open0)
    area = lambda v, t: 0.5 * np.linalg.norm(np.cross(v[t[:, 1]] - v[t[:, 0]], v[t[:, 2]] - v[t[:, 0]]),  # noqa
                                             axis=1).sum()
    assert area(v0, t0) + 0.45 < area(v1, t1) <= 2.4 * 1.2


def test_holes_inside_a_chart_are_closed_and_keep_the_charts_texture():
    """The 4 x 4 hole of chart 0: closed by the defaults with points in the plane; the faces over it map into the
    chart's own texels (not across the atlas), so painting there paints that part of the chart."""
    tp, R, pad = _texel_map()
    v0, t0, _ = proxy_arrays(tp, R, pad, target_faces=100000, stitch=0.0, close=0, fill=0)
    v1, t1, uv1 = proxy_arrays(tp, R, pad, target_faces=100000)
    assert len(_open_edges(t1)[0]) == len(_open_edges(t0)[0]) - 4 * 5  # the hole's 20 open edges are gone
    z = v1[t1][..., 2]
    assert ((z == 0) | (z == 5)).all() and (z.min(1) == z.max(1)).all()  # charts 5 apart never joined
    H, W = tp.shape[:2]
    cell = R + 2 * pad
    col = np.floor(uv1[..., 0] * W).astype(int)
    assert (col.min(1) // cell == col.max(1) // cell).all()  # every face's UVs inside one chart's cell
    on_hole = (np.abs(v1[t1].mean(1)[:, :2] - 0.1 * 7.5) < 0.2).all(1) & (z[:, 0] == 0)
    assert on_hole.sum() >= 8


@pytest.mark.parametrize("scale", [1e-6, 1e6])
def test_extreme_scales_give_the_same_mesh(scale):
    tp, R, pad = _seam_map()
    v, t, uv = proxy_arrays(tp, R, pad, target_faces=100000)
    vs, ts, uvs = proxy_arrays(tp * np.float32(scale), R, pad, target_faces=100000)
    assert np.isfinite(vs).all() and np.array_equal(t, ts) and np.array_equal(uv, uvs)
    np.testing.assert_allclose(vs, v * scale, rtol=1e-4, atol=1e-6 * scale)


def _island_map(h=0.1):
    """An island atlas (one square cell of 40 texels, no padding of cells): one plane (x in [0, 2.6), y in
    [0, 2)) cut at x = 1.3 into two islands placed 6 texels apart in the image — the left half at columns 2..14,
    the right half at columns 21..34, rows 2..21 — NaN elsewhere."""
    tp = np.full((40, 40, 3), np.nan, np.float32)
    r, c = np.mgrid[0:40, 0:40].astype(np.float32)
    left = (r >= 2) & (r <= 21) & (c >= 2) & (c <= 14)
    right = (r >= 2) & (r <= 21) & (c >= 21) & (c <= 34)
    tp[left] = np.stack([(c - 2) * h, (r - 2) * h, 0 * r], -1)[left]
    tp[right] = np.stack([(c - 21 + 13) * h, (r - 2) * h, 0 * r], -1)[right]
    return tp


def test_island_meshes_reach_their_borders_and_weld_across_the_seam():
    """Sampled every 5 texels, neither island's grid of samples reaches its border (the nearest sampled columns
    are 4 texels inside both borders, so the seam between the meshes would be 1.8 steps wide): the squares the
    borders cross are cut at the border, every border row and column carries vertices, the two islands weld into
    one piece that covers the plane, manifold and within the face budget; each face's UVs stay in one island."""
    from pointgt_blender.scene.proxy_mesh import mesh_components

    tp = _island_map()
    v0, t0, uv0 = proxy_arrays(tp, 40, 0, target_faces=80, stitch=0.0, fill=0)
    v, t, uv = proxy_arrays(tp, 40, 0, target_faces=80, fill=0)
    col = np.floor(uv[..., 0] * 40).astype(int)
    row = np.floor((1.0 - uv[..., 1]) * 40).astype(int)
    assert {2, 14, 21, 34} <= set(col.reshape(-1).tolist()) and {2, 21} <= set(row.reshape(-1).tolist())
    assert len(np.unique(mesh_components(len(v0), t0))) == 2
    assert len(np.unique(mesh_components(len(v), t)[np.unique(t)])) == 1
    _, most = _boundary_edges(t)
    assert most == 2 and 0 < len(t) <= 80 and np.isfinite(v).all()
    area = 0.5 * np.linalg.norm(np.cross(v[t[:, 1]] - v[t[:, 0]], v[t[:, 2]] - v[t[:, 0]]), axis=1).sum()
    assert 0.9 * 2.6 * 1.9 < area <= 2.6 * 1.9 + 1e-5  # rows 2..21 span 1.9
    assert ((col.min(1) <= 14) == (col.max(1) <= 14)).all()  # no face's UVs span the two islands
    np.testing.assert_array_equal(v0[t0], tp[np.floor((1.0 - uv0[..., 1]) * 40).astype(int),
                                             np.floor(uv0[..., 0] * 40).astype(int)])  # corners on their texels


def test_island_proxy_keeps_to_the_face_budget():
    tp = _island_map(h=0.01)
    for target in (40, 120, 400):
        v, t, uv = proxy_arrays(tp, 40, 0, target_faces=target)
        assert 0 < len(t) <= target and np.isfinite(v).all() and np.isfinite(uv).all()


def test_island_texels_that_share_a_point_give_no_overlapping_vertices():
    """The island texel map's nearest-sample fallback gives texels the same surface point (here the left island's
    border column repeats a sampled column inside it, and a border texel of the right island one of the left):
    Surface Deform refuses a target with overlapping vertices, so the proxy has none, and no triangle with
    coincident or collinear corners; it stays manifold and one piece."""
    from pointgt_blender.scene.proxy_mesh import mesh_components

    tp = _island_map()
    tp[2:22, 14] = tp[2:22, 10]
    tp[10, 21] = tp[10, 10]
    v, t, uv = proxy_arrays(tp, 40, 0, target_faces=80, fill=0)
    assert len(np.unique(v, axis=0)) == len(v)
    side = np.linalg.norm(v[t] - v[t[:, [1, 2, 0]]], axis=-1)
    twice_area = np.linalg.norm(np.cross(v[t[:, 1]] - v[t[:, 0]], v[t[:, 2]] - v[t[:, 0]]), axis=1)
    assert side.min() > 0 and (twice_area > 1e-6 * side.max(1)).all()
    _, most = _boundary_edges(t)
    assert most == 2 and len(np.unique(mesh_components(len(v), t)[np.unique(t)])) == 1


def test_island_fragments_far_off_the_surface_are_left_out_and_near_ones_kept():
    """A small island meshed from stray surface points far off the surface (1000 edges above the plane) is left
    out of the proxy; a small island 6 edges above it (a small part of the object, too far to weld) stays."""
    from pointgt_blender.scene.proxy_mesh import mesh_components

    h = 0.1
    tp = np.full((40, 40, 3), np.nan, np.float32)
    r, c = np.mgrid[0:40, 0:40].astype(np.float32)
    plane = (r >= 2) & (r <= 31) & (c >= 2) & (c <= 31)
    near = (r >= 34) & (r <= 37) & (c >= 2) & (c <= 5)
    far = (r >= 34) & (r <= 37) & (c >= 10) & (c <= 13)
    tp[plane] = np.stack([(c - 2) * h, (r - 2) * h, 0 * r], -1)[plane]
    tp[near] = np.stack([(c - 2) * h, (r - 34) * h, 0 * r + 6 * h], -1)[near]
    tp[far] = np.stack([(c - 10) * h, (r - 34) * h, 0 * r + 1000 * h], -1)[far]
    v, t, uv = proxy_arrays(tp, 40, 0, target_faces=100000, fill=0)
    comp = mesh_components(len(v), t)
    assert len(np.unique(comp[np.unique(t)])) == 2 and len(v) == len(np.unique(t))
    assert float(v[:, 2].max()) == pytest.approx(6 * h) and np.isfinite(uv).all()
    col = np.floor(uv[..., 0] * 40).astype(int)
    assert not ((col >= 10) & (col <= 13) & (np.floor((1 - uv[..., 1]) * 40) >= 34)).any()  # no face of it
    # the same fragment in a map of its own size is the map: kept
    v2, t2, _ = proxy_arrays(np.where(far[..., None], tp, np.nan), 40, 0, fill=0)
    assert len(t2) > 0
