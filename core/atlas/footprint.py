"""Texture refit for pixel-filtered lookups: choose the texels so that rendering the training views the way edited
frames are rendered (S x S surface points per pixel, Blackman-Harris filter in linear light, core/images/filter.py)
reproduces their pixels.

Why: the kernel texture (texture.py) is the mean colour of the pixels around each texel — pixel colours are already
filtered by the renderer, so looking that texture up through the filter again blurs twice. Fitting through the same
filter is a linear least-squares problem in linear-light texels (a deconvolution, regularised towards the kernel
texture so texels no pixel constrains keep it); its gain is measured in docs/atlas.md ("Texture refit through
the pixel filter").
"""
from __future__ import annotations

import warnings
from dataclasses import dataclass
from typing import NamedTuple

import torch

from core.atlas.packing import bilinear_entries
from core.atlas.sample_lookup import LOOKUP_K, chart_texel_matrix, keeps_samples, lookup_texel_rows, sample_lookup
from core.atlas.subpixel import subpixel_chart_uv
from core.images.colour import linear_to_srgb, srgb_to_linear
from core.images.filter import FILTER_WIDTH, blackman_harris_taps, subpixel_points
from core.images.metrics import psnr


@dataclass
class FootprintView:
    """One training view as stage 1 sees it. points [H, W, 3] surface point of each pixel's ray (on the ray),
    valid [H, W] bool (the ray hits the object), depth [H, W] along the ray, image [H, W, 3] display colours,
    alpha [H, W] ground-truth coverage, focal in pixels (sqrt(fx * fy) for cameras with Intrinsics)."""

    points: torch.Tensor
    valid: torch.Tensor
    depth: torch.Tensor
    image: torch.Tensor
    alpha: torch.Tensor
    focal: float


def _bilinear_rows(probs: torch.Tensor, uv: torch.Tensor, R: int, min_prob: float = 1e-3):
    """Sparse rows of the lookup: (sample ids, texel ids, weights) with weight = bilinear x P(c|x), as
    packing.sample_charts interpolates (texel centres at (j + 0.5) / R, clamp to edge). probs [S, n], uv [S, n, 2].
    Only the (sample, chart) pairs with P > min_prob are expanded; the entries come sorted by sample, then chart,
    then corner (row-major), so each sample's texel ids ascend but where a corner is clamped at the image's edge."""
    sid, chart = torch.nonzero(probs > min_prob, as_tuple=True)  # row-major: by sample, then chart
    return bilinear_entries(sid, chart, probs[sid, chart], uv[sid, chart], R)


def _csr(rows: torch.Tensor, cols: torch.Tensor, vals: torch.Tensor, shape: tuple[int, int]) -> torch.Tensor:
    """A CSR matrix [shape] from COO entries sorted by row (repeated (row, col) entries are summed, as coalesce
    would). Where each row's columns are ascending already (the common case here) no sort is needed; otherwise a
    stable sort by (row, col) puts them in order first."""
    key = rows * shape[1] + cols
    if key.numel() > 1 and not bool((key[1:] >= key[:-1]).all()):
        key, order = torch.sort(key, stable=True)
        rows, cols, vals = rows[order], cols[order], vals[order]
    if key.numel() > 1 and bool((key[1:] == key[:-1]).any()):
        uniq, inv = torch.unique_consecutive(key, return_inverse=True)
        vals = torch.zeros(len(uniq), dtype=vals.dtype, device=vals.device).index_add_(0, inv, vals)
        rows, cols = uniq // shape[1], uniq % shape[1]
    crow = torch.zeros(shape[0] + 1, dtype=torch.long, device=rows.device)
    crow[1:] = torch.cumsum(torch.bincount(rows, minlength=shape[0]), 0)
    with warnings.catch_warnings():  # CSR is "beta" in torch; the products used here are long supported
        warnings.filterwarnings("ignore", message="Sparse CSR tensor support is in beta")
        return torch.sparse_csr_tensor(crow, cols, vals, shape, check_invariants=False)


