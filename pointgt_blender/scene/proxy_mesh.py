"""A surface proxy mesh made from the model's texel map (the canonical 3-D point of every atlas texel): visible in
Solid, Material Preview and EEVEE/Cycles, UV-mapped into the atlas image (so Blender's own Texture Paint lands in
the atlas the neural render uses), and a deformer for the points: a Surface Deform modifier bound at rest lets
anything that moves the proxy (Automatic Weights, weight painting, shape keys, cloth) move the points.

The mesh: atlas texels sampled every `s` texels inside each chart (s chosen so the proxy has at most
`target_faces` triangles), two triangles per grid square whose four corners lie on the surface and whose edges
are not much longer than the median edge (a square across a hole or a fold is skipped). Each vertex sits on its
texel's point and has that texel's centre as UV, so painting the proxy writes the texels that the neural render
looks up there. Then the cracks close where the surface goes on: small holes in a chart's texel mask get
interpolated points before sampling, the pieces of neighbouring charts are welded along their seams (each face
corner keeps its own UV), the faces are oriented alike, and the small holes left (the notches of jagged seams)
are filled.
This module needs only numpy; `proxy` makes the Blender objects.
"""
from __future__ import annotations

import math

import numpy as np

from core.modelfile.pgt import PgtFile
from core.util.errors import InputError, ModelFileError

