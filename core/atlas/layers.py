"""Charts cut into layers: one place of the surface per texel.

A chart map t_c can lay two places of the surface over each other without reversing its orientation (a band whose
chart wraps round, a part folded back inside one side of a split chart, docs/atlas.md "Charts cut into layers"):
the two places then share texels, a texel holds the mean of both colours and its surface point lies between them,
and a lookup from either place reads the other's colour. Splitting by side (core/atlas/sides.py) separates only
places of opposite orientation.

Layers separate the rest. Each layout chart's samples are grown over their 3-D neighbour graph (breadth first, one
seed per connected part); a sample joins the growing layer unless the block of texels it lands in (2 x 2 texels)
already holds a sample of that layer farther than `radius` away in 3-D — another place of the surface. What is left
starts the next layer. Layers of fewer than `min_samples` samples go to the neighbouring layer most of their
neighbours are in (a few shared texels rather than a sliver island). Layer 0 of chart c stays chart c; every further
layer becomes a new layout chart that reads chart c's map (`src`).

Which layer a point belongs to is the layer of the nearest stored sample of its chart (`ChartLayers.assign`):
baking, the texel map and every lookup use the same rule, so a texel's point maps back to its own layer.

Shapes: layer_samples(xyz [S, 3], chart [S], t [S, 2]) -> (layout chart [S], src [N]);
ChartLayers.assign(world [M, 3], chart [M]) -> [M]; ChartLayers.expand(probs [M, n], uv [M, n, 2], final [M]) ->
(probs [M, N], uv [M, N, 2]).
"""
from __future__ import annotations

from collections import deque

import numpy as np
import torch
from scipy.spatial import cKDTree

from core.util.errors import InputError

BLOCK = 2.0  # texels per side of the blocks a layer claims (bilinear lookups and the occupancy fill reach a texel)
MAX_LAYER_POINTS = 200_000  # stored samples of layered charts (a model file keeps them)


def _grow_layers(x: np.ndarray, key: np.ndarray, nbrs: np.ndarray, radius: float) -> np.ndarray:
    """Layers of one chart's samples x [m, 3] with block keys key [m] and neighbour lists nbrs [m, k] (m: none):
    [m] layer index. Each pass grows one layer from one seed per connected part of the neighbour graph."""
    from scipy.sparse import coo_matrix
    from scipy.sparse.csgraph import connected_components

    m = len(x)
    rows = np.repeat(np.arange(m), nbrs.shape[1])
    cols = nbrs.reshape(-1)
    ok = cols < m
    _, part = connected_components(coo_matrix((np.ones(int(ok.sum())), (rows[ok], cols[ok])), shape=(m, m)),
                                   directed=False)
    layer = np.full(m, -1, np.int64)
    r2 = radius * radius
    L = 0
    while (layer < 0).any():
        claims: dict[int, int] = {}
        started = np.zeros(m, bool)  # samples this pass has reached (assigned or refused)
        seeded = set()
        for seed in np.flatnonzero(layer < 0):
            if started[seed] or int(part[seed]) in seeded:
                continue
            seeded.add(int(part[seed]))
            queue = deque([seed])
            started[seed] = True
            while queue:
                s = queue.popleft()
                b = int(key[s])
                owner = claims.get(b)
                if owner is not None:
                    d = x[owner] - x[s]
                    if float(d @ d) > r2:
                        continue  # another place holds this block: s waits for a later layer
                else:
                    claims[b] = s
                layer[s] = L
                for j in nbrs[s]:
                    if j < m and not started[j] and layer[j] < 0:
                        started[j] = True
                        queue.append(j)
        L += 1
        if L > 64:  # a pathological map: the rest stays on the last layer
            layer[layer < 0] = L - 1
    return layer


def _merge_small(layer: np.ndarray, nbrs: np.ndarray, min_samples: int) -> np.ndarray:
    """Layers of fewer than min_samples samples join the layer most of their samples' neighbours are in (the
    largest layer when none); returns layers renumbered by size (0 the largest)."""
    m = len(layer)
    for _ in range(8):
        counts = np.bincount(layer)
        small = np.flatnonzero((counts > 0) & (counts < min_samples))
        if len(small) == 0 or (counts > 0).sum() <= 1:
            break
        moved = False
        for s in small[np.argsort(counts[small])]:
            members = np.flatnonzero(layer == s)
            if len(members) == 0:
                continue
            nb = nbrs[members].reshape(-1)
            nb = nb[nb < m]
            other = layer[nb]
            other = other[other != s]
            target = int(np.bincount(other).argmax()) if len(other) else int(np.bincount(layer).argmax())
            if target != s:
                layer[members] = target
                moved = True
        if not moved:
            break
    _, layer = np.unique(-np.bincount(layer)[layer] * (m + 1) + layer, return_inverse=True)  # by size, then id
    return layer.reshape(-1)


