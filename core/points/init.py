"""Initial points: random samples inside the visual hull carved from the training views' alpha masks.

Uses the images' alpha (which every NeRF-synthetic dataset carries) instead of a random box: the points start on
or inside the object, so training spends its minutes on appearance and detail rather than on finding the object.
"""
from __future__ import annotations

import torch
import torch.nn.functional as F

from core.images.cameras import Intrinsics, project_points
from core.util.errors import DataError


def scene_radius(c2w: torch.Tensor, focal, width: int) -> float:
    """Half-size of the region every camera sees around the origin: distance × tan(half the horizontal fov).
    focal in pixels or Intrinsics (the wider side of the principal point: an off-centre camera may look at the
    object off-axis)."""
    dist = c2w[:, :3, 3].norm(dim=-1).min()
    if isinstance(focal, Intrinsics):
        return float(dist * (max(focal.cx, width - focal.cx) / focal.fx))
    return float(dist * (0.5 * width / focal))


def visual_hull_points(alphas: torch.Tensor, c2w: torch.Tensor, focal: float, n: int, seed: int = 0,
                       dilate_px: int = 1, agree: float = 0.9, max_rounds: int = 40,
                       batch: int = 200_000) -> torch.Tensor:
    """Sample n points inside the visual hull.

    Args: alphas [V, H, W] in [0, 1], c2w [V, 4, 4]. A candidate is kept when it projects onto foreground
    (alpha > 0.5 after a `dilate_px` dilation, so thin parts survive pixel discretisation) in at least `agree` of
    the views that see it (not all: a thin sheet seen exactly edge-on vanishes from a view). Returns [n, 3].
    """
    v, h, w = alphas.shape
    g = torch.Generator().manual_seed(seed)
    radius = scene_radius(c2w, focal, w)
    fg = (alphas > 0.5).float()[:, None]
    if dilate_px > 0:
        fg = F.max_pool2d(fg, 2 * dilate_px + 1, stride=1, padding=dilate_px)
    fg = fg[:, 0] > 0.5                                                      # [V, H, W]
    kept = []
    total = 0
    for _ in range(max_rounds):
        cand = (torch.rand(batch, 3, generator=g) * 2 - 1) * radius
        votes = torch.zeros(batch)
        seen = torch.zeros(batch)
        for i in range(v):
            px, depth = project_points(cand, c2w[i].float(), h, w, focal)
            col, row = px[:, 0].floor().long(), px[:, 1].floor().long()
            inside = (depth > 0) & (col >= 0) & (col < w) & (row >= 0) & (row < h)
            hit = torch.zeros(batch, dtype=torch.bool)
            hit[inside] = fg[i, row[inside], col[inside]]
            seen += inside.float()
            votes += hit.float()
        ok = (seen > 0) & (votes >= agree * seen)
        kept.append(cand[ok])
        total += int(ok.sum())
        if total >= n:
            break
    xyz = torch.cat(kept)
    if xyz.shape[0] == 0:
        raise DataError("no 3-D point projects onto the foreground of the training views: check that the images "
                        "have an alpha channel with the object opaque and that the cameras look at the object")
    if xyz.shape[0] < n:  # very thin hull: fill up by jittering what we found
        extra = xyz[torch.randint(xyz.shape[0], (n - xyz.shape[0],), generator=g)]
        xyz = torch.cat([xyz, extra + 1e-3 * radius * torch.randn(extra.shape, generator=g)])
    return xyz[torch.randperm(xyz.shape[0], generator=g)[:n]].float()
