"""Texture lookups through the atlas's stored surface samples, and the bake that fits the texels they read.

The chart networks map any canonical point to texture coordinates, but the points a frame looks up are not the
samples the texture was made from: they lie up to a few sample spacings off them, across the samples' slab or
between them, where the map's coordinates move by a texel or more. A texture sharp enough to hold a hard-edged
retexture then reads another place's colour there (docs/atlas.md, "Lookups through the samples and the
fitted bake").

Here a point's colour is instead the weighted mean of what its k nearest stored samples read, each at its own
chart coordinates (bilinear, as every lookup reads a texel): the texels a sample reads are the texels the bake
wrote for that sample (`fit_texels`, a least-squares fit of those texels to a colour function at the samples), so
a lookup returns the baked colour of the surface next to it. Weights fall with the distance relative to the nearest
sample's, exp(-½ (d / d₁)²): a point on a sample reads that sample alone, one halfway between two reads both
equally. A painted texel reaches every sample that reads it. The k-d tree over the samples and their coordinates
are built once per atlas and layout (`sample_lookup`).
"""
from __future__ import annotations

import numpy as np
import torch
import torch.nn.functional as F

from core.atlas.packing import bilinear_entries, blend_charts, chart_coords
from core.util.errors import InputError

LOOKUP_K = 2  # nearest samples a lookup blends (EditConfig.lookup_k, AtlasConfig.footprint_lookup; docs/atlas.md)
FIT_SMOOTHNESS = 0.03  # weight of a texel pair's squared difference against one sample's squared residual
FIT_DAMPING = 1e-4     # pull of every texel towards the image the fit starts from (keeps the system definite)
FIT_ITERATIONS = 300   # conjugate-gradient iterations per colour channel


class SampleLookup:
    """The stored samples of one atlas [S, 3], a k-d tree over them and each sample's chart coordinates.

    Island layouts: each sample's own chart, placed in the packed image (`chart` [S], `uv` [S, 2]); the grid: the
    chart probabilities [S, n] and coordinates [S, n, 2], blended as every grid lookup blends them."""

    def __init__(self, atlas):
        from scipy.spatial import cKDTree

        samples = atlas.bake_samples
        if samples is None or samples.shape[0] == 0:
            raise InputError("this atlas keeps no surface samples (an older model file); `pointgt atlas MODEL DATA "
                             "--texel-map-only` stores them, or render with lookups through the charts")
        self.source = samples  # the atlas's own tensor: `sample_lookup` rebuilds when the atlas holds another
        self.samples = samples.float().cpu()
        self.islands = atlas.islands
        self.layout = atlas.layout
        self.tree = cKDTree(self.samples.numpy().astype(np.float64))
        probs, uv = atlas.chart_uv(self.samples, own_chart_only=True)
        if self.islands:
            own = probs.argmax(-1)
            self.chart, self.uv, self.probs = own.cpu(), chart_coords(uv, own).cpu(), None
        else:
            self.chart, self.uv, self.probs = None, uv.cpu(), probs.cpu()

    def read(self, textures: torch.Tensor) -> torch.Tensor:
        """What every sample reads: textures [n, C, R, R] (an island layout's n views of one image) -> [S, C]."""
        if self.islands:
            g = (self.uv.to(textures.device, textures.dtype) * 2 - 1)[None, None]  # [1, 1, S, 2]
            return F.grid_sample(textures[:1], g, mode="bilinear", padding_mode="border",
                                 align_corners=False)[0, :, 0].t()
        return blend_charts(textures, self.uv.to(textures.device), self.probs.to(textures.device))

    def neighbours(self, x: torch.Tensor, k: int) -> tuple[torch.Tensor, torch.Tensor]:
        """x [M, 3] (finite) -> (indices [M, k] of the k nearest samples, weights [M, k] summing to 1)."""
        k = max(1, min(int(k), self.samples.shape[0]))
        # the tree's queries run on as many threads as torch may use (one with --threads 1)
        d, j = self.tree.query(x.detach().cpu().double().numpy(), k=k, workers=max(1, torch.get_num_threads()))
        d, j = np.asarray(d).reshape(len(x), k), np.asarray(j).reshape(len(x), k)
        scale = np.maximum(d[:, :1], 1e-12)
        w = np.exp(-0.5 * (d / scale) ** 2)
        w = w / w.sum(1, keepdims=True)
        return torch.from_numpy(j), torch.from_numpy(w)

    def lookup(self, read: torch.Tensor, x: torch.Tensor, k: int) -> torch.Tensor:
        """read [S, C] (`read` of a texture), x [M, 3] canonical points on the atlas's surface (`Atlas.on_surface`)
        -> [M, C]. Non-finite points give NaN rows."""
        out = torch.full((x.shape[0], read.shape[1]), float("nan"), dtype=read.dtype, device=read.device)
        ok = torch.isfinite(x).all(-1)
        if bool(ok.any()):
            j, w = self.neighbours(x[ok], k)
            vals = read[j.reshape(-1).to(read.device)].view(j.shape[0], j.shape[1], -1)
            out[ok] = (w.to(read.device, read.dtype)[..., None] * vals).sum(1)
        return out


