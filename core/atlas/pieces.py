"""Island charts cut where their map lays one part of the surface over another with the same orientation.

A chart map can send two places of one sheet, far apart on the surface, to the same texels with the same
orientation (around a region whose surface angle exceeds a full turn — an inner corner, a bend — a planar map
must overlap or compress; docs/atlas.md "Overlapping layers"). The side split (core/atlas/sides.py) separates only
opposite orientations. Here every (sub-)chart's samples are grouped into patches (voxels of `voxel` sample spacings)
and the patches are grown into pieces over the surface (breadth first over touching voxels): a patch
joins the piece only if none of its texel cells is already held by a patch of the piece that lies more than `far`
sample spacings away *and* either more than `far` spacings off the patch's tangent plane (a layer above or below)
or more than `texels` texels from where the map's local linear part at the patch would put it (the map came back
to these texels from elsewhere; a map that only compresses there keeps its patches together). Pieces with fewer than `min_samples` samples go to
the neighbouring piece they share most edges with. Each piece becomes its own layout chart (its own islands).

A point's piece is that of the nearest patch centre of its chart (`ChartPieces.expand`), the same rule for the
samples the layout and texture are built from, the texel map, baking and every later lookup.
"""
from __future__ import annotations

import math

import numpy as np
import torch
from scipy.spatial import cKDTree

from core.util.errors import InputError
from core.util.jit import njit

MAX_CELLS = 1 << 24  # texel cells of the grid the growth claims cells in (coarser beyond)


def _claim_py(p, cell_ptr, cells, claim, touched, nt):
    """Patch p claims its texel cells that no patch of the piece holds yet (noted in touched[nt:]); returns nt."""
    for q in range(cell_ptr[p], cell_ptr[p + 1]):
        if claim[cells[q]] < 0:
            claim[cells[q]] = p
            touched[nt] = cells[q]
            nt += 1
    return nt


_claim = njit(_claim_py)


def _grow_py(order, adj_ptr, adj, cell_ptr, cells, cen, tcen, jac, nrm, n_cells, far2, texels2):
    """Breadth-first growth of pieces over patches (module doc). Returns labels [P] (0..k-1) and k."""
    P = len(order)
    label = np.full(P, -1, np.int64)
    claim = np.full(n_cells, -1, np.int64)
    touched = np.empty(len(cells) + 1, np.int64)
    queue = np.empty(P, np.int64)
    k = 0
    for s0 in order:
        if label[s0] >= 0:
            continue
        nt, qh, qt = 0, 0, 1
        queue[0] = s0
        label[s0] = k
        nt = _claim(s0, cell_ptr, cells, claim, touched, nt)
        while qh < qt:
            i = queue[qh]
            qh += 1
            for e in range(adj_ptr[i], adj_ptr[i + 1]):
                j = adj[e]
                if label[j] >= 0:
                    continue
                ok = True
                for q in range(cell_ptr[j], cell_ptr[j + 1]):
                    o = claim[cells[q]]
                    if o < 0:
                        continue
                    d0, d1, d2 = cen[o, 0] - cen[j, 0], cen[o, 1] - cen[j, 1], cen[o, 2] - cen[j, 2]
                    if d0 * d0 + d1 * d1 + d2 * d2 <= far2:
                        continue
                    # where the map's linear part at j would put o, against where o's texels are
                    p0 = d0 * jac[j, 0, 0] + d1 * jac[j, 1, 0] + d2 * jac[j, 2, 0] - (tcen[o, 0] - tcen[j, 0])
                    p1 = d0 * jac[j, 0, 1] + d1 * jac[j, 1, 1] + d2 * jac[j, 2, 1] - (tcen[o, 1] - tcen[j, 1])
                    dn = d0 * nrm[j, 0] + d1 * nrm[j, 1] + d2 * nrm[j, 2]
                    if p0 * p0 + p1 * p1 > texels2 or dn * dn > far2:
                        ok = False
                        break
                if not ok:
                    continue
                label[j] = k
                nt = _claim(j, cell_ptr, cells, claim, touched, nt)
                queue[qt] = j
                qt += 1
        for q in range(nt):
            claim[touched[q]] = -1
        k += 1
    return label, k


_grow = njit(_grow_py)


