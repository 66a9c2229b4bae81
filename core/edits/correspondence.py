"""Canonical correspondence (paper Sec. 4.3): where in canonical space does a deformed-space ray hit?

deform-aware (the paper's):  x_def = Π_ray(x̂_def);  t_i = Σ_j a_ij (p_can_ij − p_def_ij);  x_can = x_def + t_i
naive (ablation):            x_can = Σ_j a_ij p_can_ij
deform-gradient (beyond the paper): x_can = Σ_j a_ij (p_can_ij + F_ij⁻¹ (x_def − p_def_ij)), with F the points'
                             local deformation gradients (core/edits/deformation.py): each neighbour maps the
                             ray's surface point back through its own local affine map, so local rotations and
                             stretches are undone, not only translations (F = I gives deform-aware).
a_ij are the deformed-space attention weights over the K neighbours (background slot dropped, renormalised).

Fold rejection (beyond the paper, `fold_radius`): a ray's neighbours can come from two parts of the surface that
the pose brought together on screen (the two sides of a joint's fold, a part swung behind another). Their
displacements p_can − p_def differ by about their canonical distance, so even a small attention weight on the
other part drags the lookup far across the texture. With fold_radius, only neighbours whose displacement lies
within fold_radius of that of the ray's most-attended neighbour are kept (weights renormalised over them, and x̂
recomputed from them). At rest and under a rigid translation every displacement is the same: nothing is dropped.
"""
from __future__ import annotations

import torch

from core.images.rays import project_on_ray

MODES = ("deform-aware", "naive", "deform-gradient")


def canonical_points(fg_weights: torch.Tensor, idx: torch.Tensor, x_hat: torch.Tensor, origins: torch.Tensor,
                     dirs: torch.Tensor, p_def: torch.Tensor, p_can: torch.Tensor,
                     mode: str = "deform-aware", inv_f: torch.Tensor | None = None,
                     fold_radius: float | None = None) -> torch.Tensor:
    """Canonical lookup points x_can [R, 3].

    Args: fg_weights [R, K] attention over neighbours (rows sum to 1 where any neighbour exists), idx [R, K]
    (-1 = empty slot), x_hat [R, 3] deformed surface points Σ a p_def, origins/dirs [R, 3] (unit dirs),
    p_def [M, 3] deformed positions, p_can [M, 3] canonical positions of the same points (row j of both is the
    same point; with ids: p_can = canonical_xyz[ids]); inv_f [M, 3, 3] inverse deformation gradients of the
    points (needed by mode "deform-gradient"); fold_radius: keep only the neighbours whose displacement
    p_can − p_def lies within this distance (world units) of the most-attended neighbour's (None or inf: all).
    """
    if mode not in MODES:
        raise ValueError(f"correspondence must be one of {MODES}, got {mode!r}")
    w = fg_weights * (idx >= 0)
    safe = idx.clamp_min(0)
    if fold_radius is not None and fold_radius < float("inf") and w.shape[1]:
        w, x_hat = _fold_reject(w, idx, safe, x_hat, p_def, p_can, float(fold_radius))
    if mode == "naive":
        return (w[..., None] * p_can[safe]).sum(1)
    x_def = project_on_ray(x_hat, origins, dirs)
    if mode == "deform-gradient":
        if inv_f is None:
            raise ValueError("correspondence 'deform-gradient' needs the points' inverse deformation gradients inv_f")
        off = x_def[:, None, :] - p_def[safe]                                   # [R, K, 3]
        back = (inv_f[safe] @ off[..., None]).squeeze(-1)
        # rows whose weights do not sum to one keep the rest at x_def, as the deform-aware sum does
        return (w[..., None] * (p_can[safe] + back)).sum(1) + (1.0 - w.sum(1, keepdim=True)) * x_def
    disp = (w[..., None] * (p_can[safe] - p_def[safe])).sum(1)
    return x_def + disp


def _fold_reject(w: torch.Tensor, idx: torch.Tensor, safe: torch.Tensor, x_hat: torch.Tensor, p_def: torch.Tensor,
                 p_can: torch.Tensor, radius: float) -> tuple[torch.Tensor, torch.Tensor]:
    """Weights [R, K] over the neighbours whose displacement lies within `radius` of that of each ray's
    most-attended one, renormalised to the row's old sum, and x̂ [R, 3] recomputed from them (rows the rule left
    whole unchanged)."""
    anchor = safe.gather(1, w.argmax(1, keepdim=True))                          # [R, 1]
    disp = p_can - p_def                                                        # [M, 3]
    dist = (disp[safe] - disp[anchor]).norm(dim=-1)                             # [R, K]
    keep = (idx >= 0) & ~(dist > radius)  # NaN positions: kept, as without the rule
    kept = w * keep
    total, left = w.sum(1, keepdim=True), kept.sum(1, keepdim=True)
    ok = left > 0
    dropped = ok & (kept != w).any(1, keepdim=True)  # rows the rule changed; the others stay bit-identical
    kept = torch.where(dropped, kept * (total / left.clamp_min(1e-30)), w)
    x_new = (kept[..., None] * p_def[safe]).sum(1) / kept.sum(1, keepdim=True).clamp_min(1e-30)
    return kept, torch.where(dropped, x_new, x_hat)