class FootprintSystem(NamedTuple):
    """pixels = F @ B @ texels (linear light). F [P, Q] sparse filter rows, normalised over each footprint's object
    sub-pixels; B [Q, T] sparse lookup rows (T = n*R*R texels); y [P, 3] target linear colours; view [P] long, the
    index of the view each pixel comes from."""

    F: torch.Tensor
    B: torch.Tensor
    y: torch.Tensor
    view: torch.Tensor


def _sample_rows(atlas, per_sample, points, valid, depth, sub: int, step, k: int):
    """Sub-pixel lookups through the stored samples (core/atlas/sample_lookup.py), as scipy CSR rows over the chart
    texels [K, n R²] for the K sub-pixels on the object (row-major), and `on` [S*H, S*W] marking them."""
    sp_ = subpixel_points(points, valid, depth, sub, step)
    on = torch.isfinite(sp_).all(-1)
    rows = lookup_texel_rows(sample_lookup(atlas), atlas.on_surface(sp_[on]).cpu(), k, per_sample)
    return rows, on


def footprint_system(atlas, views: list[FootprintView], sub: int = 2, alpha_min: float = 0.99,
                     lookup: str = "charts", k: int = LOOKUP_K):
    """The linear system pixels = F @ B @ texels (linear light) over the views' fully covered pixels: a
    FootprintSystem, or None when no view has such a pixel. Only pixels with ground-truth alpha > alpha_min whose
    own ray hits the object are used (their colour is the object's, not a mix with the background).
    lookup: how the sub-pixels read the texels, as edited frames do (EditConfig lookup): "charts" (the chart
    networks per pixel, interpolated) or "samples" (the k nearest stored samples' reads; the charts when the atlas
    keeps no samples)."""
    dev = atlas.device
    through_samples = lookup == "samples" and keeps_samples(atlas)
    per_sample = chart_texel_matrix(atlas, sample_lookup(atlas)) if through_samples else None
    R, n = atlas.layout.R, atlas.n
    k1 = blackman_harris_taps(sub, FILTER_WIDTH).to(dev)
    m = k1.numel()
    pad = (m - sub) // 2
    k2 = (k1[:, None] * k1[None, :]).reshape(-1)  # [m*m]
    ky, kx = torch.meshgrid(torch.arange(m, device=dev), torch.arange(m, device=dev), indexing="ij")
    ky, kx = ky.reshape(-1), kx.reshape(-1)
    f_rows, f_cols, f_vals, b_rows, b_cols, b_vals, ys, vids = [], [], [], [], [], [], [], []
    n_pix = n_sub = 0
    for vi, v in enumerate(views):
        H, W = v.valid.shape
        step = 3.0 * v.depth.abs() / v.focal  # same surface: depth within 3 pixel footprints (as edited frames)
        # the same sub-pixel lookups as edited frames (core/frames/edited.py): chart nets per pixel, interpolated,
        # or the nearest stored samples' reads
        if through_samples:
            sample_rows, on = _sample_rows(atlas, per_sample, v.points.to(dev), v.valid.to(dev), v.depth.to(dev), sub,
                                           step.to(dev), k)
        else:
            probs_all, uv_all, on = subpixel_chart_uv(atlas, v.points.to(dev), v.valid.to(dev), v.depth.to(dev), sub,
                                                      step.to(dev))
        sub_index = torch.full(on.shape, -1, dtype=torch.long, device=dev)
        sub_index[on] = torch.arange(int(on.sum()), device=dev)
        use = v.valid.to(dev) & (v.alpha.to(dev) > alpha_min)
        pr, pc = torch.nonzero(use, as_tuple=True)
        if pr.numel() == 0:
            continue
        sy = pr[:, None] * sub - pad + ky[None]  # [P, m*m] sub-pixel rows of each footprint tap
        sx = pc[:, None] * sub - pad + kx[None]
        inside = (sy >= 0) & (sy < sub * H) & (sx >= 0) & (sx < sub * W)
        syc, sxc = sy.clamp(0, sub * H - 1), sx.clamp(0, sub * W - 1)
        tap_on = inside & on[syc, sxc]
        w = k2[None] * tap_on
        w = w / w.sum(1, keepdim=True).clamp_min(1e-12)
        flat = syc * (sub * W) + sxc
        used = torch.unique(flat[tap_on])
        remap = torch.full((sub * H * sub * W,), -1, dtype=torch.long, device=dev)
        remap[used] = torch.arange(len(used), device=dev) + n_sub
        keep = tap_on.reshape(-1)
        f_rows.append((torch.arange(len(pr), device=dev)[:, None] + n_pix).expand_as(flat).reshape(-1)[keep])
        f_cols.append(remap[flat.reshape(-1)[keep]])
        f_vals.append(w.reshape(-1)[keep])
        rows = sub_index.reshape(-1)[used]
        if through_samples:
            coo = sample_rows[rows.cpu().numpy()].tocoo()  # rows in `used` order, columns ascending in each
            r, c = torch.from_numpy(coo.row).long().to(dev), torch.from_numpy(coo.col).long().to(dev)
            val = torch.from_numpy(coo.data).to(dev, v.image.dtype)
        else:
            r, c, val = _bilinear_rows(probs_all[rows], uv_all[rows], R)
        b_rows.append(r + n_sub)
        b_cols.append(c)
        b_vals.append(val)
        ys.append(srgb_to_linear(v.image.to(dev)[pr, pc].clamp(0, 1)))
        vids.append(torch.full((len(pr),), vi, dtype=torch.long, device=dev))
        n_pix += len(pr)
        n_sub += len(used)
    if n_pix == 0:
        return None
    # rows come in pixel (sub-pixel) order and each row's columns ascend (footprint taps in raster order, remapped
    # monotonically; bilinear corners by chart, then raster order; clamped corners at the edge aside)
    F = _csr(torch.cat(f_rows), torch.cat(f_cols), torch.cat(f_vals), (n_pix, n_sub))
    B = _csr(torch.cat(b_rows), torch.cat(b_cols), torch.cat(b_vals), (n_sub, n * R * R))
    return FootprintSystem(F, B, torch.cat(ys), torch.cat(vids))


