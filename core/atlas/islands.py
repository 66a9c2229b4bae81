"""Island layout: each chart is cut to the region of its UV square that the surface actually uses, the regions
(islands) are packed into one square image (by their exact cells, core/atlas/bitmap_pack.py, or by xatlas:
`pack_islands`), and every island is placed by a pure integer offset.

Lookup path: chart net -> t_c(x) (uv in [0, 1]^2 of chart c) -> texel coordinates of the chart, M_c [u, v, 1]
(a scale, chosen so every chart has the same texel density on the surface, and a rotation that gives the chart's
used region its smallest bounding box, so it packs tighter) -> clamp into the
nearest occupied cell of the chart (so a point off the sampled surface never reads another island) -> + offset of
that cell's island -> packed-image pixel (col, row). The image is square (size x size), so to code that indexes
`n` chart textures of R x R texels at origin (0, 0) (core/frames, the add-on's paint transfer) an island atlas is n
views of one image with R = size: chart c's coordinates, divided by size, are already image coordinates.

Islands are built on a grid of one cell per texel: a cell is occupied when a sample whose most probable chart is c
lands in it, or in a cell within `fill` cells (closing the gaps between samples); 4-connected components are the
islands, components below `min_cells` are dropped (their points clamp to the nearest island). The packer places
the islands with `pad` texels of padding around each; it may transpose an island (`orient`: one of the
eight symmetries of the texel grid, which keep its texels aligned with image pixels; a learned chart has no
preferred handedness anyway): curved islands pack much tighter (`transpose=False` keeps every island as its
chart lays it out).
"""
from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np
import torch

from core.atlas.outlines import ORIENT_NP, cell_pixels, cells_from_arrays, cells_to_arrays
from core.util.errors import InputError, ModelFileError

BRUTE_FORCE_SIDE = 1024  # xatlas tries every position up to this atlas side
CLAMP_MARGIN = 0.5  # texels a lookup may reach past its nearest occupied cell (bilinear reads one more: pad >= 2)
# Chart coordinates a lookup and the island grid both keep: a map is trained towards [0, 1]^2 but lays some samples
# outside it; clipping them to the square's border would pile them onto the border's cells (distant places in one
# texel), so the grid covers this wider range and only farther coordinates are clamped.
UV_REACH = (-1.0, 2.0)
ORIENT = torch.from_numpy(ORIENT_NP).float()


