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
passing beside the ray) are kept as they are. That is `front_layer`; the edited render (`EditState.visible_layer`,
core/frames/edited.py) goes further with `front_anchors` and `unoccluded`: such a ray's neighbours are searched
again (when the neighbours it hides hold more than `REDO_MIN_HIDDEN` of the ray's weight) and the first K
candidates the front layer does not hide replace them, so hidden points take no neighbour slot either
(docs/editing.md measures both).

At rest, under a rigid motion or any affine map every neighbour is in every other's layer: nothing changes (rows
the rule leaves whole stay bit-identical).

Cost: a ray inside one part passes a cheap screen (each neighbour against its most-attended one) and is left
alone; only rays with neighbours of another part walk their layers. The walk (over the whole frame's arrays) and
the choice of candidates are compiled loops on a CPU (numba, like core/points/attention_compiled.py), torch
elsewhere; both give the same kept neighbours and candidates (tests/core/edits/test_occlusion.py). The second
search reuses the frame's screen index (core/points/neighbors/select.py `screen_index`).
"""
from __future__ import annotations

import dataclasses
import math

import numpy as np
import torch

from core.points.trace import Trace
from core.util.jit import njit

try:  # optional: the torch path is used without it
    import numba
except ImportError:  # pragma: no cover - exercised only where numba is missing
    numba = None

BACKENDS = ("auto", "torch", "compiled")


def _compiled(backend: str, device: torch.device) -> bool:
    """Whether the compiled loops run for `backend` ("auto": where numba is there and the tensors are on the CPU);
    ValueError for an unknown backend, or "compiled" where it cannot run."""
    if backend not in BACKENDS:
        raise ValueError(f"occlusion backend must be one of {BACKENDS}, got {backend!r}")
    compiled = backend != "torch" and numba is not None and device.type == "cpu"
    if backend == "compiled" and not compiled:
        raise ValueError("occlusion backend 'compiled' needs numba and a CPU device; use 'auto' or 'torch'")
    return compiled


def _f32(t: torch.Tensor) -> np.ndarray:
    """t as a contiguous float32 numpy array on the CPU (what the compiled loops take)."""
    return np.ascontiguousarray(t.detach().to("cpu", torch.float32).numpy())


def _i64(t: torch.Tensor) -> np.ndarray:
    """t as a contiguous int64 numpy array on the CPU."""
    return np.ascontiguousarray(t.detach().to("cpu", torch.int64).numpy())
# The edited render searches a ray again only when the neighbours its front layer hides hold more than this share of
# its foreground weight: below it, redoing the ray changed the cloth's and the strip's joint by at most 0.03 dB
# (`python -m tools.bench.regions`) and cost a fifth to a third more redone rays.
REDO_MIN_HIDDEN = 0.05


@torch.no_grad()
def front_layer(trace: Trace, points: torch.Tensor, p_can: torch.Tensor, inv_f: torch.Tensor, spacing: float,
                alpha: float = 0.5, beta: float = 2.0, min_share: float = 0.25, backend: str = "auto") -> Trace:
    """The trace with each ray's attention restricted to its front layer (module doc).

    trace: `trace_frame` of `points`; points [M, 3] deformed positions (non-finite rows are never neighbours),
    p_can [M, 3] their canonical positions, inv_f [M, 3, 3] the inverse local deformation gradients (finite,
    bounded: `EditState.inv_f`); spacing: the model's point spacing (world units); alpha, beta: the layer test's
    relative and absolute tolerance (beta in spacings); min_share: the share of a ray's foreground weight a layer
    needs to count as its visible surface; backend: "compiled" (CPU, numba), "torch" or "auto" (compiled where
    it can run). Returns a Trace whose weights, fg_weights and x changed only on rays where a layer was dropped
    (bg unchanged); the trace itself when no ray changed.
    """
    front = front_anchors(trace, points, p_can, inv_f, spacing, alpha, beta, min_share, backend)
    if front is None:
        return trace
    rows, _, _, keep = front
    idx = trace.idx
    pts = torch.nan_to_num(points.detach().to(torch.float32), nan=0.0, posinf=0.0, neginf=0.0)
    kept = trace.fg_weights[rows] * (idx[rows] >= 0) * keep
    left = kept.sum(1)
    changed = left > 0
    if not bool(changed.any()):
        return trace
    rc, kc = rows[changed], kept[changed]
    fg = kc / left[changed][:, None]
    new_w, new_fg, new_x = trace.weights.clone(), trace.fg_weights.clone(), trace.x.clone()
    new_fg[rc] = fg
    new_w[rc] = fg * (1.0 - trace.bg[rc])[:, None]
    new_x[rc] = (fg[..., None] * pts[idx[rc].clamp_min(0)]).sum(1)
    return dataclasses.replace(trace, weights=new_w, fg_weights=new_fg, x=new_x)


@torch.no_grad()
def front_anchors(trace: Trace, points: torch.Tensor, p_can: torch.Tensor, inv_f: torch.Tensor, spacing: float,
                  alpha: float = 0.5, beta: float = 2.0, min_share: float = 0.25, backend: str = "auto",
                  min_hidden: float = 0.0):
    """The rays whose attention reaches behind their front layer (arguments as `front_layer`; min_hidden: only
    rays whose dropped neighbours hold more than this share of their foreground weight): None when there is
    none, else (rows [S] int64 ray indices, anchor [S] int64 the point that starts each ray's front layer, depth
    [S] its depth along the ray, keep [S, K] bool: the ray's neighbours in that layer or in front of it)."""
    idx = trace.idx
    compiled = _compiled(backend, idx.device)
    if idx.shape[0] == 0 or idx.shape[1] < 2:
        return None
    pts = torch.nan_to_num(points.detach().to(torch.float32), nan=0.0, posinf=0.0, neginf=0.0)
    can, fi = p_can.detach().to(torch.float32), inv_f.detach().to(torch.float32)
    if compiled:  # one pass over the whole frame's arrays (no gathers): only rays that drop something come back
        keep, first = _keep_compiled(idx, trace.fg_weights, trace.active, trace.origins, trace.dirs, pts, can, fi,
                                     float(alpha), float(beta) * float(spacing), float(min_share), float(min_hidden))
        rows = torch.nonzero(first >= 0).squeeze(1)
        if rows.numel() == 0:
            return None
        keep, first = keep[rows], first[rows]
    else:
        rows = torch.nonzero(trace.active & (idx >= 0).any(1)).squeeze(1)
        if rows.numel() == 0:
            return None
        keep, first = _keep_torch(idx[rows], trace.fg_weights[rows], trace.origins[rows], trace.dirs[rows], pts, can,
                                  fi, float(alpha), float(beta) * float(spacing), float(min_share))
        w = trace.fg_weights[rows] * (idx[rows] >= 0)
        hidden = (w * ~keep).sum(1)
        drops = (first >= 0) & ((w * ~keep) > 0).any(1) & (hidden > float(min_hidden) * w.sum(1))
        if not bool(drops.any()):
            return None
        rows, keep, first = rows[drops], keep[drops], first[drops]
    anchor = idx[rows].gather(1, first[:, None]).squeeze(1)
    depth = ((pts[anchor] - trace.origins[rows]) * trace.dirs[rows]).sum(-1)
    return rows, anchor, depth, keep


@torch.no_grad()
def unoccluded(candidates: torch.Tensor, anchor: torch.Tensor, depth: torch.Tensor, origins: torch.Tensor,
               dirs: torch.Tensor, points: torch.Tensor, p_can: torch.Tensor, inv_f: torch.Tensor, spacing: float,
               k: int, alpha: float = 0.5, beta: float = 2.0, backend: str = "auto") -> torch.Tensor:
    """The first k of each ray's ranked neighbour candidates that the front layer does not hide: in the layer of the
    ray's anchor point, or in front of it. candidates [S, C] (ranked, -1 = none), anchor [S], depth [S] and the
    rays origins / dirs [S, 3] as from `front_anchors`; points, p_can, inv_f as there; backend: "compiled" (CPU,
    numba), "torch" or "auto" (compiled where it can run; both choose the same). Returns idx [S, k] (-1 pads).
    """
    compiled = _compiled(backend, candidates.device)
    pts = torch.nan_to_num(points.detach().to(torch.float32), nan=0.0, posinf=0.0, neginf=0.0)
    can, fi = p_can.detach().to(torch.float32), inv_f.detach().to(torch.float32)
    if compiled:
        return _unoccluded_compiled(candidates, anchor, depth, origins, dirs, pts, can, fi, float(alpha),
                                    float(beta) * float(spacing), int(k))
    valid = candidates >= 0
    cs = candidates.clamp_min(0)
    dc = can[cs] - can[anchor][:, None, :]
    res = ((fi[anchor][:, None] @ (pts[cs] - pts[anchor][:, None, :])[..., None]).squeeze(-1) - dc).norm(dim=-1)
    t = ((pts[cs] - origins[:, None, :]) * dirs[:, None, :]).sum(-1)
    ok = valid & ((res <= alpha * dc.norm(dim=-1) + float(beta) * float(spacing)) | (t <= depth[:, None]))
    rank = torch.cumsum(ok.to(torch.int64), 1)
    take = ok & (rank <= k)
    out = torch.full((candidates.shape[0], k), -1, dtype=torch.long, device=candidates.device)
    b, j = torch.nonzero(take, as_tuple=True)
    out[b, rank[b, j] - 1] = candidates[b, j]
    return out


def _unoccluded_loop(cand, anchor, depth, o, d, pts, can, fi, alpha, tol, out):
    """The compiled form of `unoccluded`'s choice (fi [M, 9] row-major): writes out [S, k] int64 (-1 preset)."""
    s_n, c_n = cand.shape
    k = out.shape[1]
    for r in range(s_n):
        a = anchor[r]
        n = 0
        for j in range(c_n):
            q = cand[r, j]
            if q < 0:
                continue
            t = (pts[q, 0] - o[r, 0]) * d[r, 0] + (pts[q, 1] - o[r, 1]) * d[r, 1] + (pts[q, 2] - o[r, 2]) * d[r, 2]
            if t <= depth[r] or _in_layer(pts, can, fi, a, q, alpha, tol):
                out[r, n] = q
                n += 1
                if n == k:
                    break


def _unoccluded_compiled(cand, anchor, depth, origins, dirs, pts, can, fi, alpha, tol, k):
    """`unoccluded` by the compiled loop (float32 tensors in, idx [S, k] int64 out)."""
    out = np.full((cand.shape[0], k), -1, dtype=np.int64)
    _kernel(_unoccluded_loop)(_i64(cand), _i64(anchor), _f32(depth), _f32(origins), _f32(dirs), _f32(pts), _f32(can),
                              _f32(fi.reshape(-1, 9)), alpha, tol, out)
    return torch.from_numpy(out).to(cand.device)


def _keep_torch(idx, w, origins, dirs, pts, can, fi, alpha, tol, min_share, chunk: int = 2048):
    """Which neighbours each ray keeps (the reference form; `_keep_loop` keeps the same neighbours): idx [S, K],
    w [S, K] fg weights, origins/dirs [S, 3], pts / can [M, 3], fi [M, 3, 3] -> (keep [S, K] bool (True where
    unchanged), first [S] int64 the slot of the front layer's first neighbour, -1 where the ray has none or kept
    all)."""
    valid = idx >= 0
    safe = idx.clamp_min(0)
    w = w * valid
    keep = torch.ones_like(valid)
    first_out = torch.full((idx.shape[0],), -1, dtype=torch.long, device=idx.device)
    # screen: each neighbour against the most-attended one; rays where all pass keep everything
    anchor = safe.gather(1, w.argmax(1, keepdim=True)).squeeze(1)
    dc = can[safe] - can[anchor][:, None, :]
    res = ((fi[anchor][:, None] @ (pts[safe] - pts[anchor][:, None, :])[..., None]).squeeze(-1) - dc).norm(dim=-1)
    odd = (valid & (w > 0) & (res > alpha * dc.norm(dim=-1) + tol)).any(1)
    rows = torch.nonzero(odd).squeeze(1)
    depth = ((pts[safe] - origins[:, None, :]) * dirs[:, None, :]).sum(-1).masked_fill(~valid, math.inf)
    for s in range(0, rows.numel(), chunk):
        rr = rows[s:s + chunk]
        ix, vv, ww = safe[rr], valid[rr], w[rr]
        p, c, g = pts[ix], can[ix], fi[ix]                                                    # [B, K, ...]
        dpp = p[:, None, :, :] - p[:, :, None, :]                                             # [B, m, l, 3]
        dcc = c[:, None, :, :] - c[:, :, None, :]
        pred = torch.einsum("bmij,bmlj->bmli", g, dpp)
        layer = ((pred - dcc).norm(dim=-1) <= alpha * dcc.norm(dim=-1) + tol) & vv[:, None, :] & vv[:, :, None]
        mass = (layer * ww[:, None, :]).sum(-1)                                               # [B, m]
        t = depth[rr]
        order = t.argsort(dim=1, stable=True)                                                   # front to back
        enough = (mass.gather(1, order) >= min_share * ww.sum(1, keepdim=True)) & vv.gather(1, order)
        has = enough.any(1)
        first = order.gather(1, enough.to(torch.int8).argmax(1, keepdim=True)).squeeze(1)
        b = torch.arange(rr.numel(), device=idx.device)
        k = layer[b, first] | (t <= t[b, first][:, None]) | ~vv
        keep[rr] = torch.where(has[:, None], k, torch.ones_like(k))
        first_out[rr] = torch.where(has, first, torch.full_like(first, -1))
    return keep, first_out


def _keep_loop(idx, w, active, o, d, pts, can, fi, alpha, tol, min_share, min_hidden, keep, first_out, order,
               depth):
    """The compiled form of `_keep_torch` and of front_anchors' choice of rays (float64 arithmetic on float32
    inputs; fi [M, 9] row-major), over a whole frame: rays not `active` [S] are skipped. Writes keep [S, K] uint8
    and first_out [S] int64 (-1 preset): the front layer's first slot on the rays where a neighbour with weight
    behind it is dropped, -1 elsewhere; order [K] int64 and depth [K] float64 are scratch."""
    s_n, k = idx.shape
    for r in range(s_n):
        if not active[r]:
            continue
        # most-attended neighbour (the first of equal weights, as argmax)
        a = -1
        best = -1.0
        total = 0.0
        for j in range(k):
            wj = w[r, j] if idx[r, j] >= 0 else 0.0
            if wj > best:
                best = wj
                a = j
            total += wj
        for j in range(k):
            keep[r, j] = 1
        qa = idx[r, a] if idx[r, a] >= 0 else 0
        odd = False
        for j in range(k):
            q = idx[r, j]
            if q < 0 or w[r, j] <= 0.0:
                continue
            if not _in_layer(pts, can, fi, qa, q, alpha, tol):
                odd = True
                break
        if not odd:
            continue
        n = 0
        for j in range(k):
            q = idx[r, j]
            if q >= 0:
                depth[j] = (pts[q, 0] - o[r, 0]) * d[r, 0] + (pts[q, 1] - o[r, 1]) * d[r, 1] + \
                    (pts[q, 2] - o[r, 2]) * d[r, 2]
                # insertion sort by depth, stable
                i = n
                while i > 0 and depth[order[i - 1]] > depth[j]:
                    order[i] = order[i - 1]
                    i -= 1
                order[i] = j
                n += 1
        first = -1
        need = min_share * total
        for i in range(n):
            m = order[i]
            qm = idx[r, m]
            mass = 0.0
            for l in range(k):
                ql = idx[r, l]
                if ql >= 0 and _in_layer(pts, can, fi, qm, ql, alpha, tol):
                    mass += w[r, l]
                    if mass >= need:  # enough for a front layer: the rest of the sum changes nothing
                        break
            if mass >= need:
                first = m
                break
        if first < 0:
            continue
        qf = idx[r, first]
        drop = False
        hidden = 0.0
        for l in range(k):
            ql = idx[r, l]
            if ql < 0 or depth[l] <= depth[first]:
                continue
            if not _in_layer(pts, can, fi, qf, ql, alpha, tol):
                keep[r, l] = 0
                if w[r, l] > 0.0:
                    drop = True
                    hidden += w[r, l]
        if drop and hidden > min_hidden * total:
            first_out[r] = first


def _in_layer(pts, can, fi, m, l, alpha, tol):
    """Point l is in point m's layer: |F_m⁻¹ (p_l − p_m) − (c_l − c_m)| <= alpha |c_l − c_m| + tol."""
    ex = pts[l, 0] - pts[m, 0]
    ey = pts[l, 1] - pts[m, 1]
    ez = pts[l, 2] - pts[m, 2]
    cx = can[l, 0] - can[m, 0]
    cy = can[l, 1] - can[m, 1]
    cz = can[l, 2] - can[m, 2]
    rx = fi[m, 0] * ex + fi[m, 1] * ey + fi[m, 2] * ez - cx
    ry = fi[m, 3] * ex + fi[m, 4] * ey + fi[m, 5] * ez - cy
    rz = fi[m, 6] * ex + fi[m, 7] * ey + fi[m, 8] * ez - cz
    return math.sqrt(rx * rx + ry * ry + rz * rz) <= alpha * math.sqrt(cx * cx + cy * cy + cz * cz) + tol


_in_layer = njit(_in_layer)  # a compiled _keep_loop calls the compiled form


_kernels: dict = {}


def _kernel(loop):
    """The compiled form of one of this module's loops, compiled on first use and kept."""
    if loop not in _kernels:
        _kernels[loop] = njit(loop)
    return _kernels[loop]


def _keep_compiled(idx, w, active, origins, dirs, pts, can, fi, alpha, tol, min_share, min_hidden=0.0):
    """front_anchors' work by the compiled loop over a whole frame: idx [R, K], w [R, K] fg weights, active [R]
    bool, origins / dirs [R, 3], pts / can [M, 3], fi [M, 3, 3] -> (keep [R, K] bool, first [R] int64: the front
    layer's first slot where `_keep_torch` finds one and a weighted neighbour is dropped behind it, else -1)."""
    k = idx.shape[1]
    keep = np.ones(tuple(idx.shape), dtype=np.uint8)
    first = np.full(idx.shape[0], -1, dtype=np.int64)
    _kernel(_keep_loop)(_i64(idx), _f32(w), np.ascontiguousarray(active.to("cpu", torch.bool).numpy()),
                        _f32(origins), _f32(dirs), _f32(pts), _f32(can), _f32(fi.reshape(-1, 9)), float(alpha),
                        float(tol), float(min_share), float(min_hidden), keep, first, np.zeros(k, dtype=np.int64),
                        np.zeros(k, dtype=np.float64))
    return torch.from_numpy(keep).to(idx.device, torch.bool), torch.from_numpy(first).to(idx.device)