class _ReadTexels:
    """The system restricted to the texels some lookup reads (B's used columns, remapped), with the transposes the
    normal equations need, built once and shared by every solve on it."""

    def __init__(self, F: torch.Tensor, B: torch.Tensor):
        T = B.shape[1]  # all texels, read or not
        self.cols = torch.unique(B.col_indices())  # sorted: the remapped column indices stay sorted in every row
        remap = torch.full((T,), -1, dtype=torch.long, device=B.device)
        remap[self.cols] = torch.arange(len(self.cols), device=B.device)
        with warnings.catch_warnings():
            warnings.filterwarnings("ignore", message="Sparse CSR tensor support is in beta")
            self.Bu = torch.sparse_csr_tensor(B.crow_indices(), remap[B.col_indices()], B.values(),
                                              (B.shape[0], len(self.cols)), check_invariants=False)
            self.Bt, self.Ft = self.Bu.t().to_sparse_csr(), F.t().to_sparse_csr()
        self.F, self.T = F, T

    def A(self, u: torch.Tensor) -> torch.Tensor:
        """[U, C] read texels -> [P, C] filtered pixels."""
        return self.F @ (self.Bu @ u)

    def At(self, r: torch.Tensor) -> torch.Tensor:
        """[P, C] pixels -> [U, C] read texels."""
        return self.Bt @ (self.Ft @ r)

    def solve(self, y: torch.Tensor, u0: torch.Tensor, lam: float, iters: int, tol: float,
              weight: torch.Tensor | None = None, start: torch.Tensor | None = None) -> torch.Tensor:
        """Conjugate gradients on (AᵀWA + λ·d·I) u = AᵀWy + λ·d·u0 with W = diag(weight [P] in {0, 1}, default
        all 1), d = the sum of AᵀWA·1 over all T texels / T; from `start` (default u0); stops after `iters` iterations or
        when every channel's residual is below tol × its right-hand side. Returns u [U, C]."""
        w = None if weight is None else weight.to(y.dtype)[:, None]
        AtWA = (lambda u: self.At(self.A(u))) if w is None else (lambda u: self.At(w * self.A(u)))  # noqa: E731
        d = float(AtWA(torch.ones_like(u0[:, :1])).sum()) / max(self.T, 1)
        reg = lam * max(d, 1e-12)
        rhs = self.At(y if w is None else w * y) + reg * u0
        stop = (tol * rhs.norm(dim=0)).square().clamp_min(1e-20)
        u = (u0 if start is None else start).clone()
        r = rhs - AtWA(u) - reg * u
        p = r.clone()
        rs = (r * r).sum(0)
        for _ in range(iters):
            if bool((rs <= stop).all()):
                break
            Ap = AtWA(p) + reg * p
            a = rs / (p * Ap).sum(0).clamp_min(1e-30)
            u = u + a * p
            r = r - a * Ap
            rs_new = (r * r).sum(0)
            p = r + (rs_new / rs.clamp_min(1e-30)) * p
            rs = rs_new
        return u


