"""Projection onto the middle of the surface samples' slab, applied before every chart lookup.

Stage 1's surface points form a slab a few sample spacings thick, and the fitted chart maps change across that slab
about as fast as along it (docs/atlas.md, "Where the retexture's gap to the perfect atlas comes from"): a lookup a
little off the slab's middle then reads another place's texel. Projecting every point the atlas is asked about —
the render's canonical points, the samples the texture is fitted from, the texel map's samples and the samples a
bake splats from — onto one smooth mid-surface first makes all of them read the chart map on that surface only, so
where in the slab a point sits no longer matters.

The mid-surface is described by anchor planes: for a fixed subset of the samples, the direction of least spread
(PCA) of their `neighbours` nearest samples as normal, through the slab's middle there (the constant term of a
quadric height field fitted to those samples, which unlike their centroid does not sit inside a bend). A
neighbourhood that wide spans the slab's whole thickness, so its middle is well defined and its normal is stable
(with 48 neighbours the normals of adjacent tube samples disagree; `core/atlas/fit.py` `sample_normals`); an
anchor whose neighbourhood is not clearly thinner across than along defines no plane. A point is moved along the
normals onto the Gaussian-weighted mean of its nearest anchors' planes. Thin parts (narrower than a neighbourhood)
are put on one sheet, which folds their texels (docs/atlas.md measures it).
"""
from __future__ import annotations

import numpy as np
import torch
from scipy.spatial import cKDTree

from core.atlas.config import WORLD_SCALES
from core.util.errors import InputError


def _height_at_centroid(d: np.ndarray, vec: np.ndarray) -> np.ndarray:
    """Offsets d [m, K, 3] of each neighbourhood's samples from its centroid, principal axes vec [m, 3, 3] (columns,
    least spread first) -> [m] height of the slab's middle above the centroid along the first axis: a least-squares
    quadric h(u, v) over the tangent coordinates, read at (0, 0). On a curved surface the centroid lies inside the
    bend (by about r^2 / 4R for a neighbourhood of radius r); the quadric's constant term does not. 0 where the fit
    is not defined."""
    h, u, v = (np.einsum("mki,mi->mk", d, vec[:, :, j]) for j in range(3))
    scale = np.sqrt(np.maximum((u * u + v * v).mean(1, keepdims=True), 1e-300))
    u, v = u / scale, v / scale
    A = np.stack([np.ones_like(u), u, v, u * u, u * v, v * v], -1)          # [m, K, 6]
    ata = np.einsum("mki,mkj->mij", A, A) + 1e-6 * d.shape[1] * np.eye(6)
    atb = np.einsum("mki,mk->mi", A, h)
    with np.errstate(all="ignore"):
        try:
            coef = np.linalg.solve(ata, atb[..., None])[..., 0]
        except np.linalg.LinAlgError:
            return np.zeros(len(d))
    a = coef[:, 0]
    return np.where(np.isfinite(a), a, 0.0)


def _candidate_sizes(K: int, smallest: int = 32) -> list[int]:
    """Neighbourhood sizes an adaptive anchor chooses from: K, K/2, K/4, K/8, none below `smallest` (K itself
    always)."""
    return sorted({K} | {K >> j for j in range(1, 4) if K >> j >= smallest})


def _flattest(nb: np.ndarray, sizes: list[int]) -> np.ndarray:
    """Neighbourhoods nb [m, K, 3] (nearest first) -> [m] index into sizes of the prefix whose spread across (least
    PCA eigenvalue) is the smallest share of its spread along (the middle one); ties and undefined ratios: the
    largest."""
    ratio = np.full((len(nb), len(sizes)), np.inf)
    local = nb - nb[:, :1]                                               # moments about the anchor: no cancellation
    s1 = np.cumsum(local, 1)                                             # [m, K, 3] running sums, every size at once
    s2 = np.cumsum(local[..., :, None] * local[..., None, :], 1)         # [m, K, 3, 3]
    for j, kk in enumerate(sizes):
        mu = s1[:, kk - 1] / kk
        w = np.linalg.eigvalsh(s2[:, kk - 1] / kk - mu[:, :, None] * mu[:, None, :])
        with np.errstate(all="ignore"):
            r = np.maximum(w[:, 0], 0.0) / w[:, 1]
        ratio[:, j] = np.where(np.isfinite(r) & (w[:, 1] > 0), r, np.inf)
    # the largest size among those within 1 % of the smallest ratio (a flat sheet: every size alike -> the widest)
    best = ratio.min(1, keepdims=True)
    ok = ratio <= best * 1.01 + 1e-300
    return len(sizes) - 1 - np.argmax(ok[:, ::-1], axis=1)


