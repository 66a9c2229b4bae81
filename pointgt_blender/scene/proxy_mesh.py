"""A surface proxy mesh made from the model's texel map (the canonical 3-D point of every atlas texel): visible in
Solid, Material Preview and EEVEE/Cycles, UV-mapped into the atlas image (so Blender's own Texture Paint lands in
the atlas the neural render uses), and a deformer for the points: a Surface Deform modifier bound at rest lets
anything that moves the proxy (Automatic Weights, weight painting, shape keys, cloth) move the points.

The mesh: atlas texels sampled every `s` texels inside each chart (s chosen so the proxy has at most
`target_faces` triangles), two triangles per grid square whose four corners lie on the surface and whose edges
are not much longer than the median edge (a square across a hole or a fold is skipped). Each vertex sits exactly
on its texel's point and has that texel's centre as UV, so painting the proxy writes the texels that the neural
render looks up there. Chart pieces are stitched where their borders meet (boundary vertices of two charts
that are each other's nearest merge), so cracks between charts close where the sampling allows.
This module needs only numpy; `proxy` makes the Blender objects.
"""
from __future__ import annotations

import math

import numpy as np

from core.modelfile.pgt import PgtFile
from core.util.errors import InputError, ModelFileError

TEXELS = "atlas/texel_points"


def read_texel_map(path: str) -> tuple[np.ndarray, int, int]:
    """texel_points [H, W, 3] float32 (NaN where no surface), R (texels per chart side) and pad of the model at
    `path`. Raises ModelFileError when the model has no atlas."""
    with PgtFile(path) as f:
        meta = f.meta
        if TEXELS not in f.names or not isinstance(meta.get("atlas"), dict):
            raise ModelFileError(f"{path}: the model has no atlas (no texel map), so no proxy can be made; fit one "
                                 f"with `pointgt atlas` and re-import")
        tex = f.read(TEXELS)
    a = meta["atlas"]
    if a.get("layout") == "islands":
        # islands packed into one square image: the whole image is one "chart" (texels between islands are NaN,
        # so no face bridges two islands)
        if tex.ndim != 3 or tex.shape[2] != 3 or tex.shape[0] != tex.shape[1] or tex.shape[0] < 2:
            raise ModelFileError(f"{path}: '{TEXELS}' {list(tex.shape)} is not a square island atlas; re-export "
                                 "the model")
        return tex.astype(np.float32, copy=False), int(tex.shape[0]), 0
    try:
        R, pad = int(a["R"]), int(a["pad"])
    except (KeyError, TypeError, ValueError):
        raise ModelFileError(f"{path}: the atlas description lacks R / pad; re-export the model") from None
    if tex.ndim != 3 or tex.shape[2] != 3 or R < 2 or pad < 0 or tex.shape[0] % (R + 2 * pad) \
            or tex.shape[1] % (R + 2 * pad):
        raise ModelFileError(f"{path}: '{TEXELS}' {list(tex.shape)} does not fit charts of {R} texels with {pad} "
                             f"padding; re-export the model")
    return tex.astype(np.float32, copy=False), R, pad