def layer_samples(xyz: np.ndarray, chart: np.ndarray, t: np.ndarray, n: int, spacing: float, radius: float,
                  min_samples: int = 200, k: int = 8) -> tuple[np.ndarray, np.ndarray]:
    """Cut the n layout charts into layers. xyz [S, 3] samples (world), chart [S] their layout chart, t [S, 2] their
    texel coordinates in that chart; spacing: sample spacing (neighbours within 3 spacings are linked); radius: a
    block's samples farther apart than this in 3-D are different places. Returns (final [S] the layout chart of
    every sample after the cut, src [N] the chart each of the N >= n layout charts reads: src[c] = c for c < n)."""
    xyz = np.asarray(xyz, np.float64)
    chart = np.asarray(chart, np.int64)
    if xyz.ndim != 2 or xyz.shape[1] != 3 or len(chart) != len(xyz) or len(t) != len(xyz):
        raise InputError(f"layers: samples [S, 3], charts [S] and texel coordinates [S, 2] must agree, got "
                         f"{xyz.shape}, {chart.shape}, {np.shape(t)}")
    if not (spacing > 0 and radius > 0):
        raise InputError(f"layers: spacing and radius must be positive, got {spacing!r}, {radius!r}")
    final = chart.copy()
    src = list(range(n))
    for c in range(n):
        idx = np.flatnonzero(chart == c)
        if len(idx) < 2 * min_samples:
            continue
        x = xyz[idx]
        cell = np.floor(np.nan_to_num(np.asarray(t[idx], np.float64)) / BLOCK).astype(np.int64)
        cell -= cell.min(0)
        key = cell[:, 1] * (int(cell[:, 0].max()) + 1) + cell[:, 0]
        _, nbrs = cKDTree(x).query(x, k=min(k + 1, len(x)), distance_upper_bound=3.0 * spacing)
        nbrs = np.asarray(nbrs, np.int64).reshape(len(x), -1)[:, 1:]
        layer = _merge_small(_grow_layers(x, key, nbrs, radius), nbrs, min_samples)
        for j in range(1, int(layer.max()) + 1):
            final[idx[layer == j]] = len(src)
            src.append(c)
    return final, np.asarray(src, np.int64)


class ChartLayers:
    """The layer rule of an atlas: src [N] (the chart network output each layout chart reads; src[c] = c for
    c < n), points [P, 3] (world, float32) stored samples of the charts that have layers and final [P] their layout
    chart. A point of layout chart c (c < n) with layers goes to the layout chart of the nearest stored sample of c.
    """

    def __init__(self, src, points, final):
        self.src = np.asarray(src, np.int64).reshape(-1)
        self.points = np.asarray(points, np.float32).reshape(-1, 3)
        self.final = np.asarray(final, np.int64).reshape(-1)
        N = len(self.src)
        n = int(self.src.max()) + 1 if N else 0
        if N == 0 or not (self.src[:n] == np.arange(n)).all() or (self.src[n:] >= n).any() or (self.src < 0).any():
            raise InputError(f"chart layers: src must start 0..n-1 and map the other charts into it, got "
                             f"{self.src.tolist()[:16]}")
        if len(self.final) != len(self.points) or (len(self.final) and (
                self.final.min() < 0 or self.final.max() >= N)) or not np.isfinite(self.points).all():
            raise InputError("chart layers: stored points must be finite, one layout chart in [0, N) each")
        self.n = n
        self._trees: dict[int, tuple[cKDTree, np.ndarray]] = {}
        base = self.src[self.final] if len(self.final) else self.final
        for c in np.unique(self.src[n:]):
            m = base == c
            if m.any():
                self._trees[int(c)] = (cKDTree(self.points[m]), self.final[m])

    @property
    def N(self) -> int:
        return len(self.src)

    @classmethod
    def from_samples(cls, xyz: np.ndarray, final: np.ndarray, src: np.ndarray, seed: int = 0) -> "ChartLayers":
        """Keep (at most MAX_LAYER_POINTS, a fixed random subset) the samples of the charts that have layers."""
        src = np.asarray(src, np.int64)
        n = int(src.max()) + 1
        layered = np.isin(src[final], src[n:])
        idx = np.flatnonzero(layered)
        if len(idx) > MAX_LAYER_POINTS:
            idx = np.sort(np.random.default_rng(seed).choice(idx, MAX_LAYER_POINTS, replace=False))
        return cls(src, np.asarray(xyz, np.float32)[idx], np.asarray(final)[idx])

    def assign(self, world: torch.Tensor, chart: torch.Tensor) -> torch.Tensor:
        """world [M, 3] points, chart [M] their layout chart before the cut (< n) -> [M] after it."""
        out = chart.clone()
        if not self._trees:
            return out
        ch = chart.cpu().numpy()
        w = None
        for c, (tree, fin) in self._trees.items():
            m = ch == c
            if not m.any():
                continue
            if w is None:
                w = torch.nan_to_num(world.detach().float(), nan=0.0, posinf=0.0, neginf=0.0).cpu().numpy()
            _, j = tree.query(w[m], k=1)
            out[torch.from_numpy(m).to(out.device)] = torch.from_numpy(fin[j]).to(out.device)
        return out

    def expand(self, probs: torch.Tensor, uv: torch.Tensor, final: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """Outputs over the n charts -> over the N layout charts: every chart reads its source's coordinates; a
        point's probability of its own chart moves to its layer's chart (final [M])."""
        src = torch.from_numpy(self.src).to(uv.device)
        uv2 = uv.index_select(1, src)
        p2 = torch.zeros(probs.shape[0], self.N, dtype=probs.dtype, device=probs.device)
        p2[:, :self.n] = probs
        moved = final >= self.n
        if bool(moved.any()):
            rows = torch.nonzero(moved).squeeze(1)
            base = src[final[rows]]
            p2[rows, final[rows]] = probs[rows, base]
            p2[rows, base] = 0.0
        return p2, uv2

    # --- storage ---------------------------------------------------------------------------------------------------
    def to_arrays(self) -> dict[str, np.ndarray]:
        return {"atlas/layers/src": self.src.astype(np.int32), "atlas/layers/points": self.points.astype(np.float32),
                "atlas/layers/chart": self.final.astype(np.int32)}

    @classmethod
    def from_arrays(cls, arrays: dict) -> "ChartLayers":
        return cls(np.asarray(arrays["atlas/layers/src"]), np.asarray(arrays["atlas/layers/points"]),
                   np.asarray(arrays["atlas/layers/chart"]))