def solve_footprint_texture(F: torch.Tensor, B: torch.Tensor, y: torch.Tensor, t0: torch.Tensor,
                            lam: float = 1.0, iters: int = 100, tol: float = 1e-5) -> tuple[torch.Tensor, dict]:
    """Conjugate gradients on (AᵀA + λ·d·I) t = Aᵀy + λ·d·t0 with A = F @ B, d = the mean of AᵀA·1 over all
    T texels (so λ does not depend on the number of views). t0 [T, 3] the prior (linear light); at most `iters`
    iterations, fewer once the residual is below tol × the right-hand side. Returns (t [T, 3] in [0, 1], info with
    the training RMSE before and after).
    Texels no lookup reads (B's empty columns) have a zero row in AᵀA, so they keep t0 exactly; the iterations run
    on the read texels alone (an island atlas reads n views of one square image, so most of its T texels are
    never read)."""
    sys_ = _ReadTexels(F, B)
    u0 = t0[sys_.cols]
    u = sys_.solve(y, u0, lam, iters, tol)
    return _finish(sys_, y, t0, u0, u)


def _finish(sys_: _ReadTexels, y, t0, u0, u) -> tuple[torch.Tensor, dict]:
    u, info = _finish_read(sys_, y, u0, u)
    t = torch.nan_to_num(t0, nan=0.5).clamp(0, 1)
    t[sys_.cols] = u
    return t, info


def _finish_read(sys_: _ReadTexels, y, u0, u) -> tuple[torch.Tensor, dict]:
    """The read texels' solution u [U, 3] made finite and clamped to [0, 1], and the training RMSE before / after."""
    rmse = lambda uu: float(((sys_.A(uu) - y) ** 2).mean().sqrt())  # noqa: E731
    u = torch.nan_to_num(u, nan=0.5).clamp(0, 1)
    return u, {"rmse_before": rmse(u0), "rmse_after": rmse(u), "pixels": int(y.shape[0])}