def proxy_arrays(texel_points: np.ndarray, R: int, pad: int, target_faces: int = 4000,
                 max_edge: float = 4.0, stitch: float = 1.5) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Triangle mesh of the texel map. texel_points [H, W, 3] (NaN = no surface), charts of R x R texels in cells
    of R + 2 pad. Returns vertices [V, 3] float32 (the texels' points), triangles [F, 3] int32 and the uv of every
    triangle corner [F, 3, 2] float32 (texel centres; v = 0 at the image's bottom row, Blender's convention).
    Squares with an edge longer than `max_edge` times the median edge are skipped. Charts are then stitched
    (`stitch_charts`) with `stitch` times the median edge as the tolerance (0: not stitched)."""
    tp = np.asarray(texel_points, dtype=np.float32)
    H, W = tp.shape[:2]
    cell = R + 2 * pad
    valid = np.isfinite(tp).all(-1)
    n_valid = int(valid.sum())
    if n_valid < 4:
        raise InputError(f"the texel map has {n_valid} texels on the surface; too few for a proxy mesh")
    step = max(1, math.ceil(math.sqrt(2.0 * n_valid / max(int(target_faces), 2))))
    offs = np.arange(0, R, step)
    rows = (np.arange(H // cell)[:, None] * cell + pad + offs[None]).reshape(-1)
    cols = (np.arange(W // cell)[:, None] * cell + pad + offs[None]).reshape(-1)
    P = tp[rows][:, cols]                                        # [nr, nc, 3]
    ok = valid[rows][:, cols]
    same_r = (rows[:-1] // cell) == (rows[1:] // cell)
    same_c = (cols[:-1] // cell) == (cols[1:] // cell)
    quad = ok[:-1, :-1] & ok[1:, :-1] & ok[:-1, 1:] & ok[1:, 1:] & same_r[:, None] & same_c[None, :]
    a, b, c, d = P[:-1, :-1], P[1:, :-1], P[1:, 1:], P[:-1, 1:]  # corners (i, j), (i+1, j), (i+1, j+1), (i, j+1)
    with np.errstate(invalid="ignore"):
        edges = np.stack([np.linalg.norm(b - a, axis=-1), np.linalg.norm(c - b, axis=-1),
                          np.linalg.norm(d - c, axis=-1), np.linalg.norm(a - d, axis=-1)], -1)
    if not quad.any():
        raise InputError("the texel map holds no surface patch of 2 x 2 samples; too sparse for a proxy mesh")
    med = float(np.median(edges[quad]))
    quad &= (edges.max(-1) <= max_edge * max(med, 1e-12))
    qi, qj = np.nonzero(quad)
    corners = np.stack([np.stack([qi, qj], -1), np.stack([qi + 1, qj], -1), np.stack([qi + 1, qj + 1], -1),
                        np.stack([qi, qj + 1], -1)], 1)               # [Q, 4, 2] sample-grid indices
    flat = corners[..., 0] * len(cols) + corners[..., 1]           # [Q, 4]
    used, inverse = np.unique(flat.reshape(-1), return_inverse=True)
    ids = inverse.reshape(-1, 4).astype(np.int32)
    tris = np.concatenate([ids[:, [0, 1, 2]], ids[:, [0, 2, 3]]]).astype(np.int32)
    gr, gc = rows[used // len(cols)], cols[used % len(cols)]
    verts = tp[gr, gc].astype(np.float32)
    uv = np.stack([(gc + 0.5) / W, 1.0 - (gr + 0.5) / H], -1).astype(np.float32)
    corner_uv = uv[tris]
    if stitch > 0:
        # grid layout: the chart square a texel lies in; island layout (one cell): the connected piece
        chart = (gr // cell) * (W // cell) + gc // cell if cell < max(H, W) else mesh_components(len(verts), tris)
        verts, tris = stitch_charts(verts, tris, chart, stitch * med)
    return verts, tris, corner_uv


def mesh_components(n_verts: int, tris: np.ndarray) -> np.ndarray:
    """Connected-component label [V] int64 of every vertex of triangles [F, 3] (the smallest vertex index in its
    component): labels flow along triangles until nothing changes."""
    label = np.arange(n_verts, dtype=np.int64)
    while True:
        low = label[tris].min(axis=1)                       # [F] smallest label at each triangle
        new = label.copy()
        for k in range(3):
            np.minimum.at(new, tris[:, k], low)
        new = new[new]                                      # follow labels to their own labels (pointer jumping)
        if np.array_equal(new, label):
            return label
        label = new


def _edge_counts(tris: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Unique undirected edges [E, 2] of triangles [F, 3] and how many triangles use each [E]."""
    e = np.sort(np.concatenate([tris[:, [0, 1]], tris[:, [1, 2]], tris[:, [2, 0]]]), axis=1)
    return np.unique(e, axis=0, return_counts=True)


def stitch_charts(verts: np.ndarray, tris: np.ndarray, chart: np.ndarray, tol: float,
                  chunk: int = 1024) -> tuple[np.ndarray, np.ndarray]:
    """Close the cracks between chart pieces: boundary vertices [V] of different charts that are each other's
    nearest boundary vertex of another chart and lie within `tol` are merged at their midpoint (triangles keep
    their corner UVs, so seams stay seams in the atlas). verts [V, 3], tris [F, 3], chart [V] int. Returns
    (verts [V', 3], tris [F, 3]); unchanged when nothing merges or merging would give an edge more than two
    triangles (Surface Deform needs a manifold target)."""
    edges, counts = _edge_counts(tris)
    boundary = np.unique(edges[counts == 1])
    if len(boundary) < 2 or not tol > 0:
        return verts, tris
    bp = verts[boundary].astype(np.float64)
    bc = chart[boundary]
    nearest = np.full(len(boundary), -1, dtype=np.int64)
    dist = np.full(len(boundary), np.inf)
    for s in range(0, len(boundary), chunk):  # [chunk, B] distances: a few thousand boundary vertices at most
        d = np.linalg.norm(bp[s:s + chunk, None] - bp[None], axis=-1)
        d[bc[s:s + chunk, None] == bc[None]] = np.inf
        nearest[s:s + chunk] = d.argmin(1)
        dist[s:s + chunk] = d[np.arange(d.shape[0]), nearest[s:s + chunk]]
    i = np.arange(len(boundary))
    pair = np.isfinite(dist) & (dist <= tol) & (nearest[nearest] == i) & (i < nearest)
    if not pair.any():
        return verts, tris
    keep, drop = boundary[i[pair]], boundary[nearest[pair]]
    new_verts = verts.copy()
    new_verts[keep] = (verts[keep] + verts[drop]) / 2.0
    remap = np.arange(len(verts))
    remap[drop] = keep
    merged = remap[tris]
    _, counts = _edge_counts(merged)
    if (counts > 2).any():
        return verts, tris
    used, inverse = np.unique(merged.reshape(-1), return_inverse=True)
    return new_verts[used].astype(np.float32), inverse.reshape(-1, 3).astype(np.int32)