TEXELS = "atlas/texel_points"
SMALL_PIECE = 0.02  # island atlases: a piece with fewer than this share of the faces is welded more eagerly
FLOATER = 8.0  # ... and left out when still apart and no vertex of it lies within this many median edges of the rest
# island atlases: the weld tolerance is this many times `stitch` (the vertices on two sides of a seam between islands
# lie on each island's own sampling lines, up to about two median edges apart: the test card's cracks are 1.7-1.8)
ISLAND_STITCH = 4.0 / 3.0


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
                 max_edge: float = 4.0, stitch: float = 1.5, close: int = 1,
                 fill: int = 24) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Triangle mesh of the texel map. texel_points [H, W, 3] (NaN = no surface), charts of R x R texels in cells
    of R + 2 pad. Returns vertices [V, 3] float32 (the texels' points), triangles [F, 3] int32 and the uv of every
    triangle corner [F, 3, 2] float32 (texel centres; v = 0 at the image's bottom row, Blender's convention).
    Squares with an edge longer than `max_edge` times the median edge are skipped. In an island atlas (one cell,
    pad 0) a square is whole only when every texel along its sides is on the surface, and the squares an island's
    border crosses are cut at the border (`_border_triangles`), so each island's mesh reaches its border and the
    seams between islands are narrow enough to weld (at ISLAND_STITCH times the tolerance); the step grows when
    that overruns the face budget; a piece with fewer than SMALL_PIECE of the faces still apart after welding is
    welded to the others at twice the tolerance, and left out when even then none of its vertices lies within
    FLOATER median edges of the rest (stray surface points of the model, far off its surface). Cracks are then closed where the surface goes on: with `close` > 0,
    holes and notches of a grid chart's texel mask narrower than about 2 `close` sampling steps get surface points
    interpolated from their neighbours first (`close_texel_map`); chart pieces are welded along their seams
    (`stitch_charts`, `stitch` times the median edge as the tolerance; 0: not welded); holes left with at most
    `fill` edges and a perimeter of at most `fill` median edges are filled (`fill_holes`; 0: not filled)."""
    tp = np.asarray(texel_points, dtype=np.float32)
    H, W = tp.shape[:2]
    cell = R + 2 * pad
    valid = np.isfinite(tp).all(-1)
    n_valid = int(valid.sum())
    if n_valid < 4:
        raise InputError(f"the texel map has {n_valid} texels on the surface; too few for a proxy mesh")
    budget = max(int(target_faces), 2) * (0.9 if fill > 0 else 1.0)  # room for the faces that fill holes
    step = max(1, math.ceil(math.sqrt(2.0 * n_valid / budget)))
    grid = cell < max(H, W)  # grid layout (an island atlas is one cell: its islands are not closed across)
    if close > 0 and grid:
        tp = close_texel_map(tp, cell, int(close) * step)
        valid = np.isfinite(tp).all(-1)
        step = max(step, math.ceil(math.sqrt(2.0 * int(valid.sum()) / budget)))
    key_tris, med = _sample_faces(tp, valid, R, pad, cell, step, grid, max_edge)
    for _ in range(16):  # an island atlas's border triangles can overrun the budget: then a coarser step
        if grid or len(key_tris) <= budget:
            break
        step = max(step + 1, math.ceil(step * math.sqrt(len(key_tris) / budget)))
        try:
            key_tris, med = _sample_faces(tp, valid, R, pad, cell, step, grid, max_edge)
        except InputError:  # too coarse for any whole square: keep the finer mesh
            break
    used, inverse = np.unique(key_tris.reshape(-1), return_inverse=True)
    tris = inverse.reshape(-1, 3).astype(np.int32)
    gr, gc = used // W, used % W
    verts = tp[gr, gc].astype(np.float32)
    uv = np.stack([(gc + 0.5) / W, 1.0 - (gr + 0.5) / H], -1).astype(np.float32)
    corner_uv = uv[tris]
    if not grid:  # texels that share a surface point (the nearest-sample fallback of the island texel map)
        verts, tris, corner_uv, gr, gc = _merge_coincident(verts, tris, corner_uv, gr, gc, 1e-5 * med)
    # grid layout: the chart square a texel lies in; island layout (one cell): the connected piece
    chart = (gr // cell) * (W // cell) + gc // cell if grid else mesh_components(len(verts), tris)
    face_chart = chart[tris[:, 0]]
    if stitch > 0:
        tol = stitch * med * (1.0 if grid else ISLAND_STITCH)
        verts, tris = stitch_charts(verts, tris, chart, tol)
        if not grid:  # small pieces still apart (an island's fragment): welded to the rest at twice the tolerance
            comp = mesh_components(len(verts), tris)
            faces = np.bincount(comp[tris[:, 0]], minlength=len(verts))[comp]
            small = faces < SMALL_PIECE * len(tris)
            if small[tris[:, 0]].any() and not small[tris[:, 0]].all():
                verts, tris = stitch_charts(verts, tris, np.where(small, comp, -1), 2.0 * tol)
                keep = _near_pieces(verts, tris, FLOATER * med)
                if not keep.all():
                    tris, corner_uv, face_chart = tris[keep], corner_uv[keep], face_chart[keep]
                    used, inverse = np.unique(tris.reshape(-1), return_inverse=True)
                    verts, tris = verts[used], inverse.reshape(-1, 3).astype(np.int32)
    flip = orient_faces(tris, verts)
    tris[flip] = tris[flip][:, [0, 2, 1]]
    corner_uv[flip] = corner_uv[flip][:, [0, 2, 1]]
    if fill > 0:
        verts, tris, corner_uv = fill_holes(verts, tris, corner_uv, face_chart, int(fill), fill * med)
    return verts, tris, corner_uv


def _near_pieces(verts: np.ndarray, tris: np.ndarray, reach: float) -> np.ndarray:
    """Faces [F] bool to keep: all but those of small pieces (under SMALL_PIECE of the faces) with no vertex within
    `reach` of a larger piece — fragments meshed from a model's stray surface points, far off its surface."""
    comp = mesh_components(len(verts), tris)
    fcomp = comp[tris[:, 0]]
    faces = np.bincount(fcomp, minlength=len(verts))
    small = faces < SMALL_PIECE * len(tris)
    keep = ~small[fcomp]
    if keep.all() or not keep.any():
        return np.ones(len(tris), bool)
    big = verts[np.unique(tris[keep])].astype(np.float64)
    for c in np.unique(fcomp[~keep]):
        v = verts[np.unique(tris[fcomp == c])].astype(np.float64)
        d2 = min(float(((big - p) ** 2).sum(-1).min()) for p in v)
        if d2 <= reach * reach:
            keep |= fcomp == c
    return keep


def _sample_faces(tp: np.ndarray, valid: np.ndarray, R: int, pad: int, cell: int, step: int, grid: bool,
                  max_edge: float) -> tuple[np.ndarray, float]:
    """Triangles [F, 3] (texel keys r * W + c) of the texels sampled every `step` texels in every chart cell, and
    the median edge of the whole squares. Two triangles per square whose four corners are on the surface and whose
    edges are at most `max_edge` median edges long (grid layout: inside one chart cell; island layout: with every
    texel along its sides on the surface, and the squares an island's border crosses cut at it)."""
    H, W = valid.shape
    offs = np.arange(0, R, step)
    rows = (np.arange(H // cell)[:, None] * cell + pad + offs[None]).reshape(-1)
    cols = (np.arange(W // cell)[:, None] * cell + pad + offs[None]).reshape(-1)
    P = tp[rows][:, cols]                                        # [nr, nc, 3]
    ok = valid[rows][:, cols]
    same_r = (rows[:-1] // cell) == (rows[1:] // cell)
    same_c = (cols[:-1] // cell) == (cols[1:] // cell)
    quad = ok[:-1, :-1] & ok[1:, :-1] & ok[:-1, 1:] & ok[1:, 1:] & same_r[:, None] & same_c[None, :]
    if not grid:
        h_full, v_full = _full_sides(valid, rows, cols)
        quad &= h_full[:-1] & h_full[1:] & v_full[:, :-1] & v_full[:, 1:]
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
    key = rows[corners[..., 0]].astype(np.int64) * W + cols[corners[..., 1]]   # [Q, 4] texel keys r * W + c
    key_tris = np.concatenate([key[:, [0, 1, 2]], key[:, [0, 2, 3]]])
    if not grid:  # island atlas: the squares an island's border crosses, cut at the border
        bt = _border_triangles(valid, ok, rows, cols, ~quad, h_full, v_full)
        if len(bt):
            with np.errstate(invalid="ignore"):
                q = tp.reshape(-1, 3)[bt]                                 # [T, 3, 3]
                longest = np.linalg.norm(q - q[:, [1, 2, 0]], axis=-1).max(-1)
            key_tris = np.concatenate([key_tris, bt[longest <= max_edge * max(med, 1e-12)]])
    return key_tris, med


def _merge_coincident(verts: np.ndarray, tris: np.ndarray, corner_uv: np.ndarray, gr: np.ndarray, gc: np.ndarray,
                      tol: float):
    """Vertices [V, 3] at the same point merged into one (Surface Deform refuses a target with overlapping
    vertices); triangles [F, 3] that then lose a corner, repeat another triangle, have an edge shorter than `tol`
    or a height under `tol` (flat), or are a third triangle on an edge are dropped, with their corner UVs
    [F, 3, 2]; unused vertices go (gr, gc [V]: their texels, kept alongside). Returns (verts, tris, corner_uv, gr,
    gc)."""
    _, first, inv = np.unique(verts, axis=0, return_index=True, return_inverse=True)
    t = first[inv.reshape(-1)][tris] if len(first) < len(verts) else tris.copy()
    with np.errstate(invalid="ignore"):
        side = np.linalg.norm(verts[t] - verts[t[:, [1, 2, 0]]], axis=-1)              # [F, 3]
        twice_area = np.linalg.norm(np.cross(verts[t[:, 1]] - verts[t[:, 0]], verts[t[:, 2]] - verts[t[:, 0]]),
                                    axis=1)
        short = (side.min(1) <= tol) | (twice_area <= tol * side.max(1))              # coincident or flat corners
    keep = (t[:, 0] != t[:, 1]) & (t[:, 1] != t[:, 2]) & (t[:, 2] != t[:, 0]) & ~short
    first_copy = np.zeros(len(t), bool)
    first_copy[np.unique(np.sort(t, axis=1), axis=0, return_index=True)[1]] = True
    keep &= first_copy
    if keep.all() and len(first) == len(verts):
        return verts, tris, corner_uv, gr, gc
    idx = np.nonzero(keep)[0]
    e = np.sort(np.concatenate([t[idx][:, [0, 1]], t[idx][:, [1, 2]], t[idx][:, [2, 0]]]), axis=1)
    _, e_inv = np.unique(e, axis=0, return_inverse=True)
    e_inv = e_inv.reshape(3, -1)
    seen = np.zeros(int(e_inv.max()) + 1 if e_inv.size else 0, np.int64)
    ok = np.ones(len(idx), bool)
    for k in range(len(idx)):  # in order: a triangle that would be the third on an edge is dropped
        es = e_inv[:, k]
        if (seen[es] >= 2).any():
            ok[k] = False
        else:
            seen[es] += 1
    idx = idx[ok]
    used, new = np.unique(t[idx].reshape(-1), return_inverse=True)
    return (verts[used], new.reshape(-1, 3).astype(np.int32), corner_uv[idx], gr[used], gc[used])


def _full_sides(valid: np.ndarray, rows: np.ndarray, cols: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Whether every texel along each side of the sampling grid is on the surface: horizontal sides [nr, nc - 1]
    (row rows[i] from cols[j] to cols[j + 1]) and vertical sides [nr - 1, nc]. valid [H, W] bool."""
    H, W = valid.shape
    csr = np.concatenate([np.zeros((H, 1), np.int64), np.cumsum(valid, axis=1)], 1)   # [H, W + 1] run counts
    csc = np.concatenate([np.zeros((1, W), np.int64), np.cumsum(valid, axis=0)], 0)   # [H + 1, W]
    r, c = np.asarray(rows), np.asarray(cols)
    h_full = (csr[r][:, c[1:] + 1] - csr[r][:, c[:-1]]) == (c[1:] - c[:-1] + 1)[None]
    v_full = (csc[r[1:] + 1][:, c] - csc[r[:-1]][:, c]) == (r[1:] - r[:-1] + 1)[:, None]
    return h_full, v_full


def _border_triangles(valid: np.ndarray, ok: np.ndarray, rows: np.ndarray, cols: np.ndarray,
                      open_square: np.ndarray, h_full: np.ndarray, v_full: np.ndarray) -> np.ndarray:
    """Triangles [T, 3] (texel keys r * W + c) of the sampling squares that an island's border crosses, cut at the
    border: the squares of the sampled rows x cols grid not meshed whole (`open_square` [nr - 1, nc - 1]) are walked
    around their four corners; a side whose texels are not all on the surface ends, from each corner on the surface,
    at the last texel of the run of surface texels that starts there, so the mesh reaches to within a texel of the
    island's border instead of stopping up to a sampling step inside it. The walk is cut at every such side into
    chains (corner and end texels in order around the square), each of at least three texels a fan of triangles.
    Without this the islands' meshes stop short of their borders and their seams are too wide to weld.
    valid [H, W] bool (texels on the surface), ok [nr, nc] the same at the sampled texels; h_full, v_full:
    `_full_sides`."""
    H, W = valid.shape

    def run_end(p, q):
        """The last surface texel of the straight run from texel p towards texel q (p on the surface)."""
        (pr, pc), (qr, qc) = p, q
        dr, dc = int(np.sign(qr - pr)), int(np.sign(qc - pc))
        n = abs(qr - pr) + abs(qc - pc)
        steps = np.arange(1, n + 1)
        line = valid[pr + dr * steps, pc + dc * steps]                  # the texels after p, up to q
        k = int(np.argmin(line)) if not line.all() else len(line)     # surface texels after p before a gap
        return (pr + dr * k, pc + dc * k)

    out = []
    for i, j in zip(*np.nonzero(open_square & (ok[:-1, :-1] | ok[1:, :-1] | ok[1:, 1:] | ok[:-1, 1:]))):
        cs = [(i, j), (i + 1, j), (i + 1, j + 1), (i, j + 1)]          # the same order as the whole squares
        full = [bool(v_full[i, j]), bool(h_full[i + 1, j]), bool(v_full[i, j + 1]), bool(h_full[i, j])]
        items: list = []
        for k in range(4):
            a, b = cs[k], cs[(k + 1) % 4]
            ta, tb = (int(rows[a[0]]), int(cols[a[1]])), (int(rows[b[0]]), int(cols[b[1]]))
            if ok[a]:
                items.append(ta)
            if not full[k]:
                if ok[a]:
                    items.append(run_end(ta, tb))
                items.append(None)
                if ok[b]:
                    items.append(run_end(tb, ta))
        if None not in items:
            continue
        s0 = items.index(None)
        items = items[s0 + 1:] + items[:s0 + 1]
        chain: list = []
        for it in items:
            if it is not None:
                if not chain or chain[-1] != it:
                    chain.append(it)
                continue
            if len(chain) >= 3:
                keys = [tr * W + tc for tr, tc in chain]
                out += [[keys[0], keys[m], keys[m + 1]] for m in range(1, len(keys) - 1)]
            chain = []
    if not out:
        return np.zeros((0, 3), np.int64)
    t = np.asarray(out, np.int64)
    tr, tc = t // W, t % W
    area = (tr[:, 1] - tr[:, 0]) * (tc[:, 2] - tc[:, 0]) - (tc[:, 1] - tc[:, 0]) * (tr[:, 2] - tr[:, 0])
    return t[area != 0]                                                # no triangle flat in the atlas


def close_texel_map(texel_points: np.ndarray, cell: int, k: int) -> np.ndarray:
    """Texel map [H, W, 3] with the holes and notches of every chart's texel mask narrower than about 2 k + 1
    texels filled: a morphological closing (k dilations, then k erosions, 8-neighbour) per chart cell of `cell`
    texels, whose new texels get the mean point of their already known 8-neighbours, ring by ring. Texels with a
    surface point are kept; nothing grows outwards or across cells."""
    tp = np.array(texel_points, dtype=np.float32)
    H, W = tp.shape[:2]
    if k < 1:
        return tp

    def grow(m, value):  # one 8-neighbour dilation (value False) or erosion (value True)
        p = np.pad(m, 1, constant_values=value)
        parts = [p[1 + dr:1 + dr + m.shape[0], 1 + dc:1 + dc + m.shape[1]]
                 for dr in (-1, 0, 1) for dc in (-1, 0, 1)]
        return np.logical_or.reduce(parts) if not value else np.logical_and.reduce(parts)

    for r0 in range(0, H - cell + 1, cell):
        for c0 in range(0, W - cell + 1, cell):
            sub = tp[r0:r0 + cell, c0:c0 + cell]
            known = np.isfinite(sub).all(-1)
            if not known.any() or known.all():
                continue
            closed = known
            for _ in range(k):
                closed = grow(closed, False)
            for _ in range(k):
                closed = grow(closed, True)
            todo = closed & ~known
            for _ in range(2 * k + 2):
                if not todo.any():
                    break
                vals = np.where(known[..., None], sub, 0.0)
                pv = np.pad(vals, ((1, 1), (1, 1), (0, 0)))
                pk = np.pad(known, 1).astype(np.float32)
                acc = sum(pv[1 + dr:1 + dr + cell, 1 + dc:1 + dc + cell] for dr in (-1, 0, 1) for dc in (-1, 0, 1))
                cnt = sum(pk[1 + dr:1 + dr + cell, 1 + dc:1 + dc + cell] for dr in (-1, 0, 1) for dc in (-1, 0, 1))
                ring = todo & (cnt > 0)
                sub[ring] = acc[ring] / cnt[ring][:, None]
                known = known | ring
                todo &= ~ring
    return tp


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
    """Close the cracks between chart pieces by welding: boundary vertices of different charts within `tol` of
    each other are merged, closest pairs first, into clusters that hold at most one vertex of each chart (so no
    triangle collapses), each at the mean of its vertices (triangles keep their corner UVs, so seams stay seams
    in the atlas). Welds that would give an edge more than two triangles (Surface Deform needs a manifold
    target) are undone. verts [V, 3], tris [F, 3], chart [V] int. Returns (verts [V', 3], tris [F, 3])."""
    edges, counts = _edge_counts(tris)
    boundary = np.unique(edges[counts == 1])
    if len(boundary) < 2 or not tol > 0:
        return verts, tris
    bp = verts[boundary].astype(np.float64)
    bc = np.asarray(chart)[boundary]
    pi, pj, pd = [], [], []
    for s in range(0, len(boundary), chunk):  # [chunk, B] distances: a few thousand boundary vertices at most
        d = np.linalg.norm(bp[s:s + chunk, None] - bp[None], axis=-1)
        i, j = np.nonzero((d <= tol) & (bc[s:s + chunk, None] != bc[None]))
        keep = s + i < j
        pi.append(s + i[keep])
        pj.append(j[keep])
        pd.append(d[i[keep], j[keep]])
    pi, pj, pd = np.concatenate(pi), np.concatenate(pj), np.concatenate(pd)
    if not len(pi):
        return verts, tris
    blocked: set = set()
    for _ in range(8):
        parent = list(range(len(boundary)))
        charts = [{int(c)} for c in bc]

        def root(x):
            while parent[x] != x:
                parent[x] = parent[parent[x]]
                x = parent[x]
            return x

        for k in np.argsort(pd, kind="stable"):
            a, b = root(int(pi[k])), root(int(pj[k]))
            if a == b or charts[a] & charts[b] or int(pi[k]) in blocked or int(pj[k]) in blocked:
                continue
            parent[b] = a
            charts[a] |= charts[b]
        rep = np.array([root(x) for x in range(len(boundary))])
        remap = np.arange(len(verts))
        remap[boundary] = boundary[rep]
        merged = remap[tris]
        e, counts = _edge_counts(merged)
        bad = e[counts > 2]
        if not len(bad):
            break
        # undo the welds at the vertices of over-full edges: every boundary vertex welded into those clusters
        hit = np.isin(remap[boundary], bad.reshape(-1))
        blocked |= set(np.nonzero(hit)[0].tolist())
    else:
        return verts, tris
    new_verts = verts.astype(np.float64).copy()
    sums = np.zeros_like(new_verts)
    np.add.at(sums, remap, verts)
    n = np.bincount(remap, minlength=len(verts)).astype(np.float64)
    welded = n > 1
    new_verts[welded] = sums[welded] / n[welded, None]
    used, inverse = np.unique(merged.reshape(-1), return_inverse=True)
    return new_verts[used].astype(np.float32), inverse.reshape(-1, 3).astype(np.int32)


def orient_faces(tris: np.ndarray, verts: np.ndarray | None = None) -> np.ndarray:
    """Which triangles [F, 3] to flip (bool [F]) so that every edge two triangles share runs opposite ways in
    them (one orientation per connected piece; charts of an atlas can be mirrored against each other, so welded
    pieces disagree until flipped). In each piece the orientation most triangles already have is kept; with
    `verts` [V, 3], pieces that touch only at vertices are turned to agree with each other too."""
    t = np.asarray(tris, np.int64)
    F = len(t)
    flip = np.zeros(F, bool)
    label = np.zeros(F, np.int64)
    if not F:
        return flip
    e = np.sort(np.concatenate([t[:, [0, 1]], t[:, [1, 2]], t[:, [2, 0]]]), axis=1)
    same_dir = np.concatenate([t[:, 0] < t[:, 1], t[:, 1] < t[:, 2], t[:, 2] < t[:, 0]])  # runs low -> high
    face = np.tile(np.arange(F), 3)
    order = np.lexsort((e[:, 1], e[:, 0]))
    e, same_dir, face = e[order], same_dir[order], face[order]
    first = np.ones(len(e), bool)
    first[1:] = (e[1:] != e[:-1]).any(1)
    group = np.cumsum(first) - 1
    nbrs: list = [[] for _ in range(F)]
    for g in np.nonzero(np.bincount(group) == 2)[0]:  # manifold edges: exactly two triangles
        i = int(np.searchsorted(group, g))
        a, b = int(face[i]), int(face[i + 1])
        agree = bool(same_dir[i]) != bool(same_dir[i + 1])  # consistent when they run opposite ways
        nbrs[a].append((b, agree))
        nbrs[b].append((a, agree))
    seen = np.zeros(F, bool)
    for s0 in range(F):
        if seen[s0]:
            continue
        seen[s0] = True
        piece, stack = [s0], [s0]
        while stack:
            f = stack.pop()
            for g, agree in nbrs[f]:
                if not seen[g]:
                    seen[g] = True
                    flip[g] = flip[f] if agree else not flip[f]
                    piece.append(g)
                    stack.append(g)
        if flip[piece].sum() * 2 > len(piece):
            flip[piece] = ~flip[piece]
        label[piece] = s0
    if verts is not None:
        flip ^= _align_pieces(np.asarray(verts, np.float64), np.where(flip[:, None], t[:, [0, 2, 1]], t), label)
    return flip


def _align_pieces(verts: np.ndarray, t: np.ndarray, label: np.ndarray) -> np.ndarray:
    """Pieces of triangles [F, 3] (label [F]) that touch only at vertices cannot be oriented through edges: flip
    (bool [F]) whole pieces whose normals point against those of the pieces they touch (area-weighted normals
    summed at the shared vertices), piece by piece from the largest."""
    n = np.cross(verts[t[:, 1]] - verts[t[:, 0]], verts[t[:, 2]] - verts[t[:, 0]])   # [F, 3], |n| = 2 area
    pieces, inv = np.unique(label, return_inverse=True)
    if len(pieces) < 2:
        return np.zeros(len(t), bool)
    # normal of each (piece, vertex) pair
    pv = np.stack([np.repeat(inv, 3), t.reshape(-1)], 1)
    key, kinv = np.unique(pv, axis=0, return_inverse=True)
    normal = np.zeros((len(key), 3))
    np.add.at(normal, kinv.reshape(-1), np.repeat(n, 3, axis=0))
    shared = np.bincount(key[:, 1], minlength=len(verts))[key[:, 1]] > 1
    key, normal = key[shared], normal[shared]
    score: dict = {}  # (piece a, piece b) -> summed dot of their normals at shared vertices
    for v in np.unique(key[:, 1]):
        rows = np.nonzero(key[:, 1] == v)[0]
        for i in range(len(rows)):
            for j in range(i + 1, len(rows)):
                a, b = int(key[rows[i], 0]), int(key[rows[j], 0])
                score[(a, b)] = score.get((a, b), 0.0) + float(normal[rows[i]] @ normal[rows[j]])
    nbrs: dict = {}
    for (a, b), d in score.items():
        nbrs.setdefault(a, []).append((b, d))
        nbrs.setdefault(b, []).append((a, d))
    size = np.bincount(inv, minlength=len(pieces))
    flip_piece = np.zeros(len(pieces), bool)
    seen = np.zeros(len(pieces), bool)
    for s0 in np.argsort(-size, kind="stable"):
        if seen[s0]:
            continue
        seen[s0] = True
        stack = [int(s0)]
        while stack:
            a = stack.pop()
            for b, d in nbrs.get(a, ()):
                if not seen[b]:
                    seen[b] = True
                    flip_piece[b] = flip_piece[a] ^ (d < 0)
                    stack.append(b)
    return flip_piece[inv]


def boundary_loops(tris: np.ndarray) -> list[np.ndarray]:
    """The closed loops of boundary edges of triangles [F, 3]: vertex indices [L] each, in the order of the
    triangles' own boundary edges (a -> b where b -> a is in no triangle). A loop goes on along the boundary edge
    found by turning around the vertex through the triangles; where separate fans of triangles touch at a vertex
    (a pinch, as welding leaves between two pieces), it crosses to the next fan, so the gap between two pieces
    welded at points comes out as a loop of its own."""
    t = np.asarray(tris, np.int64)
    if not len(t):
        return []
    face_of = {}  # directed edge (a, b) -> (triangle, corner of a)
    for f, (x, y, z) in enumerate(t.tolist()):
        face_of[(x, y)] = (f, 0)
        face_of[(y, z)] = (f, 1)
        face_of[(z, x)] = (f, 2)
    und, cnt = _edge_counts(t)
    single = set(map(tuple, und[cnt == 1].tolist()))  # undirected edges of one triangle
    open_edges = [e for e in face_of if (min(e), max(e)) in single]

    def next_edge(a, b):
        """The boundary edge b -> c that follows a -> b around b's fan (None if the fan is broken)."""
        f, k = face_of[(a, b)]
        for _ in range(len(face_of)):
            c = int(t[f, (k + 2) % 3])          # triangle f = (a, b, c): its edge out of b is b -> c
            if (c, b) not in face_of:
                return (b, c)
            f, k = face_of[(c, b)]               # cross to the triangle (c, b, d) and turn on
            a, b = c, b
        return None

    succ = {e: next_edge(*e) for e in open_edges}
    # a pinch: fans of triangles that touch only at the vertex (welded pieces). The gap between them is the hole
    # to find, so a loop arriving in one fan leaves through the next fan's boundary edge.
    arriving: dict = {}
    for e in open_edges:
        arriving.setdefault(e[1], []).append(e)
    for ins in arriving.values():
        if len(ins) > 1:
            outs = [succ[e] for e in ins]
            for k, e in enumerate(ins):
                succ[e] = outs[(k + 1) % len(ins)]
    done, loops = set(), []
    for e in open_edges:
        if e in done:
            continue
        loop, cur = [], e
        while cur is not None and cur not in done:
            done.add(cur)
            loop.append(cur[0])
            cur = succ.get(cur)
        if cur == e and all((min(x, y), max(x, y)) in single for x, y in zip(loop, loop[1:] + loop[:1])):
            loops += _simple_loops(loop)
    return loops


def _simple_loops(loop: list) -> list[np.ndarray]:
    """A closed walk that passes a vertex more than once, cut into loops that pass each vertex once (each at
    least 3 long)."""
    out, path, pos = [], [], {}
    for v in loop + loop[:1]:
        if v in pos:
            k = pos[v]
            piece = path[k:]
            for x in piece[1:]:
                del pos[x]
            del path[k + 1:]
            if len(piece) >= 3:
                out.append(np.asarray(piece, np.int64))
            continue
        pos[v] = len(path)
        path.append(v)
    return out


def fill_holes(verts: np.ndarray, tris: np.ndarray, corner_uv: np.ndarray, face_chart: np.ndarray,
               max_edges: int, max_perimeter: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Fill the small holes: every boundary loop of at most `max_edges` edges whose perimeter is at most
    `max_perimeter` gets a triangle (3 edges) or a fan around a new vertex at its centroid. A hole inside one chart
    keeps its texture (the fan's corners take the UVs of the faces around the hole, the centre their mean);
    a hole between charts gets the one UV of a neighbouring corner (its colour, and paint there writes nothing).
    verts [V, 3], tris [F, 3], corner_uv [F, 3, 2], face_chart [F]. Returns (verts [V', 3], tris [F', 3],
    corner_uv [F', 3, 2])."""
    loops = boundary_loops(tris)
    if not loops:
        return verts, tris, corner_uv
    # the face and corner of every directed boundary edge a -> b
    n = len(verts)
    d = np.concatenate([tris[:, [0, 1]], tris[:, [1, 2]], tris[:, [2, 0]]]).astype(np.int64)
    F = len(tris)
    face = np.tile(np.arange(F), 3)
    corner = np.repeat([0, 1, 2], F)
    where = {int(k): i for i, k in enumerate((d[:, 0] * n + d[:, 1]).tolist())}
    new_v, new_t, new_uv = [], [], []
    nv = n
    for loop in loops:
        nxt = np.roll(loop, -1)
        per = float(np.linalg.norm(verts[nxt] - verts[loop], axis=1).sum())
        if len(loop) > max_edges or not per <= max_perimeter:
            continue
        idx = [where[int(x) * n + int(y)] for x, y in zip(loop, nxt)]
        f, c = face[idx], corner[idx]
        uv_a = corner_uv[f, c]                 # uv of a in the face of edge a -> b
        uv_b = corner_uv[f, (c + 1) % 3]       # uv of b there
        single = len(set(face_chart[f].tolist())) == 1
        if len(loop) == 3:
            new_t.append([loop[0], loop[2], loop[1]])
            new_uv.append([uv_a[0], uv_a[2], uv_a[1]] if single else [uv_a[0]] * 3)
            continue
        new_v.append(verts[loop].mean(0))
        centre_uv = uv_a.mean(0) if single else uv_a[0]
        for k in range(len(loop)):
            new_t.append([nxt[k], loop[k], nv])
            new_uv.append([uv_b[k], uv_a[k], centre_uv] if single else [uv_a[0]] * 3)
        nv += 1
    if not new_t:
        return verts, tris, corner_uv
    verts = np.concatenate([verts, np.asarray(new_v, np.float32).reshape(-1, 3)]).astype(np.float32)
    tris = np.concatenate([tris, np.asarray(new_t, np.int32)]).astype(np.int32)
    corner_uv = np.concatenate([corner_uv, np.asarray(new_uv, np.float32)]).astype(np.float32)
    return verts, tris, corner_uv
