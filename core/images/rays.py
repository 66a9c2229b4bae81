"""Ray maths shared by every stage: the projection of a point onto a ray and its distance from it."""
from __future__ import annotations

import torch


def project_on_ray(x: torch.Tensor, origins: torch.Tensor, dirs: torch.Tensor) -> torch.Tensor:
    """Orthogonal projection of x [R, 3] onto rays (origins [R, 3], unit dirs [R, 3]); t is clamped ≥ 0."""
    t = ((x - origins) * dirs).sum(-1, keepdim=True).clamp_min(0.0)
    return origins + t * dirs


def distance_to_ray(x: torch.Tensor, origins: torch.Tensor, dirs: torch.Tensor) -> torch.Tensor:
    """‖x − Π(x)‖ per ray: [R]. Uses the perpendicular component directly (no cancellation for far points)."""
    rel = x - origins
    perp = rel - (rel * dirs).sum(-1, keepdim=True) * dirs
    return perp.norm(dim=-1)