def _merge_small(label: np.ndarray, k: int, weight: np.ndarray, ei: np.ndarray, ej: np.ndarray,
                 min_samples: float) -> np.ndarray:
    """Pieces label [P] (k of them) whose samples (weight [P] per patch) sum below min_samples join the neighbouring
    piece they share most patch edges (ei, ej) with (a piece at least that large first); isolated ones join the
    largest. Returns labels 0..k'-1, piece 0 the largest."""
    for _ in range(8):
        size = np.bincount(label, weights=weight, minlength=k)
        small = size < min_samples
        small[int(np.argmax(size))] = False
        if not small[label].any():
            break
        a, b = label[ei], label[ej]
        m = (a != b) & small[a]
        if not m.any():
            break
        pair, cnt = np.unique(a[m] * k + b[m], return_counts=True)
        src, dst = pair // k, pair % k
        o = np.lexsort((-cnt, small[dst], src))  # per source: large targets first, then most edges
        src, dst = src[o], dst[o]
        first = np.r_[True, src[1:] != src[:-1]]
        relabel = np.arange(k)
        relabel[src[first]] = dst[first]
        for _ in range(k):  # follow chains of small pieces to where they end
            nxt = relabel[relabel]
            if np.array_equal(nxt, relabel):
                break
            relabel = nxt
        label = relabel[label]
    size = np.bincount(label, weights=weight, minlength=k)
    label = np.where(size[label] < min_samples, int(np.argmax(size)), label)
    used, label = np.unique(label, return_inverse=True)
    size = np.bincount(label, weights=weight)
    rank = np.empty(len(size), np.int64)
    rank[np.argsort(-size, kind="stable")] = np.arange(len(size))
    return rank[label.reshape(-1)]


def solve_columns(A: np.ndarray, B: np.ndarray) -> np.ndarray:
    """X with A X = B for stacked small systems A [P, m, m], B [P, m, k], one right-hand side at a time: numpy's
    solve with several right-hand sides takes OpenBLAS's threaded path for every one of the P systems, and with its
    threads competing for busy cores that is far slower than a column at a time. Equal to
    np.linalg.solve(A, B) up to rounding."""
    return np.stack([np.linalg.solve(A, B[..., j:j + 1])[..., 0] for j in range(B.shape[-1])], axis=-1)