@dataclass(eq=False)
class IslandLayout:
    """n charts packed as islands into one size x size image.

    affine [n, 2, 3] float: chart texel coordinates (col, row) = affine[c] @ (u, v, 1); cells [n, G, G] int:
    island id of each texel cell of chart c, -1 where unused; offset [I, 2] int and orient [I] int in 0..7 (None: 0):
    island i's chart texel coordinates t go to pixel (col, row) = ORIENT[orient[i]] @ t + offset[i] (a symmetry of
    the texel grid: turns by 90° and mirrors, exact on the grid).
    Derived on construction: nearest [n, G, G] int32 of each cell's nearest occupied cell as row * G + col
    (`nearest_cells` gives (row, col)), island_pixels
    [size, size] bool, owner [size, size] chart of the nearest island pixel, region [size, size] bool (islands and
    their padding), label [size, size] the nearest island's id within pad + 1 (-1 beyond; texture kernels stay
    inside one island)."""

    n: int
    size: int
    pad: int
    affine: torch.Tensor
    cells: torch.Tensor
    offset: torch.Tensor
    orient: torch.Tensor | None = None
    nearest: torch.Tensor = field(init=False)
    island_pixels: torch.Tensor = field(init=False)
    owner: torch.Tensor = field(init=False)
    region: torch.Tensor = field(init=False)
    label: torch.Tensor = field(init=False)
    fill_index: torch.Tensor = field(init=False)

    kind = "islands"

    def __post_init__(self):
        from scipy.ndimage import distance_transform_edt

        self.affine = torch.as_tensor(self.affine, dtype=torch.float32).reshape(-1, 2, 3).cpu()
        self.cells = torch.as_tensor(self.cells).long().cpu()
        self.offset = torch.as_tensor(self.offset).long().reshape(-1, 2).cpu()
        n, size, I = self.n, self.size, self.offset.shape[0]
        self.orient = torch.zeros(I, dtype=torch.long) if self.orient is None else \
            torch.as_tensor(self.orient).long().reshape(-1).cpu()
        if self.orient.shape[0] != I or (I and (int(self.orient.min()) < 0 or int(self.orient.max()) > 7)):
            raise InputError(f"island layout: orient must hold one value in 0..7 per island ({I}), got "
                             f"{tuple(self.orient.shape)}")
        if self.affine.shape[0] != n or self.cells.dim() != 3 or self.cells.shape[0] != n or size < 2 or self.pad < 0:
            raise InputError(f"island layout: inconsistent shapes (n={n}, affine {tuple(self.affine.shape)}, cells "
                             f"{tuple(self.cells.shape)}, size {size}, pad {self.pad})")
        if not torch.isfinite(self.affine).all():
            raise InputError("island layout: chart transforms must be finite")
        if int(self.cells.max()) >= I or int(self.cells.min()) < -1:
            raise InputError(f"island layout: cell island ids outside [-1, {I})")
        self.cells = self.cells.to(torch.int32)  # checked above; [n, G, G] per layout chart: half the memory of int64
        G = self.cells.shape[1]
        cells = self.cells.numpy()
        nearest = np.zeros((n, G, G), np.int32)  # one flat index per cell: half the memory of (row, col) pairs
        for c in range(n):
            occ = cells[c] >= 0
            if occ.any():
                _, (ri, ci) = distance_transform_edt(~occ, return_indices=True)
                nearest[c] = ri * G + ci
        self.nearest = torch.from_numpy(nearest)
        # rasterise: cell (r, k) of island i covers pixel (r + oy, k + ox)
        island_chart = np.full(I, -1, np.int64)
        pix = np.full((size, size), -1, np.int64)
        ids = np.full((size, size), -1, np.int64)
        off, orient = self.offset.numpy(), self.orient.numpy()
        for c in range(n):
            rr, kk = np.nonzero(cells[c] >= 0)
            isl = cells[c][rr, kk]
            island_chart[isl] = c
            pc, pr = cell_pixels(kk, rr, off[isl], orient[isl])
            if len(pr) and (pr.min() < 0 or pc.min() < 0 or pr.max() >= size or pc.max() >= size):
                raise InputError(f"island layout: an island of chart {c} lies outside the {size}x{size} image")
            if (pix[pr, pc] >= 0).any():
                raise InputError(f"island layout: islands overlap (chart {c})")
            pix[pr, pc] = c
            ids[pr, pc] = isl
        self.island_chart = torch.from_numpy(island_chart)
        inside = pix >= 0
        self.island_pixels = torch.from_numpy(inside)
        if inside.any():
            d, (ri, ci) = distance_transform_edt(~inside, return_indices=True)
            self.owner = torch.from_numpy(pix[ri, ci])
            self.region = torch.from_numpy(d <= self.pad)
            self.label = torch.from_numpy(np.where(d <= self.pad + 1, ids[ri, ci], -1))
            region = d <= self.pad
            _, (rj, cj) = distance_transform_edt(~region, return_indices=True)
            self.fill_index = torch.from_numpy(rj * size + cj)  # nearest pixel of the region, for unpack
        else:
            self.owner = torch.zeros(size, size, dtype=torch.long)
            self.region = torch.zeros(size, size, dtype=torch.bool)
            self.label = torch.full((size, size), -1, dtype=torch.long)
            self.fill_index = torch.arange(size * size).view(size, size)
        self.has_islands = torch.tensor([bool((cells[c] >= 0).any()) for c in range(n)])

    # --- what the grid layout offers, so code indexing n chart textures keeps working --------------------------
    @property
    def R(self) -> int:
        return self.size

    @property
    def shape(self) -> tuple[int, int]:
        return self.size, self.size

    def origin(self, c: int) -> tuple[int, int]:
        return 0, 0

    def origins(self, device=None) -> torch.Tensor:
        return torch.zeros(self.n, 2, device=device, dtype=torch.float32)

    @property
    def islands(self) -> int:
        return int(self.offset.shape[0])

    # --- lookups -------------------------------------------------------------------------------------------------
    def place(self, uv: torch.Tensor) -> torch.Tensor:
        """Chart coordinates uv [M, n, 2] (u -> column, v -> row, [0, 1]^2 per chart) -> image coordinates
        [M, n, 2] in [0, 1] (pixel = uv * size), each clamped into its chart's nearest island."""
        out = torch.empty_like(uv)
        for c in range(self.n):
            out[:, c] = self._place_chart(c, uv[:, c])
        return out

    def place_one(self, uv: torch.Tensor, chart: torch.Tensor) -> torch.Tensor:
        """uv [M, 2] coordinates of chart[M] (long) only -> image coordinates [M, 2] in [0, 1], as `place` gives
        them for that chart (each point placed once, not once per chart)."""
        out = torch.empty_like(uv)
        for c in range(self.n):
            m = chart == c
            if bool(m.any()):
                out[m] = self._place_chart(c, uv[m])
        return out

    def nearest_cells(self, chart, rows: torch.Tensor, cols: torch.Tensor) -> torch.Tensor:
        """The nearest occupied cell [M, 2] (row, col) of chart `chart` (an int, or [M] per cell) to cells (rows,
        cols) [M] (long, inside the grid)."""
        G = self.cells.shape[1]
        chart = torch.as_tensor(chart, device=self.nearest.device)
        flat = self.nearest[chart, rows.to(self.nearest.device), cols.to(self.nearest.device)].long()
        return torch.stack([flat // G, flat % G], -1)

    def _place_chart(self, c: int, uv: torch.Tensor) -> torch.Tensor:
        """uv [M, 2] of chart c -> image coordinates [M, 2] in [0, 1], clamped into c's nearest island."""
        dev = uv.device
        G = self.cells.shape[1]
        u = torch.nan_to_num(uv, nan=0.0, posinf=1.0, neginf=0.0).clamp(*UV_REACH)
        aff = self.affine[c].to(dev).to(uv.dtype)
        t = u @ aff[:, :2].T + aff[:, 2]
        k = t.floor().long().clamp(0, G - 1)
        nb = self.nearest_cells(c, k[:, 1], k[:, 0]).to(dev)  # [M, 2] (row, col)
        lo = nb.flip(-1).to(uv.dtype) - CLAMP_MARGIN  # (col, row)
        t = torch.maximum(torch.minimum(t, lo + 1 + 2 * CLAMP_MARGIN), lo)
        isl = self.cells[c].to(dev)[nb[:, 0], nb[:, 1]].clamp_min(0)
        rot = ORIENT.to(dev).to(uv.dtype)[self.orient.to(dev)[isl]]
        return ((rot @ t[..., None])[..., 0] + self.offset.to(dev).to(uv.dtype)[isl]) / self.size

    def orient_of_pixels(self, rows: torch.Tensor, cols: torch.Tensor) -> torch.Tensor:
        """The orientation matrix [K, 2, 2] of the island nearest each pixel (rows, cols [K] long): chart texel
        offsets -> image offsets; its transpose maps image offsets back (the matrices are orthogonal)."""
        isl = self.label.to(rows.device)[rows, cols].clamp_min(0)
        return ORIENT.to(rows.device)[self.orient.to(rows.device)[isl]]

    def hard_probs(self, logits_or_probs: torch.Tensor) -> torch.Tensor:
        """One chart per point: one-hot [M, n] of the most probable chart that has islands."""
        p = logits_or_probs.masked_fill(~self.has_islands.to(logits_or_probs.device), float("-inf"))
        return torch.nn.functional.one_hot(p.argmax(-1), self.n).to(logits_or_probs.dtype)

    # --- images --------------------------------------------------------------------------------------------------
    def pack(self, textures: torch.Tensor, background: float = 0.0) -> torch.Tensor:
        """Chart textures [n, C, size, size] -> image [size, size, C]: each pixel from the chart that owns it;
        pixels farther than pad from every island get `background`."""
        n, C, H, W = textures.shape
        if (n, H, W) != (self.n, self.size, self.size):
            raise InputError(f"textures {tuple(textures.shape)} do not match the island layout "
                             f"({self.n} charts, {self.size}^2)")
        owner = self.owner.to(textures.device)
        img = textures.gather(0, owner[None, None].expand(1, C, H, W))[0]
        img = torch.where(self.region.to(textures.device)[None], img, torch.full_like(img, background))
        return img.permute(1, 2, 0).contiguous()

    def unpack(self, image: torch.Tensor) -> torch.Tensor:
        """Image [size, size, C] -> n views of one texture [n, C, size, size]: the image with every pixel outside the
        islands' padding replaced by the nearest padding pixel, so a lookup that strays past the padding (the
        interpolated sub-pixel lookups of a pixel filter can) reads the island's edge colour, never the background
        the image shows there. pack(unpack(image)) == image."""
        C = image.shape[2]
        flat = image.reshape(-1, C)[self.fill_index.to(image.device).reshape(-1)]
        return flat.T.reshape(C, self.size, self.size)[None].expand(self.n, -1, -1, -1)

    # --- storage -------------------------------------------------------------------------------------------------
    def to_arrays(self) -> dict[str, np.ndarray]:
        """The layout as named arrays (atlas version 7: each chart's cells cropped to its occupied bounding box,
        `cells_to_arrays`)."""
        return {"atlas/islands/affine": self.affine.numpy().astype(np.float32),
                **cells_to_arrays(self.cells.numpy()),
                "atlas/islands/offset": self.offset.numpy().astype(np.int32),
                "atlas/islands/orient": self.orient.numpy().astype(np.int32)}

    @classmethod
    def from_arrays(cls, arrays: dict, n: int, size: int, pad: int) -> "IslandLayout":
        """Rebuild from `to_arrays` output, or from the whole cell grids of atlas versions 2-6."""
        for key in ("atlas/islands/affine", "atlas/islands/offset"):
            if key not in arrays:
                raise ModelFileError(f"atlas: missing array '{key}' (island layout) in the model file")
        cells = cells_from_arrays(arrays)
        if cells is None:
            raise ModelFileError("atlas: missing the island cell arrays ('atlas/islands/cell_boxes', "
                                 "'atlas/islands/cell_crops', 'atlas/islands/grid') in the model file")
        orient = arrays.get("atlas/islands/orient")  # files written before islands could be transposed have none
        try:
            return cls(n, size, pad, torch.from_numpy(np.asarray(arrays["atlas/islands/affine"], np.float32).copy()),
                       torch.from_numpy(cells),
                       torch.from_numpy(np.asarray(arrays["atlas/islands/offset"]).astype(np.int64)),
                       None if orient is None else torch.from_numpy(np.asarray(orient).astype(np.int64)))
        except (InputError, ValueError, IndexError) as e:
            raise ModelFileError(f"atlas: {e}") from e


# --- building ----------------------------------------------------------------------------------------------------

def occupancy(t: np.ndarray, G: int, fill: float = 1.0) -> np.ndarray:
    """Occupied cells [G, G] bool of texel coordinates t [M, 2] (col, row): cells with a point, closed over gaps
    of up to 2 * fill cells (dilate by fill, erode by fill - 1), small enclosed holes filled. Computed on the
    points' bounding box with a margin wider than fill (the same cells as on the whole grid: every step is local
    or, for the holes, decided by what the empty margin connects to) and pasted into the grid."""
    out = np.zeros((G, G), bool)
    k = np.clip(np.floor(t).astype(np.int64), 0, G - 1)
    if len(k) == 0:
        return out
    m = int(math.ceil(fill)) + 2
    (c0, r0), (c1, r1) = np.maximum(k.min(0) - m, 0), np.minimum(k.max(0) + m + 1, G)
    out[r0:r1, c0:c1] = _occupancy_full(k - [c0, r0], (r1 - r0, c1 - c0), fill)
    return out


def _occupancy_full(k: np.ndarray, shape: tuple[int, int], fill: float) -> np.ndarray:
    """`occupancy` on a whole grid of `shape` for cells k [M, 2] (col, row) inside it."""
    from scipy.ndimage import distance_transform_edt

    hit = np.zeros(shape, bool)
    hit[k[:, 1], k[:, 0]] = True
    if not hit.any():
        return hit
    grown = distance_transform_edt(~hit) <= fill
    if fill > 1.0:  # erode back by fill - 1 (distance to the outside of the grown region), never below the hit cells
        grown = (distance_transform_edt(np.pad(grown, 1))[1:-1, 1:-1] > fill - 1.0) | hit
    return fill_small_holes(grown)


def fill_small_holes(occ: np.ndarray, max_cells: int = 256) -> np.ndarray:
    """occ [G, G] bool with its enclosed holes of at most max_cells cells filled: a lookup that lands in a hole
    (sparse samples) then reads the island's dilated colour instead of the background."""
    from scipy.ndimage import binary_fill_holes, label

    holes = binary_fill_holes(occ) & ~occ
    if not holes.any():
        return occ
    lab, k = label(holes)
    small = np.bincount(lab.reshape(-1), minlength=k + 1) <= max_cells
    small[0] = False
    return occ | small[lab]


def chart_islands(occ: np.ndarray, min_cells: int) -> tuple[np.ndarray, int]:
    """4-connected components of occ [G, G] with at least min_cells cells (the largest is always kept):
    (labels [G, G] int, -1 outside, 0..k-1 inside; k)."""
    from scipy.ndimage import label

    lab, k = label(occ)
    if k == 0:
        return np.full(occ.shape, -1, np.int64), 0
    sizes = np.bincount(lab.reshape(-1), minlength=k + 1)[1:]
    keep = sizes >= min_cells
    keep[int(np.argmax(sizes))] = True
    new = np.full(k + 1, -1, np.int64)
    new[1:][keep] = np.arange(int(keep.sum()))
    return new[lab], int(keep.sum())


def start_side(masks: list[np.ndarray], pad: int, density: float = 0.9) -> int:
    """Side of the square that holds the cells of the masks (each [h, w] bool) and their padding at `density`."""
    area = sum(int(m.sum()) + pad * (m.shape[0] + m.shape[1]) * 2 for m in masks)  # cells and their padding
    return int(math.ceil(math.sqrt(area / density)))


def _crop(sel: np.ndarray) -> tuple[np.ndarray, tuple[int, int]]:
    """sel [H, W] bool (not empty) -> (its bounding box [h, w] bool, (col, row) of the box's first cell)."""
    rr, kk = np.nonzero(sel)
    r0, k0 = int(rr.min()), int(kk.min())
    m = np.zeros((int(rr.max()) - r0 + 1, int(kk.max()) - k0 + 1), bool)
    m[rr - r0, kk - k0] = True
    return m, (k0, r0)


def split_island(mask: np.ndarray, limit: int, min_box_fill: float = 0.0,
                 min_length: int = 16) -> list[tuple[np.ndarray, tuple[int, int]]]:
    """Cut an island mask [h, w] bool into pieces whose bounding boxes are at most `limit` cells long and, when at
    least min_length long, fill at least min_box_fill of their box (curved, hollow islands leave most of it empty):
    a piece that fails is cut straight across its long side, at the row or column with the fewest cells (the
    shortest seam) among those that leave both sides within the limit (for a hollow piece, or one more than twice
    the limit: in its middle half); each 4-connected part is a piece. Returns [(piece [h', w'] bool, (col, row) of
    its first cell in mask)], covering every cell of mask once. A long island forces the square image to its length
    and a hollow one wastes its box; their pieces pack closer."""
    from scipy.ndimage import label

    out, todo = [], [(mask, (0, 0))]
    while todo:
        m, (k0, r0) = todo.pop()
        h, w = m.shape
        hollow = max(h, w) >= min_length and m.sum() < min_box_fill * h * w
        if max(h, w) <= limit and not hollow:
            out.append((m, (k0, r0)))
            continue
        across = w >= h  # cut across the columns of a wide piece, across the rows of a tall one
        length = w if across else h
        counts = m.sum(0 if across else 1)  # cells per column (row): the seam a cut before it leaves
        lo, hi = max(1, length - limit), min(length - 1, limit)
        if lo > hi or hollow:
            lo, hi = max(1, length // 4), max(1, length - length // 4)
        idx = np.arange(lo, hi + 1)
        cut = int(idx[np.lexsort((np.abs(2 * idx - length), counts[idx]))[0]])
        for part in ((m[:, :cut], (k0, r0)), (m[:, cut:], (k0 + cut, r0))) if across else \
                ((m[:cut], (k0, r0)), (m[cut:], (k0, r0 + cut))):
            pm, (pk, pr) = part
            lab, k = label(pm)
            for j in range(1, k + 1):
                sub, (dk, dr) = _crop(lab == j)
                todo.append((sub, (pk + dk, pr + dr)))
    return out


def _cell_mesh(mask: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Two triangles per True cell of mask [h, w]: (vertices [V, 2] float32 (col, row), triangles [T, 3] uint32)."""
    rr, cc = np.nonzero(mask)
    w = mask.shape[1]
    corner = lambda r, k: r * (w + 1) + k  # noqa: E731
    quads = np.stack([corner(rr, cc), corner(rr, cc + 1), corner(rr + 1, cc + 1), corner(rr + 1, cc)], -1)
    tris = np.concatenate([quads[:, [0, 1, 2]], quads[:, [0, 2, 3]]])
    used, inv = np.unique(tris, return_inverse=True)
    verts = np.stack([used % (w + 1), used // (w + 1)], -1).astype(np.float32)
    return verts, inv.reshape(-1, 3).astype(np.uint32)


def pack_islands(masks: list[np.ndarray], pad: int, size: int = 0, transpose: bool = False, search: int = 5):
    """Pack island cell masks (each [h, w] bool, cropped) with xatlas, `pad` texels of padding, each island whole
    (xatlas cuts an island that does not fit into slivers: that counts as not fitting). transpose: xatlas may
    transpose islands (a symmetry of the texel grid, recorded per island); else every island keeps its layout.
    size > 0: into one size x size image (None when they do not fit); 0: the smallest square found: xatlas's own
    packing (its image grows as it packs, nearly square) gives a side that holds them, then up to `search`
    packings into fixed squares bisect between it and the side the islands' cells with their padding fill
    exactly (start_side at density 1). Returns (offsets [I, 2] int (col, row), orient [I] int (ORIENT): mask cell
    (col, row) t goes to pixel ORIENT[orient] @ t + offset, side)."""
    if size > 0:
        got = _xatlas_pack(masks, pad, size, transpose)
        return None if got is None else (got[0], got[1], size)
    longest = max(max(m.shape) for m in masks) + 2 * pad
    lo = max(start_side(masks, pad, 1.0), longest) - 1  # no square this small holds them
    best = _xatlas_pack(masks, pad, 0, transpose)
    if best is not None:
        hi = max(best[2], best[3], longest)
        best = best[0], best[1], hi
    else:  # xatlas cut an island to fit its own image: grow a fixed square from the lower bound until none is cut
        hi = lo
        while best is None:
            if hi > 64 * (lo + 1):
                raise InputError("island layout: xatlas found no packing")
            hi = int(math.ceil(hi * 1.05)) + 1
            got = _xatlas_pack(masks, pad, hi, transpose)
            best = None if got is None else (got[0], got[1], hi)
    return bisect_side(lambda side: _xatlas_pack(masks, pad, side, transpose), lo, hi, best, search)


def bisect_side(pack, lo: int, hi: int, best, search: int, tol: float = 0.0):
    """The smallest square side in (lo, hi] a packer fills, by bisection: pack(side) -> (offsets, orient, ...) or
    None when the islands do not fit; lo: a side known not to hold them; best: the packing at hi, (offsets, orient,
    hi). At most `search` packings, none once hi - lo <= max(1, tol x hi). Returns the best (offsets, orient,
    side)."""
    for _ in range(search):
        if hi - lo <= max(1, int(tol * hi)):
            break
        mid = (lo + hi) // 2
        got = pack(mid)
        if got is None:
            lo = mid
        else:
            hi, best = mid, (got[0], got[1], mid)
    return best


def _xatlas_pack(masks, pad, size, transpose=False):
    """One xatlas packing of the masks into a size x size image (size 0: xatlas's own size): (offsets [I, 2],
    orient [I], W, H), or None when an island does not fit whole."""
    import xatlas

    atlas = xatlas.Atlas()
    verts = []
    for m in masks:
        v, t = _cell_mesh(m)
        verts.append(v)
        atlas.add_uv_mesh(v, t)
    opts = xatlas.PackOptions()
    # with bilinear, xatlas keeps one texel more around each island: islands end up >= 2 * pad - 1 apart (pixel
    # centres; measured), so with pad 2 every texel a bilinear lookup reads is nearer its own island
    opts.padding = max(int(pad) - 1, 0)
    opts.texels_per_unit = 1.0
    opts.rotate_charts = bool(transpose)  # xatlas's "rotation" transposes a chart: exact on the texel grid
    opts.rotate_charts_to_axis = False
    opts.bilinear = True
    side = size if size > 0 else start_side(masks, pad, 1.0)
    opts.bruteForce = bool(side <= BRUTE_FORCE_SIDE)  # tighter, slower: small atlases only
    opts.resolution = max(int(size), 0)
    atlas.generate(pack_options=opts)
    if size > 0 and atlas.atlas_count > 1:
        return None
    W, H = int(atlas.width), int(atlas.height)
    side = max(W, H) if size <= 0 else size
    offsets = np.zeros((len(masks), 2), np.int64)
    orient = np.zeros(len(masks), np.int64)
    for i, m in enumerate(masks):
        vmap, _, uv = atlas[i]
        placed = uv * np.array([W, H], np.float64)
        v = verts[i][vmap].astype(np.float64)
        for q in (range(len(ORIENT_NP)) if transpose else (0,)):
            d = placed - v @ ORIENT_NP[q].T
            if np.ptp(d, axis=0).max() <= 0.01:
                break
        else:  # no symmetry of the grid maps the island onto its place: xatlas cut it
            return None
        orient[i] = q
        offsets[i] = np.floor(np.median(d, axis=0) + 0.5).astype(np.int64)  # xatlas places at half-texels
        corners = np.array([[0, 0], [m.shape[1], 0], [0, m.shape[0]], [m.shape[1], m.shape[0]]]) @ ORIENT_NP[q].T
        lo, hi = corners.min(0) + offsets[i], corners.max(0) + offsets[i]
        shift = np.maximum(hi - side, 0)  # the rounding may reach one texel past the image
        offsets[i] += np.maximum(shift - lo, 0) - shift
    return offsets, orient, W, H


def min_area_angle(t: np.ndarray, steps: int = 90) -> float:
    """Rotation (radians, in [0, pi/2)) that gives 2-D points t [M, 2] their smallest axis-aligned bounding box."""
    from scipy.spatial import ConvexHull, QhullError

    if len(t) < 3:
        return 0.0
    try:
        h = t[ConvexHull(t).vertices]
    except (QhullError, ValueError):
        return 0.0
    best, best_a = math.inf, 0.0
    for a in np.linspace(0, math.pi / 2, steps, endpoint=False):
        c, s = math.cos(a), math.sin(a)
        r = h @ np.array([[c, s], [-s, c]])
        area = np.ptp(r[:, 0]) * np.ptp(r[:, 1])
        if area < best - 1e-9:
            best, best_a = area, a
    return float(best_a)


def build_islands(probs: torch.Tensor, uv: torch.Tensor, scale: np.ndarray, pad: int, size: int = 0,
                  fill=1.0, min_cells: int = 8, rotate: bool = True, transpose: bool = True,
                  split: float = 0.0, min_fill: float = 0.0, packer: str = "xatlas",
                  pack_orders: int = 4) -> IslandLayout | None:
    """The island layout of samples with chart probabilities probs [S, n] and chart coordinates uv [S, n, 2], each
    chart at scale[c] texels per uv unit (rotated to its smallest bounding box when rotate); fill: occupancy
    radius in texels (one, or [n] per chart). transpose: the packer may transpose islands (pack_islands).
    split > 0: islands longer than split x the side of the square they would fill at 100 % (size when fixed),
    and those longer than a quarter of that that fill less than min_fill of their bounding box, are cut into
    pieces (split_island), each its own island of the same chart.
    size > 0: fixed image side (None when the islands do not fit). packer: "xatlas" (pack_islands) or "bitmap"
    (core/atlas/bitmap_pack.py: by the islands' exact cells, each square tried with its first pack_orders greedy
    orders)."""
    n = probs.shape[1]
    fill = np.broadcast_to(np.asarray(fill, np.float64), (n,))
    owner = probs.argmax(-1).cpu().numpy()
    uvn = uv.detach().cpu().numpy().astype(np.float64)
    affine = np.zeros((n, 2, 3))
    affine[:, 0, 0] = affine[:, 1, 1] = 1.0
    per_chart = []
    for c in range(n):
        sel = owner == c
        if not sel.any():
            per_chart.append(None)
            continue
        u = np.clip(uvn[sel, c], *UV_REACH)
        a = min_area_angle(u[np.linspace(0, len(u) - 1, min(len(u), 20000)).astype(np.int64)]) if rotate else 0.0
        rot = float(scale[c]) * np.array([[math.cos(a), -math.sin(a)], [math.sin(a), math.cos(a)]])
        t = u @ rot.T
        margin = float(fill[c]) + 2.0
        shift = margin - t.min(0)
        affine[c, :, :2], affine[c, :, 2] = rot, shift
        per_chart.append(t + shift)
    G = int(math.ceil(max(float((t.max(0)).max()) for t in per_chart if t is not None))) + int(fill.max()) + 3
    cells = np.full((n, G, G), -1, np.int64)
    pieces = []  # (chart, cropped mask [h, w] bool, crop (col, row) of its cell (0, 0) in the chart)
    for c in range(n):
        if per_chart[c] is None:
            continue
        occ = occupancy(per_chart[c], G, float(fill[c]))
        lab, k = chart_islands(occ, min_cells)
        for j in range(k):
            m, crop = _crop(lab == j)
            pieces.append((c, m, crop))
    if not pieces:
        raise InputError("island layout: no sample falls in any chart")
    if split > 0:  # islands longer than split x the square they would pack into are cut across, where narrowest
        limit = max(int(split * (size if size > 0 else start_side([m for _, m, _ in pieces], pad, 1.0))), 4 * pad + 8)
        pieces = [(c, m, (k0 + dk, r0 + dr)) for c, m0, (k0, r0) in pieces
                  for m, (dk, dr) in split_island(m0, limit, min_fill, max(limit // 4, 4 * pad + 8))]
    masks = [m for _, m, _ in pieces]
    if packer == "bitmap":
        from core.atlas.bitmap_pack import ORDERS, pack_bitmap
        packed = pack_bitmap(masks, pad, size, transpose=transpose, orders=ORDERS[:max(int(pack_orders), 1)])
    elif packer == "xatlas":
        packed = pack_islands(masks, pad, size, transpose=transpose)
    else:
        raise InputError(f"island layout: unknown packer {packer!r} (xatlas or bitmap)")
    if packed is None:
        return None
    offsets, orient, side = packed
    for i, (c, m, (k0, r0)) in enumerate(pieces):
        cells[c, r0:r0 + m.shape[0], k0:k0 + m.shape[1]][m] = i
    # mask cell (0, 0) is chart cell (col k0, row r0): pixel = M (t - crop) + offset = M t + (offset - M crop)
    crop = np.asarray([p[2] for p in pieces], np.int64)
    offsets = offsets - np.einsum("iab,ib->ia", ORIENT_NP[orient], crop)
    return IslandLayout(n, side, pad, torch.from_numpy(affine).float(), torch.from_numpy(cells),
                        torch.from_numpy(offsets), torch.from_numpy(orient))
