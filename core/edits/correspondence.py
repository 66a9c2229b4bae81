"""Canonical correspondence (paper Sec. 4.3): where in canonical space does a deformed-space ray hit?

deform-aware (the paper's):  x_def = Π_ray(x̂_def);  t_i = Σ_j a_ij (p_can_ij − p_def_ij);  x_can = x_def + t_i
naive (ablation):            x_can = Σ_j a_ij p_can_ij
deform-gradient (beyond the paper): x_can = Σ_j a_ij (p_can_ij + F_ij⁻¹ (x_def − p_def_ij)), with F the points'
                             local deformation gradients (core/edits/deformation.py): each neighbour maps the
                             ray's surface point back through its own local affine map, so local rotations and
                             stretches are undone, not only translations (F = I gives deform-aware).
a_ij are the deformed-space attention weights over the K neighbours (background slot dropped, renormalised).

`ray_canonical_points` is the one place a traced frame's rays get their canonical surface points (the edited
render, the add-on's paint transfer and the edit evaluation all call it); `canonical_points` is its arithmetic.

Fold rejection (beyond the paper, `fold_radius`): a ray's neighbours can come from two parts of the surface that
the pose brought together on screen (the two sides of a joint's fold, a part swung behind another). Their
displacements p_can − p_def differ by about their canonical distance, so even a small attention weight on the
other part drags the lookup far across the texture. With fold_radius, only neighbours whose displacement lies
within fold_radius of that of the ray's most-attended neighbour are kept (weights renormalised over them, and x̂
recomputed from them). At rest and under a rigid translation every displacement is the same: nothing is dropped.
"""
from __future__ import annotations

import math

import numpy as np
import torch

from core.images.rays import project_on_ray
from core.points.trace import Trace

try:  # optional: the torch path does the same work without it
    import numba
except ImportError:  # pragma: no cover - exercised only where numba is missing
    numba = None

MODES = ("deform-aware", "naive", "deform-gradient")
BACKENDS = ("auto", "torch", "compiled")


def canonical_points(fg_weights: torch.Tensor, idx: torch.Tensor, x_hat: torch.Tensor, origins: torch.Tensor,
                     dirs: torch.Tensor, p_def: torch.Tensor, p_can: torch.Tensor,
                     mode: str = "deform-aware", inv_f: torch.Tensor | None = None,
                     fold_radius: float | None = None, fold_inv_f: torch.Tensor | None = None,
                     backend: str = "auto") -> torch.Tensor:
    """Canonical lookup points x_can [R, 3].

    Args: fg_weights [R, K] attention over neighbours (rows sum to 1 where any neighbour exists), idx [R, K]
    (-1 = empty slot), x_hat [R, 3] deformed surface points Σ a p_def, origins/dirs [R, 3] (unit dirs),
    p_def [M, 3] deformed positions, p_can [M, 3] canonical positions of the same points (row j of both is the
    same point; with ids: p_can = canonical_xyz[ids]); inv_f [M, 3, 3] inverse deformation gradients of the
    points (needed by mode "deform-gradient"); fold_radius: keep only the neighbours whose displacement
    p_can − p_def lies within this distance (world units) of the most-attended neighbour's (None or inf: all);
    fold_inv_f [M, 3, 3]: the fold rule compares each neighbour's own estimate of the ray's canonical point,
    p_can + fold_inv_f (x_def − p_def), instead of its displacement (see `_fold_reject`).
    backend: "compiled" (one numba pass per ray: the displacement fold rule and the naive, deform-aware or
    deform-gradient sum, CPU tensors; with fold_inv_f the fold rule stays in torch and the sum is compiled),
    "torch", or "auto" (compiled where it can run). Both give the same numbers to float rounding
    (tests/core/edits/test_correspondence.py).
    """
    if mode not in MODES:
        raise ValueError(f"correspondence must be one of {MODES}, got {mode!r}")
    if backend not in BACKENDS:
        raise ValueError(f"correspondence backend must be one of {BACKENDS}, got {backend!r}")
    fold = fold_radius is not None and fold_radius < float("inf") and idx.shape[1] > 0
    if mode == "deform-gradient" and inv_f is None:
        raise ValueError("correspondence 'deform-gradient' needs the points' inverse deformation gradients inv_f")
    gradient = inv_f if mode == "deform-gradient" else None
    can_compile = (numba is not None and all(t.device.type == "cpu" for t in (fg_weights, idx, x_hat, p_def, p_can))
                   and (gradient is None or gradient.device.type == "cpu"))
    if backend == "compiled" and not can_compile:
        raise ValueError("correspondence backend 'compiled' needs numba and CPU tensors; use 'auto' or 'torch'")
    compiled = backend != "torch" and can_compile
    if compiled and not (fold and fold_inv_f is not None):
        return _canonical_compiled(fg_weights, idx, x_hat, origins, dirs, p_def, p_can, mode == "naive",
                                   float(fold_radius) if fold else None, gradient)
    w = fg_weights * (idx >= 0)
    safe = idx.clamp_min(0)
    disp = None  # the neighbours' displacements p_can − p_def [R, K, 3], once gathered
    if fold:
        local = None
        if fold_inv_f is not None:  # each neighbour's estimate of the canonical point, through its local map
            off = project_on_ray(x_hat, origins, dirs)[:, None, :] - p_def[safe]
            local = p_can[safe] + (fold_inv_f[safe] @ off[..., None]).squeeze(-1)        # [R, K, 3]
        else:
            disp = (p_can - p_def)[safe]
        w, x_hat = _fold_reject(w, idx, safe, x_hat, p_def, p_can, float(fold_radius), local, disp)
        if compiled:  # the sum as without the rule (rows it left whole: the same numbers)
            return _canonical_compiled(w, idx, x_hat, origins, dirs, p_def, p_can, mode == "naive", None, gradient)
    if mode == "naive":
        return (w[..., None] * p_can[safe]).sum(1)
    x_def = project_on_ray(x_hat, origins, dirs)
    if mode == "deform-gradient":
        off = x_def[:, None, :] - p_def[safe]                                   # [R, K, 3]
        back = (inv_f[safe] @ off[..., None]).squeeze(-1)
        # rows whose weights do not sum to one keep the rest at x_def, as the deform-aware sum does
        return (w[..., None] * (p_can[safe] + back)).sum(1) + (1.0 - w.sum(1, keepdim=True)) * x_def
    if disp is None:
        disp = p_can[safe] - p_def[safe]
    return x_def + (w[..., None] * disp).sum(1)