def chart_pieces(y: np.ndarray, t: np.ndarray, spacing: float, voxel: float = 4.0, far: float = 6.0,
                 texels: float = 2.0, min_samples: int = 200) -> tuple[np.ndarray, np.ndarray]:
    """Pieces of one chart's samples: positions y [S, 3] (world, as lookups see them), texel coordinates t [S, 2]
    within the chart, sample spacing (world). Returns (patch centres [P, 3], piece of each patch [P]; 0 the
    largest). Finite for any input: non-finite samples are left out of the patches (they read the nearest patch)."""
    y, t = np.asarray(y, np.float64), np.asarray(t, np.float64)
    if y.ndim != 2 or y.shape[1] != 3 or t.shape != (len(y), 2):
        raise InputError(f"chart pieces: expected samples [S, 3] and texel coordinates [S, 2], got {y.shape}, "
                         f"{t.shape}")
    if not (spacing > 0 and np.isfinite(spacing)):
        raise InputError(f"chart pieces: the sample spacing must be positive and finite, got {spacing!r}")
    ok = np.isfinite(y).all(1) & np.isfinite(t).all(1)
    y, t = y[ok], t[ok]
    if len(y) == 0:
        return np.zeros((0, 3)), np.zeros(0, np.int64)
    vox = np.floor((y - y.min(0)) / (voxel * spacing)).astype(np.int64)
    span = vox.max(0) + 3
    keys, inv = np.unique(((vox[:, 0] + 1) * span[1] + vox[:, 1] + 1) * span[2] + vox[:, 2] + 1, return_inverse=True)
    inv = inv.reshape(-1)
    P = int(inv.max()) + 1
    cnt = np.bincount(inv, minlength=P).astype(np.float64)
    cen = np.stack([np.bincount(inv, y[:, k], P) for k in range(3)], 1) / cnt[:, None]
    if P == 1 or len(y) < 2 * min_samples:
        return cen, np.zeros(P, np.int64)
    tcen = np.stack([np.bincount(inv, t[:, k], P) for k in range(2)], 1) / cnt[:, None]
    # the map's linear part per patch, texels per world unit [P, 3, 2] (least squares; small patches: ~0, lenient)
    dy, dt = y - cen[inv], t - tcen[inv]
    A = np.zeros((P, 3, 3))
    B = np.zeros((P, 3, 2))
    np.add.at(A, inv, dy[:, :, None] * dy[:, None, :])
    np.add.at(B, inv, dy[:, :, None] * dt[:, None, :])
    A += np.eye(3) * (1e-3 * spacing * spacing) * cnt[:, None, None]
    jac = solve_columns(A, B)
    jac = np.where(np.isfinite(jac), jac, 0.0)
    # texel cells of each patch (CSR), cells indexed row * W + col on the chart's own grid (coarser cells where a
    # map spreads its samples over more than MAX_CELLS texels, so the grid stays bounded for any map)
    coarse = max(1.0, math.sqrt(float(np.prod(t.max(0) - t.min(0) + 1.0)) / MAX_CELLS))
    t, tcen, jac, texels = t / coarse, tcen / coarse, jac / coarse, texels / coarse
    ti = np.floor(t - t.min(0)).astype(np.int64)
    W = int(ti[:, 0].max()) + 1
    pc = np.unique(inv * (W * (int(ti[:, 1].max()) + 1)) + ti[:, 1] * W + ti[:, 0])
    n_cells = W * (int(ti[:, 1].max()) + 1)
    pc_patch, pc_cell = pc // n_cells, pc % n_cells
    cell_ptr = np.searchsorted(pc_patch, np.arange(P + 1))
    # adjacency of patches: voxels that touch (faces, edges or corners)
    ea, eb = [], []
    for o in np.array(np.meshgrid([-1, 0, 1], [-1, 0, 1], [-1, 0, 1], indexing="ij")).reshape(3, -1).T:
        if tuple(o) <= (0, 0, 0):
            continue  # each pair once: the 13 offsets after (0, 0, 0) in lexicographic order
        nk = keys + (o[0] * span[1] + o[1]) * span[2] + o[2]
        j = np.searchsorted(keys, nk).clip(0, P - 1)
        hit = keys[j] == nk
        ea.append(np.nonzero(hit)[0])
        eb.append(j[hit])
    a, b = np.concatenate(ea), np.concatenate(eb)
    e = np.unique(np.r_[a * P + b, b * P + a])
    ei, ej = e // P, e % P
    adj_ptr = np.searchsorted(ei, np.arange(P + 1))
    # each patch's normal: least spread of its neighbouring patches' centres (zero with fewer than three)
    off = cen[ej] - cen[ei]
    C = np.zeros((P, 3, 3))
    np.add.at(C, ei, off[:, :, None] * off[:, None, :])
    w, vec = np.linalg.eigh(C)
    nrm = np.where((np.bincount(ei, minlength=P) >= 3)[:, None] & (w[:, 1:2] > 4 * w[:, :1]), vec[:, :, 0], 0.0)
    order = np.argsort(np.linalg.norm(tcen - np.median(tcen, 0), axis=1), kind="stable")  # from the map's middle
    label, k = _grow(order.astype(np.int64), adj_ptr.astype(np.int64), ej.astype(np.int64), cell_ptr.astype(np.int64),
                     pc_cell.astype(np.int64), cen, tcen, jac, np.ascontiguousarray(nrm), int(n_cells),
                     float((far * spacing) ** 2), float(texels ** 2))
    return cen, _merge_small(np.asarray(label), int(k), cnt, ei, ej, float(min_samples))


