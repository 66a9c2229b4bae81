"""How well the attention's surface points x_i describe the surface (the paper's two regularizer claims).

- ray distance: mean ‖x_i − Π_ray(x_i)‖ over foreground rays (close-to-ray should lower it);
- neighbour spread: mean over foreground rays of the attention-weighted ‖p_ij − x_i‖ (close-to-surface should
  lower it: the selected neighbours gather around the surface point);
- mask IoU of the rendered foreground (1 − background weight > 0.5) against the ground-truth alpha.
"""
from __future__ import annotations

import torch

from core.images.rays import distance_to_ray
from core.points.model import PointModel
from core.points.render import trace_frame


@torch.no_grad()
def surface_stats(model: PointModel, split, views) -> dict:
    """split: SplitData; views: indices. Returns the three statistics averaged over the foreground rays."""
    dist_sum = spread_sum = 0.0
    n_fg = 0
    inter = union = 0
    for i in views:
        tr = trace_frame(model, split.c2w[i], split.height, split.width, split.focal)
        gt_fg = (split.alphas[i].reshape(-1) > 0.5).to(tr.x.device)
        pred_fg = tr.fg > 0.5
        inter += int((gt_fg & pred_fg).sum())
        union += int((gt_fg | pred_fg).sum())
        sel = gt_fg & pred_fg
        if not bool(sel.any()):
            continue
        x = tr.x[sel]
        dist_sum += float(distance_to_ray(x, tr.origins[sel], tr.dirs[sel]).sum())
        idx = tr.idx[sel]
        p = model.xyz[idx.clamp_min(0)]
        w = tr.fg_weights[sel] * (idx >= 0)
        spread = (w * (p - x[:, None, :]).norm(dim=-1)).sum(1) / w.sum(1).clamp_min(1e-12)
        spread_sum += float(spread.sum())
        n_fg += int(sel.sum())
    n = max(n_fg, 1)
    return {"ray_distance": dist_sum / n, "neighbour_spread": spread_sum / n,
            "mask_iou": inter / max(union, 1), "foreground_rays": n_fg}