def ray_canonical_points(trace: Trace, sel: torch.Tensor | None = None, p_def: torch.Tensor | None = None,
                         p_can: torch.Tensor | None = None, mode: str = "deform-aware",
                         inv_f: torch.Tensor | None = None, fold_radius: float | None = None,
                         fold_inv_f: torch.Tensor | None = None) -> torch.Tensor:
    """Canonical surface points [S, 3] of the rays `sel` of a traced frame.

    trace: `trace_frame` of the points p_def [M, 3]; sel: [S] ray indices (or an [R] bool mask with S set; None:
    all R rays);
    p_can [M, 3] the canonical positions of the same points; mode, inv_f [M, 3, 3] and fold_radius as
    `canonical_points`, and fold_inv_f.
    p_def None: nothing moved, so the canonical point is the ray's surface point projected on its ray, Π(x̂), as
    the atlas saw it while fitting. Non-finite rows of p_def (a broken rig) enter the arithmetic as 0, as in
    `trace_frame` (no ray selects them as a neighbour). The result can be non-finite where the correspondence
    breaks down (e.g. a singular inv_f); what such rays become is the caller's choice.
    """
    if sel is None:
        sel = slice(None)
    x_hat, origins, dirs = trace.x[sel], trace.origins[sel], trace.dirs[sel]
    if p_def is None:
        return project_on_ray(x_hat, origins, dirs)
    if p_can is None:
        raise ValueError("ray_canonical_points: p_def was given without p_can (the canonical positions)")
    pts = torch.nan_to_num(p_def, nan=0.0, posinf=0.0, neginf=0.0)
    return canonical_points(trace.fg_weights[sel], trace.idx[sel], x_hat, origins, dirs, pts, p_can, mode,
                            inv_f=inv_f, fold_radius=fold_radius, fold_inv_f=fold_inv_f)


