"""Local deformation gradients F_j of a deformed point cloud (beyond the paper: used by F-aware rendering and the
"deform-gradient" correspondence).

For every deformed point j with canonical position c_j and deformed position d_j, F_j [3, 3] is the weighted
least-squares linear map taking its canonical neighbours' offsets to their deformed offsets:

    F_j = argmin_F  Σ_l w_jl |F (c_l − c_j) − (d_l − d_j)|²  =  B_j A_j⁻¹,
    A_j = Σ w (c_l − c_j)(c_l − c_j)ᵀ,   B_j = Σ w (d_l − d_j)(c_l − c_j)ᵀ.

The canonical k-NN lists and their Gaussian weights depend on the canonical points only: `DeformationField`
builds them once per model (`field_for` caches it), and each frame costs one vectorised O(N·k) fit.

Robustness (tests/stability/test_stability_deformation.py):
- thin sheets / lines: where A_j is (nearly) rank deficient the fit is regularised towards a prior P_j,
  F = (B + μ P)(A + μ I)⁻¹, with μ > 0 only where the smallest eigenvalue of A is below `sheet_ratio` × the
  largest (so well-spread neighbourhoods stay exact for affine deformations). For a sheet, P maps the canonical
  normal n to unit(F t₁ × F t₂) (the deformed tangent images' normal; thickness kept, and an in-plane mirror
  becomes the flip it is for a sheet); for a line the rotation that best aligns the neighbours (Kabsch) fills
  the two missing directions; no spread at all gives F = I.
- squash to ~0, huge stretch, folds, inverted (mirrored) neighbourhoods: F is bounded by clamping its singular
  values' magnitudes to [1 / max_stretch, max_stretch] (the sign of det F is kept, so a true mirror stays one).
- missing data: neighbours with a non-finite deformed position, removed neighbours and points whose own
  position is non-finite get weight 0 (F = I where nothing is left). With ids (points duplicated / removed),
  each canonical neighbour is taken from the copy nearest the deformed point (at most `max_copies` copies), and
  one whose offset grew > OUTLIER_FACTOR times more than the neighbourhood's median (a neighbour that exists
  only in another, moved copy) is dropped.
Polar parts: F = R S with R a rotation (det +1) and S symmetric (`polar`).
"""
from __future__ import annotations

import math
import weakref
from dataclasses import dataclass

import numpy as np
import torch

from core.config import opt
from core.points.neighbors.knn import point_knn
from core.util.errors import InputError
from core.util.jit import njit

try:  # optional: torch does the same work without it
    import numba
except ImportError:  # pragma: no cover - exercised only where numba is missing
    numba = None


MAX_STRETCH = 20.0  # default bound of F's singular values (DeformationConfig.max_stretch)


@dataclass
class DeformationConfig:
    """Local deformation gradients of the deformed points (F-aware rendering and correspondence)."""

    k: int = opt(12, "canonical neighbours per point in the local fit of F")
    sheet_ratio: float = opt(0.05, "a neighbourhood whose smallest/largest spread (eigenvalue) ratio is below "
                                   "this counts as (partly) flat: its missing direction comes from the tangents")
    max_stretch: float = opt(MAX_STRETCH, "bound of F's singular values: |σ| is clamped to "
                                          "[1/max_stretch, max_stretch]")
    max_copies: int = opt(8, "with ids: copies of one canonical point considered as a neighbour (nearest wins)")