def _anchor_planes(nb: np.ndarray, max_ratio: float) -> tuple[np.ndarray, np.ndarray]:
    """Neighbourhoods nb [m, K, 3] -> centres [m, 3] on the slab's middle and unit normals [m, 3] (zero where the
    neighbourhood spans no clear plane: spread across above max_ratio x the spread along its second axis)."""
    mu = nb.mean(1)
    d = nb - mu[:, None]
    w, vec = np.linalg.eigh(np.einsum("mki,mkj->mij", d, d))
    plane = np.isfinite(vec[:, :, 0]).all(-1) & (w[:, 1] > 1e-12 * np.maximum(w[:, 2], 1e-300)) \
        & (np.maximum(w[:, 0], 0.0) <= max_ratio ** 2 * w[:, 1])
    centres = mu + _height_at_centroid(d, vec)[:, None] * vec[:, :, 0] * plane[:, None]
    n0 = vec[:, :, 0] / np.maximum(np.linalg.norm(vec[:, :, 0], axis=1, keepdims=True), 1e-300)
    return centres, np.where(plane[:, None], n0, 0.0)


class SurfaceProjection:
    """Anchor planes of a sample slab: centres [m, 3] (points on the slab's middle) and unit normals [m, 3] (zero where
    a neighbourhood spans no plane: that anchor leaves points where they are); bandwidth h (world units) of the
    weights over the `k` nearest anchors.

    project(x [M, 3]) -> [M, 3]: x moved along the anchors' normals onto their planes (finite for any finite x;
    the identity when there are no anchors).
    """

    def __init__(self, centres, normals, bandwidth: float, k: int = 8):
        # kept at float32 precision, as the model file stores them: a loaded atlas projects bit for bit the same
        c = np.asarray(centres, dtype=np.float32).reshape(-1, 3).astype(np.float64)
        nrm = np.asarray(normals, dtype=np.float32).reshape(-1, 3).astype(np.float64)
        if c.shape != nrm.shape or not (np.isfinite(c).all() and np.isfinite(nrm).all()):
            raise InputError(f"surface projection: centres and normals must be finite [m, 3] arrays of one shape, "
                             f"got {c.shape} and {nrm.shape}")
        length = np.linalg.norm(nrm, axis=1)
        if not ((length < 1e-6) | (np.abs(length - 1) < 1e-3)).all():
            raise InputError("surface projection: every normal must be a unit vector or zero")
        if not WORLD_SCALES[0] <= float(bandwidth) <= WORLD_SCALES[1] or not 1 <= int(k) <= 64:
            raise InputError(f"surface projection: bandwidth must lie in {WORLD_SCALES[0]:g}-{WORLD_SCALES[1]:g} "
                             f"(world units) and 1 <= k <= 64, got {bandwidth!r}, {k!r}")
        self.centres, self.normals = c, nrm
        self.bandwidth, self.k = float(bandwidth), int(k)
        self._tree = cKDTree(c) if len(c) else None

    @classmethod
    def from_samples(cls, xyz, neighbours: int = 1024, max_ratio: float = 0.7, max_anchors: int = 20000, k: int = 8,
                     seed: int = 0, chunk: int = 500, adaptive: bool = False) -> "SurfaceProjection":
        """Anchor planes from surface samples xyz [S, 3]: at most `max_anchors` anchors (a fixed random subset),
        each the PCA normal of its `neighbours` nearest samples through the slab's middle there; the bandwidth is
        the anchors' median nearest-anchor distance. An anchor whose neighbourhood is not clearly thinner across
        than along (spread across / spread along the second axis above `max_ratio`: a slab as thick as it is
        wide, or an edge where two faces meet) defines no plane and gets a zero normal (points near it stay
        where they are). adaptive: each anchor's neighbourhood is the one of `neighbours`, 1/2, 1/4 and 1/8 of it
        (at least 32 samples) whose spread across is the smallest share of its spread along — a neighbourhood
        stops growing where a bend, an edge or the other face of a thin part makes it thicker."""
        x = np.asarray(xyz, dtype=np.float64).reshape(-1, 3)
        if not np.isfinite(x).all():
            raise InputError("surface projection: the samples contain NaN or infinite values")
        S = len(x)
        if S < 4:
            return cls(np.zeros((0, 3)), np.zeros((0, 3)), 1.0, k)
        K = min(int(neighbours), S)
        tree = cKDTree(x)
        sel = np.sort(np.random.default_rng(seed).permutation(S)[:max_anchors])
        centres, normals = np.zeros((len(sel), 3)), np.zeros((len(sel), 3))
        for s in range(0, len(sel), chunk):
            _, idx = tree.query(x[sel[s:s + chunk]], k=K)
            nb = x[idx.reshape(-1, K)]                                    # [m, K, 3], nearest first
            sizes = _candidate_sizes(K) if adaptive else [K]
            size = np.full(len(nb), K) if len(sizes) == 1 else np.asarray(sizes)[_flattest(nb, sizes)]
            for kk in sizes:
                rows = np.nonzero(size == kk)[0]
                if len(rows) == 0:
                    continue
                c, n = _anchor_planes(nb[rows, :kk], max_ratio)
                centres[s + rows], normals[s + rows] = c, n
        if len(centres) > 1:
            dd, _ = cKDTree(centres).query(centres, k=2)
            h = float(np.median(dd[:, 1]))
        else:
            h = 0.0
        if not h > 0:  # coincident anchors: any positive width gives them equal weights
            h = max(float(np.ptp(x, axis=0).max()), 1e-6)
        return cls(centres, normals, h, k)

    def orient(self, neighbours: int = 8) -> "SurfaceProjection":
        """Give the anchors' normals one side (in place; the projection does not change, it is even in n): along a
        minimum spanning tree of the anchors' `neighbours`-nearest graph weighted by 1 - |cos| of their normals
        (smooth parts first), each anchor's normal is turned to agree with its parent's. Each connected part of the
        surface gets its own side (arbitrary); anchors without a plane are left out. Returns self."""
        from scipy.sparse import coo_matrix
        from scipy.sparse.csgraph import breadth_first_order, connected_components, minimum_spanning_tree

        have = np.nonzero(np.linalg.norm(self.normals, axis=1) > 0.5)[0]
        if len(have) < 2:
            return self
        c, nrm = self.centres[have], self.normals[have]
        k = min(int(neighbours), len(have) - 1)
        _, nb = cKDTree(c).query(c, k=k + 1)
        rows, cols = np.repeat(np.arange(len(have)), k), nb[:, 1:].reshape(-1)
        w = 1.0 - np.abs(np.einsum("ij,ij->i", nrm[rows], nrm[cols])) + 1e-6  # > 0: a stored edge
        tree = minimum_spanning_tree(coo_matrix((w, (rows, cols)), shape=(len(have),) * 2).tocsr())
        tree = tree + tree.T
        n_parts, part = connected_components(tree, directed=False)
        flip = np.ones(len(have))
        for root in np.unique(part, return_index=True)[1]:
            order, parent = breadth_first_order(tree, int(root), directed=False)
            for i in order[1:]:  # parents come first in breadth-first order
                j = parent[i]
                flip[i] = flip[j] * (1.0 if nrm[i] @ nrm[j] >= 0 else -1.0)
        self.normals[have] = nrm * flip[:, None]
        return self

    def __len__(self) -> int:
        return len(self.centres)

    def project(self, x) -> torch.Tensor:
        """Points x [M, 3] (torch or numpy, finite) -> [M, 3] on the anchors' mid-surface, same dtype and device
        (torch tensors; numpy input gives float32 tensors)."""
        xt = torch.as_tensor(x)
        if xt.dim() != 2 or xt.shape[-1] != 3:
            raise InputError(f"surface projection: expected points [M, 3], got {tuple(xt.shape)}")
        if self._tree is None or xt.shape[0] == 0:
            return xt.clone() if isinstance(x, torch.Tensor) else xt.float()
        q = xt.detach().cpu().double().numpy()
        k = min(self.k, len(self.centres))
        dist, idx = self._tree.query(q, k=k)
        dist, idx = dist.reshape(len(q), k), idx.reshape(len(q), k)
        # Gaussian weights relative to the nearest anchor, so far points still weigh their nearest anchors (no 0/0)
        w = np.exp(-0.5 * (dist ** 2 - dist[:, :1] ** 2) / self.bandwidth ** 2)
        w /= w.sum(1, keepdims=True)
        n = self.normals[idx]                                             # [M, k, 3]
        off = np.einsum("mki,mki->mk", q[:, None] - self.centres[idx], n)  # signed distance to each plane
        moved = q - np.einsum("mk,mk,mki->mi", w, off, n)
        out = torch.from_numpy(moved).to(dtype=xt.dtype if xt.is_floating_point() else torch.float32)
        return out.to(xt.device)

    def normals_at(self, x) -> torch.Tensor:
        """Unit normals of the mid-surface at points x [M, 3] (torch or numpy, finite) -> [M, 3] float32 tensor on
        x's device: the anchors' normals under the projection's weights, each turned to agree with the nearest
        anchor's (PCA normals have no sign); zero where no nearby anchor defines a plane (or there are no anchors).
        The sign is arbitrary; what uses it (the tangent part of a Jacobian) is even in n."""
        xt = torch.as_tensor(x)
        if xt.dim() != 2 or xt.shape[-1] != 3:
            raise InputError(f"surface projection: expected points [M, 3], got {tuple(xt.shape)}")
        if self._tree is None or xt.shape[0] == 0:
            return torch.zeros(xt.shape[0], 3, dtype=torch.float32, device=xt.device)
        q = xt.detach().cpu().double().numpy()
        k = min(self.k, len(self.centres))
        dist, idx = self._tree.query(q, k=k)
        dist, idx = dist.reshape(len(q), k), idx.reshape(len(q), k)
        w = np.exp(-0.5 * (dist ** 2 - dist[:, :1] ** 2) / self.bandwidth ** 2)
        n = self.normals[idx]                                             # [M, k, 3]
        ref = n[np.arange(len(q)), np.argmax(np.linalg.norm(n, axis=2) > 0.5, axis=1)]  # nearest anchor with a plane
        sign = np.where(np.einsum("mki,mi->mk", n, ref) < 0, -1.0, 1.0)
        mean = np.einsum("mk,mk,mki->mi", w, sign, n)
        length = np.linalg.norm(mean, axis=1, keepdims=True)
        # a plane's weight must dominate: where the anchors with planes are far (their weight tiny) or cancel, none
        ok = length > 0.1 * w.sum(1, keepdims=True)
        out = np.where(ok, mean / np.maximum(length, 1e-300), 0.0)
        return torch.from_numpy(out.astype(np.float32)).to(xt.device)

    def to_arrays(self) -> dict[str, np.ndarray]:
        return {"atlas/surface/centres": self.centres.astype(np.float32),
                "atlas/surface/normals": self.normals.astype(np.float32)}

    def meta(self) -> dict:
        return {"bandwidth": self.bandwidth, "k": self.k}

    @classmethod
    def from_arrays(cls, arrays: dict, meta: dict) -> "SurfaceProjection":
        return cls(arrays["atlas/surface/centres"], arrays["atlas/surface/normals"], float(meta["bandwidth"]),
                   int(meta.get("k", 8)))
