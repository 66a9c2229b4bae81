"""The "kdtree" backend (uncapped searches, CPU tensors): a scipy k-d tree over keys x_j (pixel coords, or unit
directions from the shared origin) and an exact re-rank. Every metric here is w_j · φ(‖q − x_j‖) with a per-point
weight w_j > 0 (1, depth / focal, or |p − o|) and φ increasing, so once K candidates give an upper bound r on the
K-th distance, every closer point has key distance < φ⁻¹(r / w_min): a ball query of that radius is complete. The
few points with the smallest weights (a stray point next to the camera would blow the ball up) are checked by
brute force instead."""
from __future__ import annotations

import math

import numpy as np

_NEAR_POINTS = 32  # smallest-weight points handled by brute force in the weighted tree search
_LAYERS = 4  # weight layers of the weighted tree search (see WeightedTree)


class WeightedTree:
    """K smallest w_j · φ(‖q − x_j‖) over keys x [M, D] (float64) with weights w [M] > 0 (or None = all 1).

    `phi` maps key distances -> metric factor (inf where a point can never be a neighbour; None = identity) and
    `phi_inv` maps a bound on the factor to a bound on the key distance. Exact, in three steps:
    1. the `_NEAR_POINTS` smallest weights are checked by brute force, the rest is split into `_LAYERS` layers by
       weight, one tree each; the K nearest keys of every layer give an upper bound r on each ray's K-th value;
    2. in layer l every point better than r has key distance < φ⁻¹(r / min w_l); a ball count tells whether
       step 1 already saw all of them;
    3. where it did not, that layer is queried for exactly that many keys and merged.
    Layers keep the balls small: a pixel far from the object gets a wide ball only in the front layer.
    """

    def __init__(self, keys: np.ndarray, weight: np.ndarray | None, phi=None, phi_inv=None):
        from scipy.spatial import cKDTree  # heavy import kept local

        self.m = keys.shape[0]
        self.keys, self.weight, self.phi, self.phi_inv = keys, weight, phi, phi_inv
        ids = np.arange(self.m)
        near = np.empty(0, dtype=np.int64)
        self.layers: list[tuple[np.ndarray, float, object]] = []  # (point ids, min weight, tree)
        self.layer_of = np.full(self.m, -1, dtype=np.int64)
        if weight is not None and self.m > 2 * _NEAR_POINTS:
            order = np.argsort(weight, kind="stable")
            near, ids = order[:_NEAR_POINTS], order[_NEAR_POINTS:]
            for l, chunk in enumerate(np.array_split(ids, min(_LAYERS, ids.size))):
                self.layers.append((chunk, float(weight[chunk[0]]), cKDTree(keys[chunk], balanced_tree=False)))
                self.layer_of[chunk] = l
        elif weight is not None:
            near, ids = ids, ids[:0]  # tiny sets: brute force is all there is
        self.near, self.tree_ids = near, ids
        self.tree = cKDTree(keys[ids], balanced_tree=False) if ids.size and not self.layers else None

    def _exact(self, key_dist: np.ndarray, cand: np.ndarray) -> np.ndarray:
        """key_dist/cand [r, c] (cand indexes self.keys, -1 = none) -> metric [r, c] float64, inf = none."""
        with np.errstate(invalid="ignore", over="ignore"):
            f = key_dist if self.phi is None else self.phi(key_dist)
            if self.weight is not None:
                f = f * self.weight[np.maximum(cand, 0)]
        return np.where((cand >= 0) & ~np.isnan(f), f, np.inf)

    def _tree_query(self, tree, ids: np.ndarray, q: np.ndarray, k: int) -> tuple[np.ndarray, np.ndarray]:
        """k nearest keys of one tree: (key dist [r, k], cand [r, k] indexing self.keys, -1 = none)."""
        kd, ki = tree.query(q, k=k, workers=-1)
        kd, ki = kd.reshape(q.shape[0], k), ki.reshape(q.shape[0], k)
        cand = np.where(ki < ids.size, ids[np.minimum(ki, ids.size - 1)], -1)
        return kd, cand

    def query(self, q: np.ndarray, k: int) -> tuple[np.ndarray, np.ndarray]:
        """q [R, D] float64 -> (idx [R, k'] into keys, -1 = none; dist [R, k'] float64 ascending), k' = min(k, M)."""
        r = q.shape[0]
        kk = min(k, self.m)
        if kk == 0 or r == 0:
            return np.full((r, kk), -1, dtype=np.int64), np.full((r, kk), np.inf)
        parts = []  # (key dist, cand) blocks of step 1
        if self.layers:
            for ids, _, tree in self.layers:
                parts.append(self._tree_query(tree, ids, q, min(kk, ids.size)))
        elif self.tree is not None:
            parts.append(self._tree_query(self.tree, self.tree_ids, q, min(kk, self.tree_ids.size)))
        cand_k = np.concatenate([p[0] for p in parts], axis=1) if parts else np.empty((r, 0))
        cand_i = np.concatenate([p[1] for p in parts], axis=1) if parts else np.full((r, 0), -1, dtype=np.int64)
        cand_d = self._exact(cand_k, cand_i)
        if self.near.size:
            nk = np.linalg.norm(q[:, None, :] - self.keys[self.near][None, :, :], axis=-1)  # [R, m]
            near_i = np.broadcast_to(self.near, nk.shape)
            cand_i = np.concatenate([cand_i, near_i], axis=1)
            cand_k = np.concatenate([cand_k, nk], axis=1)
            cand_d = np.concatenate([cand_d, self._exact(nk, near_i)], axis=1)
        extras = []  # (rows, exact [rows, n], cand [rows, n]) of step 3, merged after the base top-k
        if self.layers:
            r_k = np.partition(cand_d, kk - 1, axis=1)[:, kk - 1]  # upper bound on the K-th best
            layer = np.where(cand_i >= 0, self.layer_of[np.maximum(cand_i, 0)], -1)
            for l, (ids, w_min, tree) in enumerate(self.layers):  # steps 2 and 3
                with np.errstate(divide="ignore", invalid="ignore", over="ignore"):
                    b = r_k / w_min if self.phi_inv is None else self.phi_inv(r_k / w_min)
                b = np.minimum(b * (1 + 1e-9) + 1e-12, 1e300)  # margin for rounding; inf -> huge
                seen = ((layer == l) & (cand_k <= b[:, None])).sum(axis=1)
                count = tree.query_ball_point(q, b, return_length=True, workers=-1)
                rows = np.nonzero(count > seen)[0]
                if rows.size == 0:
                    continue
                need = np.minimum(2 ** np.ceil(np.log2(count[rows])).astype(np.int64), ids.size)
                for n_q in np.unique(need):  # a few power-of-two buckets, not a loop over rays
                    sub = rows[need == n_q]
                    ek, ei = self._tree_query(tree, ids, q[sub], int(n_q))
                    extras.append((sub, self._exact(ek, ei), ei))
                drop = layer[rows] == l  # the layer query returns these again: avoid duplicates
                cand_d[rows] = np.where(drop, np.inf, cand_d[rows])
                cand_i[rows] = np.where(drop, -1, cand_i[rows])
        best_d, best_i = _smallest(cand_d, cand_i, kk)
        for rows, ed, ei in extras:
            best_d[rows], best_i[rows] = _smallest(np.concatenate([best_d[rows], ed], 1),
                                                   np.concatenate([best_i[rows], ei], 1), kk)
        srt = np.argsort(best_d, axis=1, kind="stable")
        best_d, best_i = np.take_along_axis(best_d, srt, 1), np.take_along_axis(best_i, srt, 1)
        return np.where(np.isfinite(best_d), best_i, -1), best_d