class ChartPieces:
    """Pieces of the sub-charts (the charts split by side, or the networks' charts) as layout charts.

    centres [P, 3] float32 world patch centres, sub [P] long the sub-chart of each patch, piece [P] long the layout
    chart of each patch; first [n_sub] long: the layout chart of sub-chart s's largest piece (every sub-chart has
    one, patches or not). Layout charts: n = max(first, piece) + 1; sub_of [n] the sub-chart each reads through.
    """

    def __init__(self, centres, sub, piece, first):
        self.centres = np.asarray(centres, np.float32).reshape(-1, 3)
        self.sub = np.asarray(sub, np.int64).reshape(-1)
        self.piece = np.asarray(piece, np.int64).reshape(-1)
        self.first = np.asarray(first, np.int64).reshape(-1)
        P, S = len(self.centres), len(self.first)
        if not (len(self.sub) == len(self.piece) == P and S >= 1):
            raise InputError(f"chart pieces: {P} centres, {len(self.sub)} sub-charts and {len(self.piece)} pieces "
                             f"per patch (one each), {S} sub-charts")
        if not np.isfinite(self.centres).all():
            raise InputError("chart pieces: patch centres must be finite")
        if P and (self.sub.min() < 0 or self.sub.max() >= S or self.piece.min() < 0):
            raise InputError("chart pieces: sub-chart or piece indices out of range")
        n = int(max(self.first.max(), self.piece.max(initial=-1))) + 1
        sub_of = np.full(n, -1, np.int64)
        sub_of[self.first] = np.arange(S)
        sub_of[self.piece] = np.where(sub_of[self.piece] < 0, self.sub, sub_of[self.piece])
        if (sub_of < 0).any() or len(np.unique(self.first)) != S or (P and (sub_of[self.piece] != self.sub).any()):
            raise InputError("chart pieces: every layout chart must be one piece of one sub-chart")
        self.sub_of = torch.from_numpy(sub_of)
        self.n, self.n_sub = n, S
        # sub-charts with more than one piece (the only ones whose points need a patch query)
        self.split = [s for s in range(S) if len(np.unique(self.piece[self.sub == s])) > 1]
        self._trees: dict[int, tuple[cKDTree, np.ndarray]] = {}

    def _tree(self, s: int):
        if s not in self._trees:
            m = self.sub == s
            # leaves of 64: lookups that lie many patches away from the chart's patches (off its part of the
            # surface) visit far fewer nodes than with 16; the nearest centre is the same
            self._trees[s] = (cKDTree(self.centres[m].astype(np.float64), leafsize=64), self.piece[m])
        return self._trees[s]

    def piece_of(self, world: torch.Tensor, sub: torch.Tensor) -> torch.Tensor:
        """Layout chart [M] long of points world [M, 3] in sub-charts sub [M] long: the piece of the nearest patch
        centre of that sub-chart (its largest piece where it has no patches or the point is not finite)."""
        out = torch.from_numpy(self.first).to(sub.device)[sub.clamp(0, self.n_sub - 1)]
        for s in self.split:
            m = sub == s
            if not bool(m.any()):
                continue
            q = world[m].detach().cpu().double().numpy()
            fin = np.isfinite(q).all(1)
            tree, piece = self._tree(s)
            got = np.full(len(q), self.first[s], np.int64)
            if fin.any():
                _, j = tree.query(q[fin], k=1)
                got[fin] = piece[j]
            out[m] = torch.from_numpy(got).to(out.device)
        return out

    def expand(self, probs: torch.Tensor, uv: torch.Tensor, world: torch.Tensor,
               sub_has: torch.Tensor | None = None, has: torch.Tensor | None = None
               ) -> tuple[torch.Tensor, torch.Tensor]:
        """Outputs over the sub-charts (probs [M, S], uv [M, S, 2]) at world points [M, 3] -> over the layout
        charts (probs [M, n], uv [M, n, 2]): each sub-chart's probability on its largest piece, except the point's
        own sub-chart (the most probable one with islands, sub_has [S] bool; None: all), whose probability goes
        to the point's piece when that piece has islands (has [n] bool; None: all)."""
        M = probs.shape[0]
        first = torch.from_numpy(self.first).to(probs.device)
        out = probs.new_zeros(M, self.n)
        out[:, first] = probs
        if M and self.split:
            p = probs if sub_has is None else probs.masked_fill(~sub_has.to(probs.device), float("-inf"))
            own = p.argmax(-1)
            piece = self.piece_of(world, own).to(probs.device)
            if has is not None:
                piece = torch.where(has.to(probs.device)[piece], piece, first[own])
            moved = piece != first[own]
            if bool(moved.any()):
                r = torch.nonzero(moved).squeeze(1)
                out[r, piece[r]] = probs[r, own[r]]
                out[r, first[own[r]]] = 0.0
        return out, uv[:, self.sub_of.to(uv.device)]

    # --- storage ---------------------------------------------------------------------------------------------------
    def to_arrays(self) -> dict[str, np.ndarray]:
        return {"atlas/pieces/centres": self.centres.astype(np.float32),
                "atlas/pieces/sub": self.sub.astype(np.int32), "atlas/pieces/piece": self.piece.astype(np.int32),
                "atlas/pieces/first": self.first.astype(np.int32)}

    @classmethod
    def from_arrays(cls, arrays: dict) -> "ChartPieces":
        return cls(*(np.asarray(arrays[f"atlas/pieces/{k}"]) for k in ("centres", "sub", "piece", "first")))