class DeformationField:
    """Canonical neighbourhoods of a model's points and per-frame deformation gradients.

    canonical [N, 3]: the model's canonical points (non-finite ones are never anyone's neighbour).
    """

    def __init__(self, canonical: torch.Tensor, cfg: DeformationConfig | None = None):
        self.cfg = cfg or DeformationConfig()
        if int(self.cfg.k) < 1:
            raise InputError(f"deformation k: neighbours per point must be at least 1, got {self.cfg.k}")
        if not (self.cfg.max_stretch >= 1.0 and math.isfinite(self.cfg.max_stretch)):
            raise InputError(f"deformation max_stretch must be a finite number >= 1, got {self.cfg.max_stretch}")
        can = canonical.detach().to(torch.float32)
        self.canonical = can
        self.device = can.device
        n = can.shape[0]
        finite = torch.isfinite(can).all(1)
        ids = torch.nonzero(finite).squeeze(1)
        sub_idx, sub_dist = point_knn(can[ids], int(self.cfg.k))
        self.nbr = torch.full((n, int(self.cfg.k)), -1, dtype=torch.long, device=self.device)  # [N, k]
        self.nbr[ids] = torch.where(sub_idx >= 0, ids[sub_idx.clamp_min(0)], -1)
        dist = torch.full((n, int(self.cfg.k)), math.inf, device=self.device)
        dist[ids] = sub_dist
        # Gaussian weights, bandwidth = distance to the farthest neighbour (weight e^-1 there): scale-free.
        h = torch.where(torch.isfinite(dist), dist, torch.zeros_like(dist)).amax(1, keepdim=True)
        w = torch.exp(-(dist / h.clamp_min(1e-30)) ** 2)
        self.weights = torch.where(torch.isfinite(dist) & (self.nbr >= 0), w, torch.zeros_like(w))  # [N, k]
        # Length scale per point: zero-spread tests are relative to it.
        self.scale = h.squeeze(1)                                                                 # [N]
        # The canonical side of the fit with every neighbour present: a frame reuses it for each point whose
        # neighbours all came through (the common case) and recomputes it for the others only.
        dc = torch.where(self.nbr[..., None] >= 0, can[self.nbr.clamp_min(0)] - can[:, None, :], 0.0)
        dc = torch.nan_to_num(dc.double() / self.scale.double().clamp_min(1e-30)[:, None, None], 0.0, 0.0, 0.0)
        self._terms = self._canonical_terms(self.weights.double(), dc)
        self._dc = torch.nan_to_num(torch.where(self.nbr[..., None] >= 0, can[self.nbr.clamp_min(0)] - can[:, None, :],
                                                0.0), 0.0, 0.0, 0.0)  # [N, k, 3] canonical offsets (float32)

    @property
    def num_points(self) -> int:
        return self.canonical.shape[0]

    def _gather_deformed(self, points: torch.Tensor, ids: torch.Tensor | None, with_rows: bool = False):
        """Neighbour offsets of each deformed point: (dc [M, k, 3] canonical, dd [M, k, 3] deformed, w [M, k],
        cid [M] canonical index, own_ok [M] finite own position); with_rows: also the row of `points` each
        neighbour was taken from [M, k] (meaningful where w > 0)."""
        n, k = self.num_points, self.nbr.shape[1]
        m = points.shape[0]
        own_ok = torch.isfinite(points).all(1)
        pts = torch.where(own_ok[:, None], points, torch.zeros_like(points))
        if ids is None:
            if m != n:
                raise InputError(f"deformation: {m} points for a model of {n} points and no ids")
            cid = torch.arange(n, device=points.device)
            nbr = self.nbr                                                       # [M, k] canonical = deformed
            present = nbr >= 0
            ok = present & own_ok[:, None] & own_ok[nbr.clamp_min(0)]
            p_nb = pts[nbr.clamp_min(0)]                                         # [M, k, 3]
        else:
            cid = ids.to(points.device, torch.long)
            if cid.shape != (m,):
                raise InputError(f"deformation: ids must have shape [{m}], got {tuple(cid.shape)}")
            if m and (int(cid.min()) < 0 or int(cid.max()) >= n):
                raise InputError(f"deformation: ids must lie in [0, {n - 1}]")
            # copies [N, C]: the deformed rows of each canonical point (finite positions only), -1 padded
            rows = torch.nonzero(own_ok).squeeze(1)
            order = torch.argsort(cid[rows], stable=True)
            rows = rows[order]
            owner = cid[rows]
            count = torch.bincount(owner, minlength=n)
            c = max(1, min(int(self.cfg.max_copies), int(count.max()) if count.numel() else 1))
            start = torch.cumsum(count, 0) - count
            slot = torch.arange(rows.numel(), device=points.device) - start[owner]
            copies = torch.full((n, c), -1, dtype=torch.long, device=points.device)
            keep = slot < c
            copies[owner[keep], slot[keep]] = rows[keep]
            nbr = self.nbr[cid]                                                  # [M, k] canonical ids
            cand = torch.where((nbr >= 0)[..., None], copies[nbr.clamp_min(0)], -1)  # [M, k, C]
            cp = pts[cand.clamp_min(0)]                                          # [M, k, C, 3]
            dist = (cp - pts[:, None, None, :]).pow(2).sum(-1).masked_fill(cand < 0, math.inf)
            best = dist.argmin(-1, keepdim=True)                                  # [M, k, 1]
            pick = cand.gather(-1, best).squeeze(-1)                             # [M, k]
            ok = (pick >= 0) & own_ok[:, None]
            p_nb = pts[pick.clamp_min(0)]
        dc = self._dc if ids is None else self._dc[cid]
        dd = p_nb - pts[:, None, :]
        ok = ok & torch.isfinite(dd).all(-1) & (dd.abs() < 1e18).all(-1)
        if ids is not None:
            # a neighbour found only in another copy (a duplicated part moved away) is an outlier: its offset
            # grew far more than the neighbourhood's typical one
            ratio = dd.norm(dim=-1) / dc.norm(dim=-1).clamp_min(1e-30)
            med = torch.where(ok, ratio, torch.full_like(ratio, float("nan"))).nanmedian(1, keepdim=True).values
            ok = ok & ~(ratio > OUTLIER_FACTOR * med.nan_to_num(math.inf))
        w = self.weights[cid] * ok
        dd = torch.where(ok[..., None], dd, torch.zeros_like(dd))
        if with_rows:
            return dc, dd, w, cid, own_ok, (nbr if ids is None else pick).clamp_min(0)
        return dc, dd, w, cid, own_ok

    def _canonical_terms(self, w: torch.Tensor, dc: torch.Tensor) -> dict:
        """What the fit needs of the canonical side, per point: w [M, k], dc [M, k, 3] (float64, in units of the
        point's scale) -> dict of [M, ...] tensors (the weighted offsets, the eigenbasis of A, the regularised
        inverse (A + μ I)⁻¹, the tangent-plane pseudo-inverse, μ and the flags)."""
        a = _moments(w, dc, dc)
        lam, e = torch.linalg.eigh(a)                                           # ascending
        lam = lam.clamp_min(0.0)
        lmax = lam[:, 2]
        lmax_s = lmax.clamp_min(1e-30)
        ratio = self.cfg.sheet_ratio
        e2, e3 = e[:, :, 1], e[:, :, 2]                                         # middle, largest spread
        e1 = torch.linalg.cross(e3, e2)  # smallest spread, oriented so that F t3 × F t2 is its image
        line = lam[:, 1] < 1e-6 * lmax_s
        inv2 = torch.where(line, torch.zeros_like(lmax), 1.0 / lam[:, 1].clamp_min(1e-30))
        # the fit restricted to the two best-spread directions: g2 = B p2
        p2 = e3[..., None] @ (e3[:, None, :] / lmax_s[:, None, None]) + e2[..., None] @ (e2[:, None, :] *
                                                                                         inv2[:, None, None])
        # μ > 0 only for (partly) flat neighbourhoods: μ = ratio · λmax · (1 − λmin/(ratio λmax))²
        h = (1.0 - lam[:, 0] / (ratio * lmax_s)).clamp(0.0, 1.0)
        mu = ratio * lmax * h * h
        inv = e @ torch.diag_embed(1.0 / (lam + mu[:, None]).clamp_min(1e-30)) @ e.transpose(1, 2)
        wdc = w[..., None] * dc / w.sum(1).clamp_min(1e-30)[:, None, None]     # B = Σ_l dd_l wdc_lᵀ
        spread = torch.where(lmax < 1e-12, torch.zeros_like(lmax), lam[:, 0] / lmax_s)  # λmin/λmax in [0, 1]
        return {"wdc": wdc, "e1": e1, "e2": e2, "e3": e3, "p2": p2, "inv": inv, "mu": mu, "line": line,
                "empty": lmax < 1e-12, "spread": spread}

    def normals(self, ids: torch.Tensor | None = None) -> torch.Tensor:
        """Unit direction of least canonical spread of each point's neighbourhood (a surface's normal) [M, 3]
        float64; ids [M] as in `gradients` (None: every canonical point)."""
        n = self._terms["e1"]
        return n if ids is None else n[ids.to(n.device, torch.long)]

    def spread_ratios(self, ids: torch.Tensor | None = None) -> torch.Tensor:
        """How thick each point's canonical neighbourhood is [M] float64 in [0, 1]: its smallest / largest spread
        (eigenvalues of the weighted offsets' second moments); near 0 on a thin sheet or a line, where `normals` is
        the surface's normal, up to 1 in a cloud spread evenly in 3-D, where the least-spread direction is noise.
        0 where a point has no neighbour. ids [M] as in `gradients` (None: every canonical point)."""
        r = self._terms["spread"]
        return r if ids is None else r[ids.to(r.device, torch.long)]

    @property
    def median_spread(self) -> float:
        """The median of `spread_ratios` over the points that have neighbours (0 when none has): how thick the
        model's point cloud is at the scale of the fit (a thin sheet's ≈ 0.05–0.1, a solid's shell ≈ 0.2–0.35)."""
        if getattr(self, "_median_spread", None) is None:
            r = self._terms["spread"][~self._terms["empty"]]
            self._median_spread = float(r.median()) if r.numel() else 0.0
        return self._median_spread

    @torch.no_grad()
    def gradients(self, points: torch.Tensor, ids: torch.Tensor | None = None) -> torch.Tensor:
        """Deformation gradients F [M, 3, 3] (float32, finite, singular values in [1/max_stretch, max_stretch]).

        points [M, 3] deformed positions (non-finite = absent); ids [M] canonical index of each (None: M == N,
        row j is canonical point j)."""
        pts = points.detach().to(self.device, torch.float32)
        if pts.dim() != 2 or pts.shape[1] != 3:
            raise InputError(f"deformation: points must have shape [M, 3], got {tuple(pts.shape)}")
        if pts.shape[0] == 0:
            return torch.zeros(0, 3, 3, device=self.device)
        return self._fit(pts, *self._gather_deformed(pts, ids), ids)

    @torch.no_grad()
    def gradients_and_fill(self, points: torch.Tensor, ids: torch.Tensor | None = None, ratio: float = 1.5,
                           max_per_pair: int = 8, budget: float = 1.0, with_partner: bool = False,
                           with_gap: bool = False, gap_pairs: str = "all", tear: float | None = None):
        """`gradients` and `fill` of the same points, sharing their neighbour gathering: (F [M, 3, 3], (new [P, 3],
        canonical [P, 3], source [P])); with_partner: the fill's tuple also holds partner [P] and fraction [P]
        (see `fill`); with_gap: it also ends with gap [M] and sparse [M] (see `fill`, and gap_pairs); tear: see
        `fill`."""
        pts = points.detach().to(self.device, torch.float32)
        if pts.dim() != 2 or pts.shape[1] != 3:
            raise InputError(f"deformation: points must have shape [M, 3], got {tuple(pts.shape)}")
        if pts.shape[0] == 0:
            return torch.zeros(0, 3, 3, device=self.device), self.fill(pts, ids, ratio, max_per_pair, budget,
                                                                       with_partner, with_gap, gap_pairs, tear)
        gathered = self._gather_deformed(pts, ids, with_rows=True)
        return (self._fit(pts, *gathered[:5], ids),
                self._fill(pts, gathered, ratio, max_per_pair, budget, with_partner, with_gap,
                           canonical_rows=ids is None, gap_pairs=gap_pairs, tear=tear))

    def _fit(self, pts, dc, dd, w, cid, own_ok, ids):
        """The fit of `gradients` from gathered neighbour offsets (see _gather_deformed)."""
        # Work in float64 and in units of each point's neighbourhood size: scale-free and well conditioned.
        s = self.scale[cid].double().clamp_min(1e-30)[:, None, None]
        # a deformation sent to 1e18 must not overflow the squares: bound offsets (F is clamped anyway)
        dd = (dd.double() / s).clamp(-1e6, 1e6)
        # canonical terms: cached for points whose neighbours all came through, recomputed for the others
        whole = self._terms
        if ids is None:
            t = dict(whole)
        else:
            t = {k: v[cid] for k, v in whole.items()}
        dirty = (w != self.weights[cid]).any(1)
        if bool(dirty.any()):
            t = {k: v.clone() for k, v in t.items()}
            sub = self._canonical_terms(w[dirty].double(), dc[dirty].double() / s[dirty])
            for k, v in sub.items():
                t[k][dirty] = v
        b = torch.einsum("mki,mkj->mij", dd, t["wdc"])                          # [M, 3, 3]
        f = b @ t["inv"]
        flat = t["mu"] > 0
        n_flat = int(flat.sum())
        if n_flat:  # (partly) flat neighbourhoods: regularise towards the prior P
            every = n_flat > flat.shape[0] // 4  # many: work on every row (μ = 0 cancels P) instead of gathering
            sel = slice(None) if every else flat
            bf, e1, e2 = b[sel], t["e1"][sel], t["e2"][sel]
            line = t["line"][sel]
            g2 = bf @ t["p2"][sel]
            ft1, ft2 = (g2 @ t["e3"][sel][..., None]).squeeze(-1), (g2 @ e2[..., None]).squeeze(-1)
            cross = torch.linalg.cross(ft1, ft2)
            cn = cross.norm(dim=-1, keepdim=True)
            sheet_ok = (cn.squeeze(-1) > 1e-9 * (ft1.norm(dim=-1) * ft2.norm(dim=-1)).clamp_min(1e-30)) & ~line
            # Kabsch rotation (proper) for lines and degenerate sheets (only where it is used)
            rot = torch.eye(3, dtype=b.dtype, device=b.device).repeat(bf.shape[0], 1, 1)
            need = (line | ~sheet_ok) & flat[sel]
            if bool(need.any()):
                u, _, vh = torch.linalg.svd(bf[need] + 1e-12 * torch.eye(3, dtype=b.dtype, device=b.device))
                dfix = torch.ones(u.shape[0], 3, dtype=b.dtype, device=b.device)
                dfix[:, 2] = torch.where(torch.linalg.det(u @ vh) < 0, -1.0, 1.0)
                rot[need] = u @ (dfix[..., None] * vh)
            normal_img = torch.where(sheet_ok[:, None], cross / cn.clamp_min(1e-30),
                                     (rot @ e1[..., None]).squeeze(-1))
            prior = g2 + normal_img[..., None] @ e1[:, None, :]
            prior = torch.where(line[:, None, None], g2 + rot @ (e1[..., None] @ e1[:, None, :] +
                                                                 e2[..., None] @ e2[:, None, :]), prior)
            mu = t["mu"][sel][:, None, None]
            if every:
                f = (bf + mu * prior) @ t["inv"]
            else:
                f[flat] = (bf + mu * prior) @ t["inv"][flat]
        eye = torch.eye(3, dtype=f.dtype, device=f.device).expand_as(f)
        f = torch.where((t["empty"] | ~own_ok)[:, None, None] | ~torch.isfinite(f).all(-1).all(-1)[:, None, None],
                        eye, f)
        return bound(f, self.cfg.max_stretch).float()


    @torch.no_grad()
    def fill(self, points: torch.Tensor, ids: torch.Tensor | None = None, ratio: float = 1.5,
             max_per_pair: int = 8, budget: float = 1.0, with_partner: bool = False,
             with_gap: bool = False, gap_pairs: str = "all", tear: float | None = None) -> tuple:
        """Extra points where the deformation pulled canonical neighbours apart (a stretched surface: a joint's
        blend band, a scaled part), so the deformed cloud keeps about its canonical density.

        Every canonical neighbour pair (j, l) (each pair once) whose deformed distance grew by g = |d_l − d_j| /
        |c_l − c_j| > ratio gets n = ceil(g / ratio) − 1 points (at most max_per_pair) evenly spaced on the
        segment between them: deformed d_j + t (d_l − d_j), canonical c_j + t (c_l − c_j), t = i / (n + 1). Pairs
        that grew beyond the tear growth (`tear`, None = max_stretch; at most max_stretch: parts moved apart) are
        left open. At most budget × M points are added: past that the ratio is raised until they fit.

        points [M, 3] deformed (non-finite = absent), ids [M] as in `gradients`. Returns (new [P, 3] deformed
        positions, canonical [P, 3] their canonical positions, source [P] int64 the row of `points` each takes
        its features and F from: the nearer end of its segment). P = 0 where nothing stretched. with_partner: also
        partner [P] int64, the row of the segment's other end, and fraction [P] float32 in (0, 0.5], how far along
        the segment from the source towards the partner the point lies (to blend the two ends' features).
        with_gap: the tuple ends with gap [M] and sparse [M], float32 >= 1, per given point: gap = the largest
        growth left between consecutive points on any of its pairs (g / (n + 1) on a filled pair, g on a pair left as
        it is, at most `ratio`; 1 for none grown; pairs beyond the tear growth are tears and count as closed); sparse =
        that growth only where it exceeds `ratio` (the budget or max_per_pair kept a stretched pair sparser than the
        ratio), else 1; gap_pairs "budget": for sparse, only pairs the budget kept sparse count (those that got
        max_per_pair points, grown past max_per_pair + 1 times the ratio — a joint's near-tears — count as
        closed)."""
        pts = points.detach().to(self.device, torch.float32)
        if pts.dim() != 2 or pts.shape[1] != 3:
            raise InputError(f"deformation: points must have shape [M, 3], got {tuple(pts.shape)}")
        gathered = self._gather_deformed(pts, ids, with_rows=True) if pts.shape[0] else None
        return self._fill(pts, gathered, ratio, max_per_pair, budget, with_partner, with_gap,
                          canonical_rows=ids is None, gap_pairs=gap_pairs, tear=tear)

    @property
    def reverse_slots(self) -> torch.Tensor:
        """[N, k] int64: for each canonical pair (j, l = nbr[j, s]) the slot of j in l's neighbour list, -1 where l
        does not list j (or the slot is empty). Built on first use, once per model."""
        if getattr(self, "_reverse", None) is None:
            nb = self.nbr
            rev = torch.full_like(nb, -1)
            for s in range(0, nb.shape[0], 4096):  # [chunk, k, k] matches, bounded memory
                part = nb[s:s + 4096]
                hit = (nb[part.clamp_min(0)] == torch.arange(s, s + part.shape[0], device=nb.device)[:, None, None])
                hit &= (part >= 0)[..., None]
                first = hit.int().argmax(-1)
                rev[s:s + part.shape[0]] = torch.where(hit.any(-1), first, -1)
            self._reverse = rev
        return self._reverse

    def _fill(self, pts, gathered, ratio, max_per_pair, budget, with_partner=False, with_gap=False,
              canonical_rows=False, gap_pairs="all", tear=None):
        """The work of `fill` from gathered neighbour offsets (_gather_deformed with rows; None: no points).
        canonical_rows: the points are the canonical ones in order (no ids), so the rows gathered are the cached
        neighbour lists and whether a pair's other end lists it back is looked up (`reverse_slots`)."""
        gap = torch.ones(pts.shape[0], dtype=torch.float32, device=self.device)
        sparse = gap
        empty = (pts.new_zeros(0, 3), pts.new_zeros(0, 3), torch.zeros(0, dtype=torch.long, device=self.device))
        if with_partner:
            empty = empty + (torch.zeros(0, dtype=torch.long, device=self.device), pts.new_zeros(0))
        if with_gap:
            empty = empty + (gap, sparse)
        if not (ratio > 1.0 and math.isfinite(ratio)):
            raise InputError(f"fill ratio must be a finite number > 1, got {ratio}")
        if not (budget >= 0 and math.isfinite(budget)):
            raise InputError(f"fill budget must be a finite number >= 0, got {budget}")
        torn = self.cfg.max_stretch if tear is None else min(float(tear), self.cfg.max_stretch)
        if not torn > 1.0:
            raise InputError(f"fill tear growth must be a number > 1, got {tear}")
        if gathered is None or int(max_per_pair) < 1 or budget == 0:
            return empty
        dc, dd, w, cid, own_ok, rows = gathered
        m = pts.shape[0]
        # no pair grown by at most the tear growth (to float32 rounding) reaches ceil(tear / ratio) points, and no
        # more than that many times the pairs can be added: larger caps and budgets change nothing (and overflow)
        cap = min(int(max_per_pair), math.ceil(torn / ratio) + 1)
        limit = min(int(budget * m), m * rows.shape[1] * cap)
        loop = _fill_compiled(pts)
        if dc is self._dc:  # the canonical offsets' lengths, once per model
            if getattr(self, "_dc_len", None) is None:
                self._dc_len = self._dc.norm(dim=-1)
            lc = self._dc_len
        else:
            lc = dc.norm(dim=-1)
        ld = dd.norm(dim=-1)                                                         # [M, k]
        short = 1e-6 * self.scale[cid]
        if loop is not None:
            use_rev = canonical_rows and rows.shape == self.nbr.shape
            rev = self.reverse_slots if use_rev else rows.new_zeros(1, 1)
            arr = lambda x: np.ascontiguousarray(x.detach().numpy())  # noqa: E731
            gap_np, sparse_np = arr(torch.ones(m)), arr(torch.ones(m))
            out = loop(arr(pts), arr(dd), arr(dc), arr(self.canonical), arr(cid), arr(ld), arr(lc), arr(short),
                       arr(w), arr(rows), arr(rev), use_rev, np.float32(ratio), np.float32(torn), float(ratio),
                       cap, limit, gap_pairs == "budget", bool(with_gap), gap_np, sparse_np)
            new, canonical, source, partner, fraction = (torch.from_numpy(x) for x in out)
            res = (new, canonical, source)
            if with_partner:
                res = res + (partner, fraction)
            return res + (torch.from_numpy(gap_np), torch.from_numpy(sparse_np)) if with_gap else res
        grow = ld / lc.clamp_min(1e-30)
        pair = (w > 0) & (lc > short[:, None]) & (grow <= torn)
        sel = pair & (grow > ratio)
        if with_gap:  # pairs left as they are (grown by at most the ratio, or shrunk): their own growth, both ends
            keep = torch.where(pair & ~sel, grow, torch.ones_like(grow)).clamp_min(1.0).to(torch.float32)
            gap = gap.scatter_reduce(0, rows.reshape(-1), keep.reshape(-1), "amax").maximum(keep.amax(1))
            empty = empty[:-2] + (gap, sparse)
        # each pair once: keep j -> l when j < l, or when l does not list j (one-sided neighbourhoods)
        if canonical_rows and rows.shape == self.nbr.shape:  # the cached lists: look the other side up
            rev = self.reverse_slots
            k = rows.shape[1]
            back = (rev >= 0) & (w.reshape(-1)[rows * k + rev.clamp_min(0)] > 0)
            sel &= (torch.arange(m, device=rows.device)[:, None] < rows) | ~back
            j, slot = torch.nonzero(sel, as_tuple=True)
            if j.numel() == 0:
                return empty
        else:
            j, slot = torch.nonzero(sel, as_tuple=True)
            if j.numel() == 0:
                return empty
            other = rows[j, slot]
            back = ((rows[other] == j[:, None]) & (w[other] > 0)).any(1)
            once = (j < other) | ~back
            j, slot = j[once], slot[once]
        g = grow[j, slot].double()

        def count(r: float) -> torch.Tensor:  # points per pair at ratio r (g / r = i exactly gives i − 1)
            return (torch.ceil(g / r * (1.0 - 1e-12)) - 1.0).clamp(0, cap).long()

        n = count(ratio)
        if int(n.sum()) > limit:
            n = count(_budget_ratio(g, ratio, cap, limit, count))
        if with_gap:  # growth left between consecutive points of each filled pair, at both ends
            left = (g / (n + 1).to(g.dtype)).to(torch.float32)
            gap = gap.scatter_reduce(0, j, left, "amax").scatter_reduce(0, rows[j, slot], left, "amax")
            open_ = left > ratio
            if gap_pairs == "budget":
                open_ &= n < cap
            left = torch.where(open_, left, torch.ones_like(left))
            sparse = sparse.scatter_reduce(0, j, left, "amax").scatter_reduce(0, rows[j, slot], left, "amax")
            empty = empty[:-2] + (gap, sparse)
        keep = n > 0
        j, slot, n = j[keep], slot[keep], n[keep]
        if j.numel() == 0:
            return empty
        rep = torch.repeat_interleave(torch.arange(j.numel(), device=self.device), n)
        first = torch.cumsum(n, 0) - n
        i = torch.arange(rep.numel(), device=self.device) - first[rep] + 1
        t = (i.to(torch.float32) / (n[rep] + 1).to(torch.float32))[:, None]           # [P, 1] in (0, 1)
        jr, sr = j[rep], slot[rep]
        new = pts[jr] + t * dd[jr, sr]
        canonical = self.canonical[cid[jr]] + t * dc[jr, sr]
        near_j = t[:, 0] <= 0.5
        source = torch.where(near_j, jr, rows[jr, sr])
        out = (new, canonical, source)
        if with_partner:
            partner = torch.where(near_j, rows[jr, sr], jr)
            fraction = torch.where(near_j, t[:, 0], 1.0 - t[:, 0])
            out = out + (partner, fraction)
        return out + (gap, sparse) if with_gap else out