def _fold_reject(w: torch.Tensor, idx: torch.Tensor, safe: torch.Tensor, x_hat: torch.Tensor, p_def: torch.Tensor,
                 p_can: torch.Tensor, radius: float, local: torch.Tensor | None = None,
                 disp: torch.Tensor | None = None) -> tuple[torch.Tensor, torch.Tensor]:
    """Weights [R, K] over the neighbours whose displacement lies within `radius` of that of each ray's
    most-attended one, renormalised to the row's old sum, and x̂ [R, 3] recomputed from them (rows the rule left
    whole unchanged). local [R, K, 3]: compare these per-neighbour canonical estimates instead of the
    displacements (under any affine map of one part they agree exactly: a uniform stretch or a rotation drops
    nothing; a part the pose brought there from elsewhere still disagrees by about its canonical distance).
    disp [R, K, 3]: the neighbours' displacements p_can − p_def when the caller has gathered them."""
    slot = w.argmax(1, keepdim=True)                                             # [R, 1]
    if local is not None:
        dist = (local - local.gather(1, slot[..., None].expand(-1, 1, 3))).norm(dim=-1)      # [R, K]
    else:
        if disp is None:
            disp = (p_can - p_def)[safe]                                         # [R, K, 3]
        dist = (disp - disp.gather(1, slot[..., None].expand(-1, 1, 3))).norm(dim=-1)  # [R, K]
    keep = (idx >= 0) & ~(dist > radius)  # NaN positions: kept, as without the rule
    kept = w * keep
    total, left = w.sum(1, keepdim=True), kept.sum(1, keepdim=True)
    ok = left > 0
    dropped = ok & (kept != w).any(1, keepdim=True)  # rows the rule changed; the others stay bit-identical
    kept = torch.where(dropped, kept * (total / left.clamp_min(1e-30)), w)
    rows = torch.nonzero(dropped.squeeze(1)).squeeze(1)
    x_new = x_hat.clone()
    kr = kept[rows]
    x_new[rows] = (kr[..., None] * p_def[safe[rows]]).sum(1) / kr.sum(1, keepdim=True).clamp_min(1e-30)
    return kept, x_new