def keeps_samples(atlas) -> bool:
    """Whether the atlas keeps its surface samples (every model fitted since they are stored; older files do not)."""
    return atlas is not None and atlas.bake_samples is not None and atlas.bake_samples.shape[0] > 0


def sample_lookup(atlas) -> SampleLookup:
    """The atlas's SampleLookup, built on first use and kept until its samples or layout change."""
    cached = getattr(atlas, "_sample_lookup", None)
    if cached is not None and cached.layout is atlas.layout and cached.source is atlas.bake_samples:
        return cached
    atlas._sample_lookup = SampleLookup(atlas)
    return atlas._sample_lookup


def chart_texel_matrix(atlas, lk: SampleLookup):
    """What each sample reads as a sparse matrix [S, n R²] over the atlas's chart textures (texel (c, row, col) is
    column (c R + row) R + col, as the footprint refit indexes them): `packing.bilinear_entries`; island layouts in
    each sample's own chart (n views of one image), the grid blended over the charts by their probabilities."""
    import scipy.sparse as sp

    S = len(lk.samples)
    if lk.islands:
        sid, chart, p, uv = torch.arange(S), lk.chart, torch.ones(S, dtype=torch.float64), lk.uv
    else:
        sid, chart = torch.nonzero(lk.probs > 0, as_tuple=True)
        p, uv = lk.probs[sid, chart].double(), lk.uv[sid, chart]
    rows, cols, vals = bilinear_entries(sid, chart, p, uv.double(), atlas.layout.R)
    return sp.csr_matrix((vals.numpy(), (rows.numpy(), cols.numpy())), shape=(S, atlas.n * atlas.layout.R ** 2))


def lookup_texel_rows(lk: SampleLookup, x: torch.Tensor, k: int, per_sample):
    """What points x [Q, 3] (finite, on the atlas's surface) read of the texels, as a CSR matrix [Q, T] with sorted
    columns: W @ per_sample, W [Q, S] the points' blend weights over the samples (`SampleLookup.neighbours`) and
    per_sample [S, T] CSR (`chart_texel_matrix`), gathered row by row (each point's k samples' entries, weighted)
    instead of a general sparse product, whose work grows with T (every column of the atlas's charts) on each
    call."""
    import scipy.sparse as sp

    j, w = lk.neighbours(x, k)
    Q, kk = j.shape
    jj, ww = j.reshape(-1).numpy(), w.reshape(-1).numpy()
    start, cnt = per_sample.indptr[jj], per_sample.indptr[jj + 1] - per_sample.indptr[jj]
    total = int(cnt.sum())
    at = np.repeat(start - (np.cumsum(cnt) - cnt), cnt) + np.arange(total)  # each entry's place in per_sample
    out = sp.csr_matrix((np.repeat(ww, cnt) * per_sample.data[at], (np.repeat(np.repeat(np.arange(Q), kk), cnt),
                                                                   per_sample.indices[at])),
                        shape=(Q, per_sample.shape[1]))
    out.sum_duplicates()  # one entry per (point, texel); sorts the columns
    out.eliminate_zeros()  # a sample whose weight underflowed to 0 reads nothing, as in the product
    return out