def _smallest(d: np.ndarray, i: np.ndarray, k: int) -> tuple[np.ndarray, np.ndarray]:
    """The k smallest entries per row (unsorted): d, i [r, c] -> [r, min(k, c)]."""
    if d.shape[1] <= k:
        return d.copy(), i.copy()
    part = np.argpartition(d, k - 1, axis=1)[:, :k]
    return np.take_along_axis(d, part, 1), np.take_along_axis(i, part, 1)


def chord_to_sin(c: np.ndarray) -> np.ndarray:
    """Chord length between unit vectors -> sin of their angle; inf at or beyond 90° (point not in front)."""
    with np.errstate(invalid="ignore"):
        s = c * np.sqrt(np.clip(1.0 - 0.25 * c * c, 0.0, None))
    return np.where(c < math.sqrt(2.0), s, np.inf)


def sin_to_chord(s: np.ndarray) -> np.ndarray:
    """Bound on sin(angle) -> bound on the chord, capped at the whole front hemisphere (chord √2)."""
    s = np.asarray(s, dtype=np.float64)
    with np.errstate(invalid="ignore"):
        c = 2.0 * np.sin(0.5 * np.arcsin(np.clip(s, 0.0, 1.0)))
    return np.where(s < 1.0, c, math.sqrt(2.0))
