"""Canonical correspondence (paper Sec. 4.3): where in canonical space does a deformed-space ray hit?

deform-aware (the paper's):  x_def = Π_ray(x̂_def);  t_i = Σ_j a_ij (p_can_ij − p_def_ij);  x_can = x_def + t_i
naive (ablation):            x_can = Σ_j a_ij p_can_ij
a_ij are the deformed-space attention weights over the K neighbours (background slot dropped, renormalised).
"""
from __future__ import annotations

import torch

from core.images.rays import project_on_ray

MODES = ("deform-aware", "naive")


def canonical_points(fg_weights: torch.Tensor, idx: torch.Tensor, x_hat: torch.Tensor, origins: torch.Tensor,
                     dirs: torch.Tensor, p_def: torch.Tensor, p_can: torch.Tensor,
                     mode: str = "deform-aware") -> torch.Tensor:
    """Canonical lookup points x_can [R, 3].

    Args: fg_weights [R, K] attention over neighbours (rows sum to 1 where any neighbour exists), idx [R, K]
    (-1 = empty slot), x_hat [R, 3] deformed surface points Σ a p_def, origins/dirs [R, 3] (unit dirs),
    p_def [M, 3] deformed positions, p_can [M, 3] canonical positions of the same points (row j of both is the
    same point; with ids: p_can = canonical_xyz[ids]).
    """
    if mode not in MODES:
        raise ValueError(f"correspondence must be one of {MODES}, got {mode!r}")
    w = fg_weights * (idx >= 0)
    safe = idx.clamp_min(0)
    if mode == "naive":
        return (w[..., None] * p_can[safe]).sum(1)
    x_def = project_on_ray(x_hat, origins, dirs)
    disp = (w[..., None] * (p_can[safe] - p_def[safe])).sum(1)
    return x_def + disp
