"""Occlusion between parts of a posed surface (beyond the paper): which of the layers a ray's neighbours come from
is in front.

The proximity attention orders what a ray sees by a depth feature measured from the ray's nearest neighbour. A
model learns that ordering only for the layers its training views showed: a single sheet (the cloth) never saw
one part of itself behind another, and its key network weighs points 5 or 20 spacings behind the nearest
neighbour about alike. When a pose folds the sheet (an armature joint), a ray's K neighbours hold points of two or
three parts of the surface — the one in front, the one folded behind it, an edge of a third passing beside the ray
— and the attention mixes their colours by how many points each brings.

The rule sorts a ray's neighbours into layers by the points' own local maps and keeps the front one. Neighbour l
belongs to the layer of neighbour m when m's local deformation predicts l's position from their canonical offset:

    |F_m⁻¹ (p_l − p_m) − (c_l − c_m)| ≤ alpha · |c_l − c_m| + beta · spacing

(p deformed, c canonical positions, F the local deformation gradient, core/edits/deformation.py). This holds for
any neighbours of one part however it was rotated, stretched or squashed (exactly for an affine map, up to the
map's change over their distance otherwise) and fails for points of another part, whose canonical offset is
unrelated to their deformed one. Walking the neighbours front to back along the ray, the first whose layer holds
at least `min_share` of the ray's attention is the visible surface: neighbours behind it that are not in its
layer get weight 0, and the weights left are scaled back to the ray's foreground weight (coverage unchanged, the
colour and the surface point x̂ taken from the front layer). Layers with less weight in front of it (an edge
passing beside the ray) are kept as they are.

At rest, under a rigid motion or any affine map every neighbour is in every other's layer: nothing changes (rows
the rule leaves whole stay bit-identical).
"""
from __future__ import annotations

import dataclasses

import torch

from core.points.trace import Trace


@torch.no_grad()
def front_layer(trace: Trace, points: torch.Tensor, p_can: torch.Tensor, inv_f: torch.Tensor, spacing: float,
                alpha: float = 0.5, beta: float = 2.0, min_share: float = 0.25, chunk: int = 2048) -> Trace:
    """The trace with each ray's attention restricted to its front layer (module doc).

    trace: `trace_frame` of `points`; points [M, 3] deformed positions (non-finite rows are never neighbours),
    p_can [M, 3] their canonical positions, inv_f [M, 3, 3] the inverse local deformation gradients (finite,
    bounded: `EditState.inv_f`); spacing: the model's point spacing (world units); alpha, beta: the layer test's
    relative and absolute tolerance (beta in spacings); min_share: the share of a ray's foreground weight a layer
    needs to count as its visible surface. Returns a Trace whose weights, fg_weights and x changed only on rays
    where a layer was dropped (bg unchanged).
    """
    idx, w = trace.idx, trace.fg_weights
    r_n, k = idx.shape
    if r_n == 0 or k < 2:
        return trace
    valid = (idx >= 0) & trace.active[:, None]
    safe = idx.clamp_min(0)
    pts = torch.nan_to_num(points.to(torch.float32), nan=0.0, posinf=0.0, neginf=0.0)
    can = p_can.to(torch.float32)
    fi = inv_f.to(torch.float32)
    tol_abs = float(beta) * float(spacing)
    # cheap screen: a ray needs the full test only when some attended neighbour fails the test against its
    # most-attended one (a ray inside one part passes everywhere)
    anchor = safe.gather(1, w.argmax(1, keepdim=True)).squeeze(1)                        # [R]
    dp = pts[safe] - pts[anchor][:, None, :]
    dc = can[safe] - can[anchor][:, None, :]
    res = ((fi[anchor][:, None] @ dp[..., None]).squeeze(-1) - dc).norm(dim=-1)
    odd = valid & (res > alpha * dc.norm(dim=-1) + tol_abs) & (w > 0)
    rows = torch.nonzero(odd.any(1)).squeeze(1)
    if rows.numel() == 0:
        return trace
    new_w, new_fg, new_x = trace.weights.clone(), trace.fg_weights.clone(), trace.x.clone()
    depth_all = ((pts[safe] - trace.origins[:, None, :]) * trace.dirs[:, None, :]).sum(-1)  # [R, K]
    for s in range(0, rows.numel(), chunk):
        rr = rows[s:s + chunk]
        ix, vv, ww = safe[rr], valid[rr], w[rr] * valid[rr]
        p, c, g = pts[ix], can[ix], fi[ix]                                                    # [B, K, ...]
        # layer[b, m, l]: l is in m's layer
        dpp = p[:, None, :, :] - p[:, :, None, :]                                             # [B, m, l, 3]
        dcc = c[:, None, :, :] - c[:, :, None, :]
        pred = torch.einsum("bmij,bmlj->bmli", g, dpp)
        layer = (pred - dcc).norm(dim=-1) <= alpha * dcc.norm(dim=-1) + tol_abs
        layer &= vv[:, None, :] & vv[:, :, None]
        mass = (layer * ww[:, None, :]).sum(-1)                                               # [B, m]
        total = ww.sum(1)
        t = depth_all[rr].masked_fill(~vv, float("inf"))
        order = t.argsort(1)                                                                  # front to back
        enough = (mass.gather(1, order) >= min_share * total[:, None]) & vv.gather(1, order)
        has = enough.any(1)
        first = order.gather(1, enough.to(torch.int8).argmax(1, keepdim=True)).squeeze(1)     # [B]
        b = torch.arange(rr.numel(), device=idx.device)
        keep = layer[b, first] | (t <= t[b, first][:, None])                                  # in front: kept
        keep = torch.where(has[:, None], keep, torch.ones_like(keep)) | ~vv
        kept = ww * keep
        left = kept.sum(1)
        changed = has & (left > 0) & (kept != ww).any(1)
        if not bool(changed.any()):
            continue
        rc, kc = rr[changed], kept[changed]
        fg = kc / left[changed][:, None]
        fg_total = 1.0 - trace.bg[rc]
        new_fg[rc] = fg
        new_w[rc] = fg * fg_total[:, None]
        new_x[rc] = (fg[..., None] * pts[safe[rc]]).sum(1)
    return dataclasses.replace(trace, weights=new_w, fg_weights=new_fg, x=new_x)