def _canonical_loop(w_in, idx, x_hat, o, d, p_def, p_can, disp, naive, fold, radius, gradient, inv_f, out):
    """The compiled path of `canonical_points` (every mode, the displacement fold rule): per ray,
    the weights w = fg · (idx ≥ 0); with fold, the neighbours whose displacement disp = p_can − p_def lies farther
    than radius from that of the most-attended one (the first maximum) dropped, the rest scaled back to the row's
    sum and x̂ recomputed from them (rows that drop nothing, or would drop everything, are left as they are); then
    Σ w p_can (naive), Π_ray(x̂) + Σ w disp (deform-aware) or, with gradient,
    Σ w (p_can + inv_f (x_def − p_def)) + (1 − Σ w) x_def, x_def = Π_ray(x̂) (deform-gradient; inv_f [M, 3, 3]).
    float32 inputs, out [R, 3] float32; the torch path's float32 steps (sums in neighbour order; the radius test on
    squared lengths)."""
    f32 = np.float32
    r_n, k = idx.shape
    w = np.empty(k, dtype=np.float32)
    keep = np.empty(k, dtype=np.bool_)
    r2 = radius * radius
    for r in range(r_n):
        total = f32(0.0)
        best = 0
        for j in range(k):
            w[j] = w_in[r, j] if idx[r, j] >= 0 else f32(0.0)
            total += w[j]
            if w[j] > w[best]:
                best = j
        xx, xy, xz = x_hat[r, 0], x_hat[r, 1], x_hat[r, 2]
        if fold:
            qb = idx[r, best] if idx[r, best] >= 0 else 0
            bx, by, bz = disp[qb, 0], disp[qb, 1], disp[qb, 2]
            left = f32(0.0)
            dropped = False
            for j in range(k):
                q = idx[r, j]
                keep[j] = False
                if q < 0:
                    continue
                ex, ey, ez = disp[q, 0] - bx, disp[q, 1] - by, disp[q, 2] - bz
                keep[j] = not (ex * ex + ey * ey + ez * ez > r2)  # NaN: kept, as in the torch path
                if keep[j]:
                    left += w[j]
                elif w[j] != f32(0.0):
                    dropped = True
            if dropped and left > f32(0.0):
                scale = total / max(left, f32(1e-30))
                sx, sy, sz, sw = f32(0.0), f32(0.0), f32(0.0), f32(0.0)
                for j in range(k):
                    if keep[j]:
                        q = idx[r, j]
                        w[j] = w[j] * scale
                        sx += w[j] * p_def[q, 0]
                        sy += w[j] * p_def[q, 1]
                        sz += w[j] * p_def[q, 2]
                        sw += w[j]
                    else:
                        w[j] = f32(0.0)
                sw = max(sw, f32(1e-30))
                xx, xy, xz = sx / sw, sy / sw, sz / sw
        dx, dy, dz = f32(0.0), f32(0.0), f32(0.0)
        if not naive:  # x_def = Π_ray(x̂)
            t = (xx - o[r, 0]) * d[r, 0] + (xy - o[r, 1]) * d[r, 1] + (xz - o[r, 2]) * d[r, 2]
            if not t > f32(0.0):  # clamped at 0 (NaN stays NaN)
                t = t if t != t else f32(0.0)
            dx, dy, dz = o[r, 0] + t * d[r, 0], o[r, 1] + t * d[r, 1], o[r, 2] + t * d[r, 2]
        if gradient:
            ax, ay, az, sw = f32(0.0), f32(0.0), f32(0.0), f32(0.0)
            for j in range(k):
                q = idx[r, j]
                if q < 0:
                    q = 0  # its weight is 0, as the torch path's clamped index
                ex, ey, ez = dx - p_def[q, 0], dy - p_def[q, 1], dz - p_def[q, 2]
                ax += w[j] * (p_can[q, 0] + (inv_f[q, 0, 0] * ex + inv_f[q, 0, 1] * ey + inv_f[q, 0, 2] * ez))
                ay += w[j] * (p_can[q, 1] + (inv_f[q, 1, 0] * ex + inv_f[q, 1, 1] * ey + inv_f[q, 1, 2] * ez))
                az += w[j] * (p_can[q, 2] + (inv_f[q, 2, 0] * ex + inv_f[q, 2, 1] * ey + inv_f[q, 2, 2] * ez))
                sw += w[j]
            rest = f32(1.0) - sw
            out[r, 0], out[r, 1], out[r, 2] = ax + rest * dx, ay + rest * dy, az + rest * dz
            continue
        ax, ay, az = f32(0.0), f32(0.0), f32(0.0)
        for j in range(k):
            q = idx[r, j]
            if q < 0:
                q = 0  # its weight is 0, as the torch path's clamped index
            if naive:
                ax += w[j] * p_can[q, 0]
                ay += w[j] * p_can[q, 1]
                az += w[j] * p_can[q, 2]
            else:
                ax += w[j] * disp[q, 0]
                ay += w[j] * disp[q, 1]
                az += w[j] * disp[q, 2]
        if naive:
            out[r, 0], out[r, 1], out[r, 2] = ax, ay, az
        else:
            out[r, 0], out[r, 1], out[r, 2] = dx + ax, dy + ay, dz + az


_compiled_canonical = None


def _canonical_compiled(fg_weights, idx, x_hat, origins, dirs, p_def, p_can, naive: bool,
                        radius: float | None, inv_f: torch.Tensor | None = None) -> torch.Tensor:
    """canonical_points through the compiled loop (`_canonical_loop`): x_can [R, 3] in x_hat's dtype; inv_f
    [M, 3, 3]: the deform-gradient sum."""
    global _compiled_canonical
    if _compiled_canonical is None:
        try:
            _compiled_canonical = numba.njit(cache=True, nogil=True)(_canonical_loop)
        except RuntimeError:  # no writable cache location: compile per process
            _compiled_canonical = numba.njit(cache=False, nogil=True)(_canonical_loop)

    def f32(t):
        return np.ascontiguousarray(t.detach().to(torch.float32).numpy())

    r = idx.shape[0]
    out = np.empty((r, 3), dtype=np.float32)
    if r:
        pd, pc = f32(p_def), f32(p_can)
        _compiled_canonical(f32(fg_weights), np.ascontiguousarray(idx.detach().to(torch.int64).numpy()), f32(x_hat),
                            f32(origins), f32(dirs), pd, pc, pc - pd, bool(naive), radius is not None,
                            np.float32(0.0 if radius is None else min(radius, 1e18)), inv_f is not None,
                            np.zeros((1, 3, 3), np.float32) if inv_f is None else f32(inv_f), out)
    return torch.from_numpy(out).to(x_hat.dtype)
