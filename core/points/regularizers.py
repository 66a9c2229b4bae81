"""The paper's two geometry regularizers (Sec. 4.1), on foreground rays only.

close-to-ray      L = mean_i ‖x_i − Π_ray(x_i)‖      (points detached: only attention is pulled)
close-to-surface  L = mean_ij ‖p_ij − sg(x_i)‖       (x_i detached: only the neighbours move)
"""
from __future__ import annotations

import torch

from core.images.rays import distance_to_ray


def _masked_mean(v: torch.Tensor, mask: torch.Tensor) -> torch.Tensor:
    m = mask.to(v.dtype)
    return (v * m).sum() / m.sum().clamp_min(1.0)


def close_to_ray(att: dict, origins: torch.Tensor, dirs: torch.Tensor, fg_mask: torch.Tensor) -> torch.Tensor:
    """Close-to-ray loss. att: output of `PointModel.attend` (uses fg_weights [R, K], p [R, K, 3]);
    fg_mask [R] bool selects foreground rays. The neighbour positions are detached so that the gradient only
    sharpens/moves the attention, as in the reference cloth configuration."""
    x = (att["fg_weights"][..., None] * att["p"].detach()).sum(1)
    return _masked_mean(distance_to_ray(x, origins, dirs), fg_mask)


def close_to_surface(att: dict, fg_mask: torch.Tensor) -> torch.Tensor:
    """Close-to-surface loss: mean distance of every valid neighbour p_ij [R, K, 3] to the detached x_i."""
    x = att["x"].detach()
    d = (att["p"] - x[:, None, :]).norm(dim=-1)                       # [R, K]
    m = att["valid"] & fg_mask[:, None]
    return _masked_mean(d, m)