def packed_read_matrix(atlas, lk: SampleLookup, H: int, W: int):
    """`chart_texel_matrix` over the packed image's H*W pixels: what each sample reads of the packed image,
    `SampleLookup.read` as a linear map (an island layout's charts all read the image itself, origin (0, 0))."""
    import scipy.sparse as sp

    m = chart_texel_matrix(atlas, lk).tocoo()
    R = atlas.layout.R
    chart, pix = m.col // (R * R), m.col % (R * R)
    origin = atlas.layout.origins().long().numpy()  # [n, 2] (row, col)
    packed = (origin[chart, 0] + pix // R) * W + origin[chart, 1] + pix % R
    return sp.csr_matrix((m.data, (m.row, packed)), shape=(m.shape[0], H * W))


def _pair_matrix(atlas, H: int, W: int):
    """Differences of horizontally and vertically adjacent texels of one island (island layouts) or one chart
    square (the grid), as a sparse matrix [P, H*W]."""
    import scipy.sparse as sp

    if atlas.islands:
        lab = atlas.layout.label.cpu().numpy().reshape(-1)
    else:
        lab = np.full(H * W, -1, np.int64)
        R = atlas.layout.R
        grid = lab.reshape(H, W)
        for c in range(atlas.n):
            r0, c0 = atlas.layout.origin(c)
            grid[r0:r0 + R, c0:c0 + R] = c
    idx = np.arange(H * W).reshape(H, W)
    a = np.concatenate([idx[:, :-1].reshape(-1), idx[:-1, :].reshape(-1)])
    b = np.concatenate([idx[:, 1:].reshape(-1), idx[1:, :].reshape(-1)])
    keep = (lab[a] == lab[b]) & (lab[a] >= 0)
    a, b = a[keep], b[keep]
    P = len(a)
    ar = np.arange(P)
    return sp.csr_matrix((np.r_[np.ones(P), -np.ones(P)], (np.r_[ar, ar], np.r_[a, b])), shape=(P, H * W))


@torch.no_grad()
def fit_texels(atlas, image: torch.Tensor, target: torch.Tensor, smoothness: float = FIT_SMOOTHNESS,
               iterations: int = FIT_ITERATIONS) -> torch.Tensor:
    """The packed image [H, W, C] changed as little as it takes for every stored sample to read its target colour.

    Minimises Σ_s |read_s(image + D) − target_s|² + smoothness Σ_pairs |D_a − D_b|² + FIT_DAMPING |D|² over the
    change D (pairs: adjacent texels of one island, or of one chart square for the grid), by conjugate gradients
    per channel; texels no sample reads follow their island's neighbours smoothly. target [S, C] at the atlas's
    stored samples (`atlas.bake_samples`). Returns the new image clamped to [0, 1] (the input's dtype and device)."""
    from scipy.sparse import identity
    from scipy.sparse.linalg import cg

    lk = sample_lookup(atlas)
    img = torch.as_tensor(image)
    H, W, C = img.shape
    if target.shape != (len(lk.samples), C):
        raise InputError(f"fit_texels: expected targets [{len(lk.samples)}, {C}], got {tuple(target.shape)}")
    A = packed_read_matrix(atlas, lk, H, W)
    D = _pair_matrix(atlas, H, W)
    t0 = img.detach().double().cpu().numpy().reshape(-1, C)
    res = target.detach().double().cpu().numpy() - A @ t0
    res = np.nan_to_num(res, nan=0.0)
    K = (A.T @ A) + smoothness * (D.T @ D) + FIT_DAMPING * identity(H * W, format="csr")
    out = t0.copy()
    for ch in range(C):
        rhs = A.T @ res[:, ch]
        if not np.any(rhs):
            continue
        d, _ = cg(K, rhs, maxiter=iterations, rtol=1e-6)
        out[:, ch] += d
    new = torch.from_numpy(np.clip(out, 0.0, 1.0).reshape(H, W, C))
    return new.to(img.device, img.dtype)