def choose_footprint_lambda(system: FootprintSystem, t0: torch.Tensor | None, lambdas: list[float],
                            iters: int = 100, tol: float = 1e-3, holdout: int = 4, sys_: _ReadTexels | None = None,
                            u0: torch.Tensor | None = None) -> tuple[float | None, dict[float, float]]:
    """The refit's λ for this scene: fit the texels on the views but every `holdout`-th (views holdout-1,
    2·holdout-1, ...) for each candidate in `lambdas`, and keep the one whose render of the held-out views' pixels
    is closest to them (display-colour PSNR). t0 [T, 3] the prior (linear light), or None with u0 [U, 3] the read
    texels' prior alone. Returns (λ, {λ: held-out PSNR}); (None, {}) when there are fewer than `holdout` views or no
    held-out pixel (nothing to choose by).
    Candidates are solved from the largest λ down, each starting from the previous answer, to a looser tolerance
    than the final solve (they are only compared, not kept)."""
    view = system.view
    n_views = int(view.max()) + 1 if view.numel() else 0
    held = (view % holdout) == holdout - 1
    if n_views < holdout or not bool(held.any()) or bool(held.all()) or not lambdas:
        return None, {}
    sys_ = sys_ or _ReadTexels(system.F, system.B)
    u0 = t0[sys_.cols] if u0 is None else u0
    fit = (~held).to(system.y.dtype)
    scores: dict[float, float] = {}
    u = None
    for lam in sorted(set(float(x) for x in lambdas), reverse=True):
        u = sys_.solve(system.y, u0, lam, iters, tol, weight=fit, start=u)
        scores[lam] = psnr(linear_to_srgb(sys_.A(u.clamp(0, 1))[held].clamp(0, 1)),
                           linear_to_srgb(system.y[held].clamp(0, 1)))  # display colours
    best = max(scores, key=lambda k: (scores[k], k))  # ties: the stronger pull
    return best, scores


@torch.no_grad()
def refit_texture_footprint(atlas, views: list[FootprintView], sub: int = 2, lam: float = 1.0,
                            iters: int = 100, lambdas: list[float] | None = None, tol: float = 1e-5,
                            lookup: str = "charts", k: int = LOOKUP_K) -> dict:
    """Replace atlas.textures by the footprint fit (kept in display space; texels no pixel reaches keep their
    kernel-texture colour, dilated as fit_atlas left them). With `lambdas` (two or more candidates), λ is chosen
    among them from held-out training views (choose_footprint_lambda), one candidate is used as it is, and `lam`
    when there are none or they cannot choose (fewer than 4 views).
    Returns info (pixels, RMSE before/after in linear light, the λ used, the held-out PSNR of each candidate);
    {'pixels': 0} when no view has a covered pixel. lookup, k: how the frames read the texels (footprint_system)."""
    system = footprint_system(atlas, views, sub, lookup=lookup, k=k)
    if system is None:
        return {"pixels": 0}
    n, R = atlas.n, atlas.layout.R
    # only the texels some pixel reads take part (an island atlas is n views of one image: most of its n R² texels
    # are never read); texel (c, row, col) is column (c R + row) R + col
    sys_ = _ReadTexels(system.F, system.B)
    chart, pix = sys_.cols // (R * R), sys_.cols % (R * R)
    tex = atlas.textures.detach()  # an island layout's one image [1, 3, R, R] (every chart reads it), else [n, ...]
    read = tex.view(3, R * R)[:, pix].T if atlas.islands else tex.view(n, 3, R * R)[chart, :, pix]
    u0 = srgb_to_linear(read.clamp(0, 1))  # [U, 3] linear light
    scores: dict[float, float] = {}
    if lambdas is not None and len(set(lambdas)) > 1:
        chosen, scores = choose_footprint_lambda(system, None, lambdas, iters, sys_=sys_, u0=u0)
        lam = lam if chosen is None else chosen
    elif lambdas:  # one candidate: that λ
        lam = float(lambdas[0])
    u, info = _finish_read(sys_, system.y, u0, sys_.solve(system.y, u0, lam, iters, tol))
    info = {**info, "lambda": float(lam)}
    if scores:
        info["holdout_psnr"] = {f"{k:g}": round(v, 3) for k, v in sorted(scores.items())}
    # texels no pixel reaches keep the kernel texture's dilated colour; an island layout keeps each pixel's owner's
    if atlas.islands:
        own = chart == atlas.layout.owner.to(chart.device).reshape(-1)[pix]
        tex.view(3, R * R)[:, pix[own]] = linear_to_srgb(u[own]).T
    else:
        tex.view(n, 3, R * R)[chart, :, pix] = linear_to_srgb(u)
    atlas.canonicalise_textures()
    return info