def _fill_count(g, r, cap):
    """Points per pair at ratio r (as `_fill`'s count): g [P] float64 growths -> their sum."""
    total = 0
    for p in range(g.shape[0]):
        c = math.ceil(g[p] / r * (1.0 - 1e-12)) - 1.0
        total += int(min(max(c, 0.0), cap))
    return total


def _kth_smallest(a, n, k):
    """The k-th smallest (0-based) of a[:n] (float64), reordering a[:n] in place: quickselect with a three-way
    partition around the median of three (many equal values, as a uniform stretch gives, cost no extra passes)."""
    lo, hi = 0, n - 1
    while lo < hi:
        x, y, z = a[lo], a[(lo + hi) // 2], a[hi]
        pivot = max(min(x, y), min(max(x, y), z))
        lt, i, gt = lo, lo, hi
        while i <= gt:  # a[lo:lt] < pivot, a[lt:i] == pivot, a[gt+1:hi+1] > pivot
            v = a[i]
            if v < pivot:
                a[i], a[lt] = a[lt], v
                lt += 1
                i += 1
            elif v > pivot:
                a[i], a[gt] = a[gt], v
                gt -= 1
            else:
                i += 1
        if k < lt:
            hi = lt - 1
        elif k > gt:
            lo = gt + 1
        else:
            return pivot
    return a[k]


def _fill_next_step(g, r, ratio, cap, up):
    """The step g / i >= ratio (i = 1 .. cap) next above r (up) or next below it (not up); -1 where there is none."""
    best = -1.0
    for p in range(g.shape[0]):
        for i in range(1, cap + 1):
            v = g[p] / i
            if v < ratio:  # the steps of one pair fall with i
                break
            if up:
                if v > r and (best < 0.0 or v < best):
                    best = v
            elif v < r and v > best:
                best = v
    return best


def _fill_budget_ratio(g, ratio, cap, limit):
    """_budget_ratio's value, compiled: the smallest step g / i >= ratio (i = 1 .. cap) whose count keeps the limit.
    A floor below which it cannot lie first (a few halvings of [ratio, max g] by the count: more than limit + 1 steps
    above it); the (limit + 1)-th largest step above the floor (above the ratio where too few lie above the floor) by
    a quickselect; from there, the next larger step while the count is above the limit, then the next smaller one
    while that one keeps it (the count only falls as the ratio rises, so this ends on the same step the bisection
    over every distinct step finds; usually no step is walked)."""
    lo, hi = ratio, ratio
    for p in range(g.shape[0]):
        hi = max(hi, g[p])
    for _ in range(8):
        mid = 0.5 * (lo + hi)
        if _fill_count_c(g, mid, cap) > limit + 1:
            lo = mid
        else:
            hi = mid
    steps = np.empty(g.shape[0] * cap)
    r = -1.0
    for floor in (lo, ratio):
        cnt = 0
        for p in range(g.shape[0]):
            for i in range(1, cap + 1):
                v = g[p] / i
                if v < floor:
                    break
                steps[cnt] = v
                cnt += 1
        if cnt > limit:
            at = cnt - 1 - limit
            r = _kth_smallest_c(steps, cnt, at)
            below = -1.0  # the next smaller step: every step above the floor and below r lies left of it
            for j in range(at):
                if steps[j] < r and steps[j] > below:
                    below = steps[j]
            if _fill_count_c(g, r, cap) <= limit and (below >= 0.0 or floor == ratio) and (
                    below < 0.0 or _fill_count_c(g, below, cap) > limit):
                return r  # the common case: r keeps the limit, the next smaller step does not
            break
        if floor == ratio and cnt:  # fewer steps than the limit above the ratio: start from the smallest
            r = _kth_smallest_c(steps, cnt, 0)
    while _fill_count_c(g, r, cap) > limit:
        r = _fill_next_step_c(g, r, ratio, cap, True)  # the largest step has count 0: this ends
    while True:
        below = _fill_next_step_c(g, r, ratio, cap, False)
        if below < 0.0 or _fill_count_c(g, below, cap) > limit:
            return r
        r = below


def _fill_loop(pts, dd, dc, canonical, cid, ld, lc, short, w, rows, rev, use_rev, ratio32, torn32, ratio, cap,
               limit, budget_pairs, with_gap, gap, sparse):
    """The compiled path of `DeformationField._fill` from the neighbour offsets' lengths (ld, lc [M, k] float32
    deformed and canonical; short [M] float32 the length below which a point's canonical offset is no pair): the same
    pairs, budget ratio, points (in the same order, bit for bit) and, with_gap, gap and sparse [M] float32
    written in place (given as ones). Returns (new [P, 3], canonical [P, 3] float32, source [P], partner [P] int64,
    fraction [P] float32)."""
    m, k = ld.shape
    one = np.float32(1.0)
    tiny = np.float32(1e-30)
    pj = np.empty(m * k, dtype=np.int64)
    ps = np.empty(m * k, dtype=np.int64)
    g = np.empty(m * k)
    q = 0
    for a in range(m):
        best = one
        for s in range(k):
            grow = ld[a, s] / max(lc[a, s], tiny)
            pair = w[a, s] > 0 and lc[a, s] > short[a] and grow <= torn32
            sel = pair and grow > ratio32
            if with_gap:  # pairs left as they are: their own growth, at both ends
                v = grow if pair and not sel and grow > one else one
                best = max(best, v)
                b = rows[a, s]
                gap[b] = max(gap[b], v)
            if not sel:
                continue
            # each pair once: j -> l when j < l, or when l does not list j back
            o = rows[a, s]
            back = False
            if use_rev:
                back = rev[a, s] >= 0 and w[o, rev[a, s]] > 0
            else:
                for u in range(k):
                    if rows[o, u] == a and w[o, u] > 0:
                        back = True
                        break
            if a < o or not back:
                pj[q] = a
                ps[q] = s
                g[q] = np.float64(grow)
                q += 1
        if with_gap:
            gap[a] = max(gap[a], best)
    g = g[:q]
    n = np.empty(q, dtype=np.int64)
    if _fill_count_c(g, ratio, cap) > limit:
        ratio_n = _fill_budget_ratio_c(g, ratio, cap, limit)
    else:
        ratio_n = ratio
    total = 0
    for p in range(q):
        c = math.ceil(g[p] / ratio_n * (1.0 - 1e-12)) - 1.0
        n[p] = int(min(max(c, 0.0), cap))
        total += n[p]
        if with_gap:  # growth left between consecutive points of the pair, at both ends
            left = np.float32(g[p] / np.float64(n[p] + 1))
            a, b = pj[p], rows[pj[p], ps[p]]
            gap[a] = max(gap[a], left)
            gap[b] = max(gap[b], left)
            if left > ratio32 and (not budget_pairs or n[p] < cap):
                sparse[a] = max(sparse[a], left)
                sparse[b] = max(sparse[b], left)
    new = np.empty((total, 3), dtype=np.float32)
    can = np.empty((total, 3), dtype=np.float32)
    source = np.empty(total, dtype=np.int64)
    partner = np.empty(total, dtype=np.int64)
    fraction = np.empty(total, dtype=np.float32)
    e = 0
    for p in range(q):
        a, s = pj[p], ps[p]
        o = rows[a, s]
        c = cid[a]
        for i in range(1, n[p] + 1):
            t = np.float32(i) / np.float32(n[p] + 1)
            for d in range(3):
                new[e, d] = pts[a, d] + t * dd[a, s, d]
                can[e, d] = canonical[c, d] + t * dc[a, s, d]
            if t <= np.float32(0.5):
                source[e], partner[e], fraction[e] = a, o, t
            else:
                source[e], partner[e], fraction[e] = o, a, one - t
            e += 1
    return new, can, source, partner, fraction


_fill_count_c = njit(_fill_count)
_fill_next_step_c = njit(_fill_next_step)
_kth_smallest_c = njit(_kth_smallest)
_fill_budget_ratio_c = njit(_fill_budget_ratio)
_compiled_fill_loop = None


def _fill_compiled(pts: torch.Tensor):
    """The compiled fill loop for CPU tensors where numba is installed, else None (the torch path)."""
    global _compiled_fill_loop
    if numba is None or pts.device.type != "cpu":
        return None
    if _compiled_fill_loop is None:
        _compiled_fill_loop = njit(_fill_loop)
    return _compiled_fill_loop


def _budget_ratio(g: torch.Tensor, ratio: float, cap: int, limit: int, count) -> float:
    """The smallest ratio r among the values g / i (i = 1 .. cap, r >= ratio) at which count(r).sum() <= limit:
    g [P] float64 the pairs' growths, count(r) -> [P] the points per pair at ratio r (non-increasing in r).

    The count only changes where r crosses some g / i, so r is one of those steps. A pair gets one point per step
    above r (at most cap), so the count at r is the number of steps above it and r is about the (limit + 1)-th
    largest step: taken from a partial sort and checked (it keeps the budget, the next smaller step does not);
    where the check fails (ties, rounding) a bisection over all distinct steps decides, as it always did."""
    steps = (g[:, None] / torch.arange(1, cap + 1, dtype=g.dtype, device=g.device)).reshape(-1)
    ok = lambda r: int(count(r).sum()) <= limit  # noqa: E731
    if limit + 1 <= steps.numel():
        top = torch.topk(steps, min(limit + 2, steps.numel())).values               # descending
        r = float(top[limit])
        below = float(top[limit + 1]) if limit + 1 < top.numel() else None
        if below is not None and below >= r:  # a tie at r: the largest step below it
            low = steps[steps < r]
            below = float(low.max()) if low.numel() else None
        if below is not None and below < ratio:
            below = None  # r is the smallest step at or above the ratio
        if r >= ratio and ok(r) and (below is None or not ok(below)):
            return r
    steps = steps[steps >= ratio]
    cands = torch.unique(steps)                                                       # ascending; count(max) = 0
    lo, hi = 0, cands.numel() - 1
    while lo < hi:
        mid = (lo + hi) // 2
        lo, hi = (lo, mid) if ok(float(cands[mid])) else (mid + 1, hi)
    return float(cands[lo])


def _moments(w: torch.Tensor, x: torch.Tensor, y: torch.Tensor) -> torch.Tensor:
    """Weighted mean outer products Σ_l w_l x_l y_lᵀ / Σ_l w_l: w [M, k], x, y [M, k, 3] -> [M, 3, 3]."""
    return torch.einsum("mk,mki,mkj->mij", w, x, y) / w.sum(1).clamp_min(1e-30)[:, None, None]


def _min_sv_at_least(f: torch.Tensor, lo: float) -> torch.Tensor:
    """[M] bool: certainly every singular value of F [M, 3, 3] is ≥ lo (FᵀF − lo² I positive definite, by its
    leading principal minors); False where unsure."""
    c = f.transpose(1, 2) @ f - (lo * lo) * torch.eye(3, dtype=f.dtype, device=f.device)
    m1 = c[:, 0, 0]
    m2 = c[:, 0, 0] * c[:, 1, 1] - c[:, 0, 1] * c[:, 1, 0]
    m3 = det3(c)
    return (m1 > 0) & (m2 > 0) & (m3 > 0)


def bound(f: torch.Tensor, max_stretch: float) -> torch.Tensor:
    """F [M, 3, 3] with the magnitudes of its singular values clamped to [1/max_stretch, max_stretch], sign of
    det F kept (an exactly singular F becomes orientation-preserving). Untouched rows stay bit-identical."""
    lo, hi = 1.0 / max_stretch, max_stretch
    # σmax ≤ ‖F‖_F: rows with a small norm and certainly no small singular value need no SVD
    need = (torch.linalg.matrix_norm(f) > hi) | ~_min_sv_at_least(f, lo)
    if not bool(need.any()):
        return f
    out = f.clone()
    f = f[need]
    u, sv, vh = torch.linalg.svd(f)
    sv = sv.clamp(lo, hi)
    # keep the sign of det F (a singular F: positive); its SVD's own sign is arbitrary when det F = 0
    want = torch.where(torch.linalg.det(f) < 0, -1.0, 1.0).to(sv.dtype)
    sv[:, 2] = sv[:, 2] * want * torch.sign(torch.linalg.det(u @ vh))
    out[need] = u @ torch.diag_embed(sv) @ vh
    return out


def polar(f: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """Polar parts of F [M, 3, 3]: (R [M, 3, 3] rotation, det +1; S [M, 3, 3] symmetric) with F = R S.
    S is positive definite unless det F < 0 (a mirrored neighbourhood: one negative eigenvalue)."""
    u, sv, vh = torch.linalg.svd(f)
    d = torch.ones_like(sv)
    d[:, 2] = torch.where(torch.linalg.det(u @ vh) < 0, -1.0, 1.0).to(sv.dtype)
    r = u @ (d[..., None] * vh)
    s = vh.transpose(1, 2) @ torch.diag_embed(d * sv) @ vh
    return r, s


def inverse(f: torch.Tensor) -> torch.Tensor:
    """F⁻¹ [M, 3, 3] of bounded gradients (their singular values are ≥ 1/max_stretch, so this is finite), in float64:
    by the adjugate in the compiled loop of `key_inverse` (no cap) on CPU tensors, else torch.linalg.inv (the
    reference it is tested against)."""
    loop = _key_compiled(f)
    if loop is not None:
        return _run_key_loop(loop, f, torch.full((f.shape[0],), math.inf, dtype=torch.float64), None, 1)
    return torch.linalg.inv(f.double()).to(f.dtype)


def det3(a: torch.Tensor) -> torch.Tensor:
    """Determinants [...] of 3×3 matrices a [..., 3, 3] by the cofactor expansion (in a's dtype): a batched LU
    (torch.linalg.det) costs ten times as much for thousands of small matrices."""
    return (a[..., 0, 0] * (a[..., 1, 1] * a[..., 2, 2] - a[..., 1, 2] * a[..., 2, 1])
            - a[..., 0, 1] * (a[..., 1, 0] * a[..., 2, 2] - a[..., 1, 2] * a[..., 2, 0])
            + a[..., 0, 2] * (a[..., 1, 0] * a[..., 2, 1] - a[..., 1, 1] * a[..., 2, 0]))


def _jacobi_eigen(a, v, tol):
    """Cyclic Jacobi rotations on the symmetric 3×3 float64 array a, in place, until its off-diagonal part is at most
    tol times its diagonal's (squared sums; at most 16 sweeps): a -> diag(λ), v [3, 3] -> v times the rotations (the
    eigenvectors in its columns when v starts as I). Compiled as `_jacobi` for the compiled loops below."""
    for _sweep in range(16):
        off = a[0, 1] * a[0, 1] + a[0, 2] * a[0, 2] + a[1, 2] * a[1, 2]
        if off <= tol * (a[0, 0] * a[0, 0] + a[1, 1] * a[1, 1] + a[2, 2] * a[2, 2]) or off == 0.0:
            break
        for p, q in ((0, 1), (0, 2), (1, 2)):
            if a[p, q] == 0.0:
                continue
            theta = (a[q, q] - a[p, p]) / (2.0 * a[p, q])
            t = 1.0 / (abs(theta) + math.sqrt(theta * theta + 1.0))
            if theta < 0.0:
                t = -t
            c = 1.0 / math.sqrt(t * t + 1.0)
            s = t * c
            for k in range(3):
                akp, akq = a[k, p], a[k, q]
                a[k, p], a[k, q] = c * akp - s * akq, s * akp + c * akq
            for k in range(3):
                apk, aqk = a[p, k], a[q, k]
                a[p, k], a[q, k] = c * apk - s * aqk, s * apk + c * aqk
            for k in range(3):
                vkp, vkq = v[k, p], v[k, q]
                v[k, p], v[k, q] = c * vkp - s * vkq, s * vkp + c * vkq


def _njit(fn):
    """fn compiled by numba on first call (cached on disk where the cache folder is writable); None without numba."""
    return None if numba is None else njit(fn)


_jacobi = _njit(_jacobi_eigen) or _jacobi_eigen


def _adjugate_inverse(g, out, m):
    """out[m] = g⁻¹ for a 3×3 float64 array g, by the adjugate; I where g is singular or not finite. The one form of
    F⁻¹ the compiled loops below write (`_key_loop`, `_inverse_rows_loop`), so they give the same numbers."""
    c00 = g[1, 1] * g[2, 2] - g[1, 2] * g[2, 1]
    c01 = g[1, 2] * g[2, 0] - g[1, 0] * g[2, 2]
    c02 = g[1, 0] * g[2, 1] - g[1, 1] * g[2, 0]
    det = g[0, 0] * c00 + g[0, 1] * c01 + g[0, 2] * c02
    if det == 0.0 or not math.isfinite(det):
        for i in range(3):
            for j in range(3):
                out[m, i, j] = 1.0 if i == j else 0.0
        return
    r = 1.0 / det
    out[m, 0, 0] = c00 * r
    out[m, 1, 0] = c01 * r
    out[m, 2, 0] = c02 * r
    out[m, 0, 1] = (g[0, 2] * g[2, 1] - g[0, 1] * g[2, 2]) * r
    out[m, 1, 1] = (g[0, 0] * g[2, 2] - g[0, 2] * g[2, 0]) * r
    out[m, 2, 1] = (g[0, 1] * g[2, 0] - g[0, 0] * g[2, 1]) * r
    out[m, 0, 2] = (g[0, 1] * g[1, 2] - g[0, 2] * g[1, 1]) * r
    out[m, 1, 2] = (g[0, 2] * g[1, 0] - g[0, 0] * g[1, 2]) * r
    out[m, 2, 2] = (g[0, 0] * g[1, 1] - g[0, 1] * g[1, 0]) * r


_adjugate = _njit(_adjugate_inverse) or _adjugate_inverse


def _inverse_rows_loop(f, rows, out):
    """The compiled path of inverse_at: f [M, 3, 3] float32, rows [P] int64 -> out [M, 3, 3] float32 at those rows,
    each F⁻¹ in float64 by `_adjugate`, as `_key_loop` computes it without a cap (I where F is singular or not
    finite)."""
    g = np.empty((3, 3))
    for r in range(rows.shape[0]):
        m = rows[r]
        for i in range(3):
            for j in range(3):
                g[i, j] = f[m, i, j]
        _adjugate(g, out, m)


_inverse_rows = _njit(_inverse_rows_loop)


def inverse_at(f: torch.Tensor, rows: torch.Tensor, out: torch.Tensor) -> None:
    """F⁻¹ of the rows [P] long of bounded gradients f [M, 3, 3] written into out [M, 3, 3] (f's dtype) at those
    rows, each `inverse(f)`'s row: a frame that reads a few points' inverses (the occlusion rule) does not invert
    them all. Compiled on float32 CPU tensors, else by `inverse` of the rows."""
    if rows.numel() == 0:
        return
    if (_inverse_rows is not None and f.device.type == "cpu" and f.dtype == torch.float32
            and out.dtype == torch.float32 and f.is_contiguous() and out.is_contiguous()):
        _inverse_rows(f.detach().numpy(), np.ascontiguousarray(rows.to(torch.int64).numpy()), out.numpy())
        return
    out[rows] = inverse(f[rows])


def _expansion_inverse_loop(f, out):
    """The compiled path of expansion_inverse: f [M, 3, 3] float64 -> out [M, 3, 3]. Per row: FᵀF = V diag(σ²) Vᵀ
    by cyclic Jacobi rotations, then V diag(1/(σ max(σ, 1))) Vᵀ Fᵀ."""
    a = np.empty((3, 3))
    v = np.empty((3, 3))
    h = np.empty(3)
    for m in range(f.shape[0]):
        for i in range(3):
            for j in range(3):
                a[i, j] = f[m, 0, i] * f[m, 0, j] + f[m, 1, i] * f[m, 1, j] + f[m, 2, i] * f[m, 2, j]
                v[i, j] = 1.0 if i == j else 0.0
        _jacobi(a, v, 1e-30)
        for i in range(3):
            sv = max(math.sqrt(max(a[i, i], 0.0)), 1e-6)
            h[i] = 1.0 / (sv * max(sv, 1.0))
        for i in range(3):
            for j in range(3):  # (V diag(h) Vᵀ)[i, j], then times Fᵀ
                a[i, j] = v[i, 0] * h[0] * v[j, 0] + v[i, 1] * h[1] * v[j, 1] + v[i, 2] * h[2] * v[j, 2]
        for i in range(3):
            for j in range(3):
                out[m, i, j] = a[i, 0] * f[m, j, 0] + a[i, 1] * f[m, j, 1] + a[i, 2] * f[m, j, 2]


_compiled_loop = None


def _compiled():
    global _compiled_loop
    if _compiled_loop is None:
        _compiled_loop = _njit(_expansion_inverse_loop)
    return _compiled_loop


def expansion_inverse(f: torch.Tensor) -> torch.Tensor:
    """Inverse [M, 3, 3] of F [M, 3, 3] with its singular values raised to at least 1: undoes the stretch of a
    neighbourhood (and its rotation / mirror), leaves its compression. F = U Σ Vᵀ -> V max(Σ, 1)⁻¹ Uᵀ.
    Compiled (numba) on CPU tensors, else torch."""
    loop = _compiled() if f.device.type == "cpu" else None
    if loop is not None and f.shape[0]:
        fd = np.ascontiguousarray(torch.nan_to_num(f.detach(), 0.0, 0.0, 0.0).double().numpy())
        out = np.empty_like(fd)
        loop(fd, out)
        return torch.from_numpy(out).to(f.dtype)
    return _expansion_inverse_torch(f)


def _expansion_inverse_torch(f: torch.Tensor) -> torch.Tensor:
    """expansion_inverse in torch (any device; the reference the compiled path is tested against)."""
    fd = f.double()
    out, info = torch.linalg.inv_ex(fd)
    # no singular value below 1 - 1e-3: F⁻¹ as it is (within 0.1 % of undoing no compression); SVD for the others
    need = ~_min_sv_at_least(fd, 1.0 - 1e-3) | (info != 0) | ~torch.isfinite(out).all(-1).all(-1)
    if bool(need.any()):
        # with FᵀF = V diag(σ²) Vᵀ (eigh: cheaper than an SVD), V max(Σ, 1)⁻¹ Uᵀ = V diag(1/(σ max(σ, 1))) Vᵀ Fᵀ
        fn = fd[need]
        lam, v = torch.linalg.eigh(fn.transpose(1, 2) @ fn)
        sv = lam.clamp_min(0.0).sqrt().clamp_min(1e-6)
        out[need] = v @ torch.diag_embed(1.0 / (sv * sv.clamp_min(1.0))) @ v.transpose(1, 2) @ fn.transpose(1, 2)
    return out.to(f.dtype)


def _key_loop(f, cap, n, mode, out):
    """The compiled path of bound_above and key_inverse: f [M, 3, 3] float64, cap [M], n [M, 3] unit normals (read
    with mode 2) -> out [M, 3, 3]. Per row, first the capped F: F itself when ‖F‖_F ≤ cap or cap² I − FᵀF is
    positive definite or, by Gershgorin's bound, σ1² ≤ cap² (1 + 1e-12) (every σ within the cap), else F V
    diag(min(σ, cap) / σ) Vᵀ with FᵀF = V diag(σ²) Vᵀ: where one or two σ² exceed cap² and lie 1e-6 σ1² or more from
    those within it, from the closed-form eigenvalues and eigenvectors by cross products of the rows of FᵀF − σ² I;
    else by cyclic Jacobi rotations. mode 0: out = that; 1: its inverse; 2: the inverse of it with its column along
    n raised to unit length where shorter (G = F + (1/|F n| − 1) F n nᵀ, the tangent rule)."""
    a = np.empty((3, 3))
    v = np.empty((3, 3))
    u = np.empty((2, 3))
    h = np.empty(3)
    g = np.empty((3, 3))
    for m in range(f.shape[0]):
        c2 = cap[m] * cap[m]
        fro = 0.0
        for i in range(3):
            for j in range(3):
                g[i, j] = f[m, i, j]
                fro += f[m, i, j] * f[m, i, j]
        if fro > c2:
            for i in range(3):
                for j in range(3):
                    a[i, j] = f[m, 0, i] * f[m, 0, j] + f[m, 1, i] * f[m, 1, j] + f[m, 2, i] * f[m, 2, j]
                    v[i, j] = 1.0 if i == j else 0.0
            # cap² I − FᵀF positive definite (its leading principal minors): every σ < cap, F stays
            b00, b11, b22 = c2 - a[0, 0], c2 - a[1, 1], c2 - a[2, 2]
            m2 = b00 * b11 - a[0, 1] * a[0, 1]
            m3 = (b00 * (b11 * b22 - a[1, 2] * a[1, 2]) - a[0, 1] * (a[0, 1] * b22 + a[1, 2] * a[0, 2])
                  - a[0, 2] * (a[0, 1] * a[1, 2] + b11 * a[0, 2]))
            # the common cases: the largest σ (or the two largest) beyond the cap, well apart from the rest. Their
            # eigenvalues of FᵀF in closed form (trigonometric), v1 and v3 from the cross products of the rows of
            # FᵀF − λ I, V diag(h) Vᵀ = h2 I + (h1 − h2) v1 v1ᵀ + (1 − h2) v3 v3ᵀ; the Jacobi rotations below else
            jacobi = not (b00 > 0.0 and m2 > 0.0 and m3 > 0.0)
            if jacobi and max(a[0, 0] + abs(a[0, 1]) + abs(a[0, 2]), a[1, 1] + abs(a[0, 1]) + abs(a[1, 2]),
                              a[2, 2] + abs(a[0, 2]) + abs(a[1, 2])) <= c2 * (1.0 + 1e-12):
                jacobi = False  # σ1² ≤ cap² to rounding (Gershgorin; a rigidly moved part at a cap of 1): F stays
            if jacobi:
                p1 = a[0, 1] * a[0, 1] + a[0, 2] * a[0, 2] + a[1, 2] * a[1, 2]
                qq = (a[0, 0] + a[1, 1] + a[2, 2]) / 3.0
                d0, d1, d2 = a[0, 0] - qq, a[1, 1] - qq, a[2, 2] - qq
                pp = math.sqrt((d0 * d0 + d1 * d1 + d2 * d2 + 2.0 * p1) / 6.0)
                if pp > 1e-150 * max(qq, 1.0):
                    ip = 1.0 / pp
                    x00, x11, x22 = d0 * ip, d1 * ip, d2 * ip
                    x01, x02, x12 = a[0, 1] * ip, a[0, 2] * ip, a[1, 2] * ip
                    r = 0.5 * (x00 * (x11 * x22 - x12 * x12) - x01 * (x01 * x22 - x12 * x02)
                               + x02 * (x01 * x12 - x11 * x02))
                    r = min(max(r, -1.0), 1.0)
                    phi = math.acos(r) / 3.0
                    lam1 = qq + 2.0 * pp * math.cos(phi)
                    lam3 = qq + 2.0 * pp * math.cos(phi + 2.0943951023931957)
                    lam2 = 3.0 * qq - lam1 - lam3
                    one = lam2 < c2 and lam1 - lam2 > 1e-6 * lam1       # only σ1 beyond the cap
                    two = lam2 >= c2 and lam3 < c2 and lam2 - lam3 > 1e-6 * lam1  # σ1 and σ2 beyond it
                    if one and lam1 <= c2:  # every σ within the cap after all (rounding at the border): F stays
                        jacobi = False
                    elif one or two:
                        ok = True
                        for e in range(2 if two else 1):
                            lv = lam1 if e == 0 else lam3
                            r00, r01, r02 = a[0, 0] - lv, a[0, 1], a[0, 2]
                            r10, r11, r12 = a[0, 1], a[1, 1] - lv, a[1, 2]
                            r20, r21, r22 = a[0, 2], a[1, 2], a[2, 2] - lv
                            best = -1.0
                            for pick in range(3):
                                if pick == 0:
                                    y0, y1, y2 = r01 * r12 - r02 * r11, r02 * r10 - r00 * r12, r00 * r11 - r01 * r10
                                elif pick == 1:
                                    y0, y1, y2 = r01 * r22 - r02 * r21, r02 * r20 - r00 * r22, r00 * r21 - r01 * r20
                                else:
                                    y0, y1, y2 = r11 * r22 - r12 * r21, r12 * r20 - r10 * r22, r10 * r21 - r11 * r20
                                yn = y0 * y0 + y1 * y1 + y2 * y2
                                if yn > best:
                                    best, u[e, 0], u[e, 1], u[e, 2] = yn, y0, y1, y2
                            if best > 1e-24 * lam1 * lam1 * lam1 * lam1:
                                yi = 1.0 / math.sqrt(best)
                                u[e, 0], u[e, 1], u[e, 2] = u[e, 0] * yi, u[e, 1] * yi, u[e, 2] * yi
                            elif e == 0 and two:  # σ1 = σ2 (to rounding): h1 = h2, no v1 term
                                u[e, 0] = u[e, 1] = u[e, 2] = 0.0
                            else:
                                ok = False
                        if ok:
                            h1 = cap[m] / math.sqrt(lam1)
                            if two:
                                h2 = cap[m] / math.sqrt(lam2)
                                c0, c1, c3 = h2, h1 - h2, 1.0 - h2
                            else:
                                c0, c1, c3 = 1.0, h1 - 1.0, 0.0
                                u[1, 0] = u[1, 1] = u[1, 2] = 0.0
                            for i in range(3):
                                for j in range(3):
                                    a[i, j] = (c0 if i == j else 0.0) + c1 * u[0, i] * u[0, j] + c3 * u[1, i] * u[1, j]
                            for i in range(3):
                                for j in range(3):
                                    g[i, j] = f[m, i, 0] * a[0, j] + f[m, i, 1] * a[1, j] + f[m, i, 2] * a[2, j]
                            jacobi = False
            if jacobi:
                _jacobi(a, v, 1e-20)
                if max(a[0, 0], a[1, 1], a[2, 2]) > c2:
                    for i in range(3):
                        sv = max(math.sqrt(max(a[i, i], 0.0)), 1e-30)
                        h[i] = min(sv, cap[m]) / sv
                    for i in range(3):
                        for j in range(3):  # V diag(h) Vᵀ, then F times it
                            a[i, j] = v[i, 0] * h[0] * v[j, 0] + v[i, 1] * h[1] * v[j, 1] + v[i, 2] * h[2] * v[j, 2]
                    for i in range(3):
                        for j in range(3):
                            g[i, j] = f[m, i, 0] * a[0, j] + f[m, i, 1] * a[1, j] + f[m, i, 2] * a[2, j]
        if mode == 2:  # the tangent rule: the column along n raised to unit length where shorter
            fn0 = g[0, 0] * n[m, 0] + g[0, 1] * n[m, 1] + g[0, 2] * n[m, 2]
            fn1 = g[1, 0] * n[m, 0] + g[1, 1] * n[m, 1] + g[1, 2] * n[m, 2]
            fn2 = g[2, 0] * n[m, 0] + g[2, 1] * n[m, 1] + g[2, 2] * n[m, 2]
            ln = max(math.sqrt(fn0 * fn0 + fn1 * fn1 + fn2 * fn2), 1e-12)
            if ln < 1.0:
                k = 1.0 / ln - 1.0
                for j in range(3):
                    g[0, j] += k * fn0 * n[m, j]
                    g[1, j] += k * fn1 * n[m, j]
                    g[2, j] += k * fn2 * n[m, j]
        if mode == 0:
            for i in range(3):
                for j in range(3):
                    out[m, i, j] = g[i, j]
            continue
        _adjugate(g, out, m)  # its inverse


_compiled_key_loop = None


def _key_compiled(f: torch.Tensor):
    global _compiled_key_loop
    if _compiled_key_loop is None and f.device.type == "cpu":
        _compiled_key_loop = _njit(_key_loop)
    return _compiled_key_loop if f.device.type == "cpu" and f.shape[0] else None


def _run_key_loop(loop, f, cap, n, mode):
    fd = np.ascontiguousarray(torch.nan_to_num(f.detach(), 0.0, 0.0, 0.0).double().numpy())
    cd = np.ascontiguousarray(cap.detach().double().numpy())
    nd = np.ascontiguousarray((torch.zeros(f.shape[0], 3) if n is None else n.detach()).double().numpy())
    out = np.empty_like(fd)
    loop(fd, cd, nd, mode, out)
    return torch.from_numpy(out).to(f.dtype)


def bound_above(f: torch.Tensor, cap: torch.Tensor) -> torch.Tensor:
    """F [M, 3, 3] with its singular values clamped to at most cap [M] (> 0) per row: F = U Σ Vᵀ -> U min(Σ, cap)
    Vᵀ (directions, orientation and the smaller singular values kept; rows whose largest singular value is within
    their cap unchanged). Compiled (numba) on CPU tensors, else torch."""
    loop = _key_compiled(f)
    if loop is not None:
        return _run_key_loop(loop, f, cap, None, 0)
    return _bound_above_torch(f, cap)


def key_inverse(f: torch.Tensor, cap: torch.Tensor | None = None, normals: torch.Tensor | None = None) -> torch.Tensor:
    """Inverse [M, 3, 3] of F [M, 3, 3] (bounded: `bound`) with its singular values capped at cap [M] (None: no
    cap) and, given normals [M, 3] (unit), its column along the normal raised to unit length where shorter: G = F' +
    (1/|F' n| − 1) F' n nᵀ for |F' n| < 1, F' the capped F (the tangent compression rule: compression across the
    surface not undone). Compiled (numba) on CPU tensors, else torch."""
    if cap is None:
        cap = torch.full((f.shape[0],), math.inf, dtype=torch.float64, device=f.device)
    loop = _key_compiled(f)
    if loop is not None:
        return _run_key_loop(loop, f, cap, normals, 1 if normals is None else 2)
    return _key_inverse_torch(f, cap, normals)


def _key_inverse_torch(f: torch.Tensor, cap: torch.Tensor, normals: torch.Tensor | None) -> torch.Tensor:
    """key_inverse in torch (any device; the reference the compiled path is tested against)."""
    fk = _bound_above_torch(f, cap).double()
    fi = torch.linalg.inv(fk)
    if normals is None:
        return fi.to(f.dtype)
    n = normals.double()
    fn = (fk @ n[..., None]).squeeze(-1).norm(dim=-1).clamp_min(1e-12)
    k = fn / fn.clamp_min(1.0) - 1.0  # 1/scale − 1, scale = max(|F n|, 1) / |F n|
    # G⁻¹ = (I + (1/scale − 1) n nᵀ) F⁻¹
    return (fi + k[:, None, None] * n[..., None] @ (n[:, None, :] @ fi)).to(f.dtype)


def _bound_above_torch(f: torch.Tensor, cap: torch.Tensor) -> torch.Tensor:
    """bound_above in torch (any device; the reference the compiled path is tested against)."""
    need = stretch(f.double()) > cap.to(f.device, torch.float64)
    if not bool(need.any()):
        return f
    out = f.clone()
    u, sv, vh = torch.linalg.svd(f[need].double())
    sv = torch.minimum(sv, cap.to(f.device, torch.float64)[need][:, None])
    out[need] = (u @ torch.diag_embed(sv) @ vh).to(f.dtype)
    return out


def stretch(f: torch.Tensor) -> torch.Tensor:
    """Largest singular value of F [M, 3, 3] -> [M]: how much a point's neighbourhood grew in its most stretched
    direction (1 at rest)."""
    return torch.linalg.matrix_norm(f, ord=2)


OUTLIER_FACTOR = 8.0  # with ids: neighbours whose offset grew this many times more than the median one are dropped

_FIELDS: "weakref.WeakKeyDictionary" = weakref.WeakKeyDictionary()


def field_for(model, cfg: DeformationConfig | None = None) -> DeformationField:
    """The model's DeformationField, built on first use and cached while the model lives (rebuilt when its
    canonical points or the config change)."""
    cfg = cfg or DeformationConfig()
    key = (int(model.xyz._version), model.xyz.data_ptr(), tuple(model.xyz.shape), str(model.xyz.device), cfg)
    hit = _FIELDS.get(model)
    if hit is not None and hit[0] == key:
        return hit[1]
    fld = DeformationField(model.xyz.detach(), cfg)
    _FIELDS[model] = (key, fld)
    return fld
