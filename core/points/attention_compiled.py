"""Compiled CPU kernel of the render-time proximity attention (`PointModel.attend` without gradients).

Same maths as the torch path, in the same float32 steps: per ray, the neighbours' depths along the ray and
perpendicular distances (in each neighbour's canonical frame when inverse deformation gradients are given; one
compiled loop), their Fourier features and the key MLP (the model's own torch functions: vectorised sines and a
BLAS matrix product beat a compiled loop), then the influence, the background slot, both softmaxes and the surface point (a second loop).
Why compiled loops: on a CPU the torch path materialises a dozen [R, K, ·] temporaries per chunk of rays (gathers,
Fourier terms, 3 × 3 products, masks); one pass per ray keeps them in registers. It equals the torch path to float
rounding (≤ 1e-5 on weights and frames, tests/core/points/test_fast_paths.py).

Needs numba (an optional dependency, as for core/points/neighbors/compiled.py): without it `available()` is False
and rendering keeps the torch path. CPU only; the CUDA path stays torch. Used by `trace_frame` (no gradients);
training keeps `PointModel.attend`.
"""
from __future__ import annotations

import math

import numpy as np
import torch
import torch.nn as nn

from core.points.model import fourier

try:  # optional: the torch path is used without it
    import numba

    _NUMBA_ERROR = None
except ImportError as exc:  # pragma: no cover - exercised only where numba is missing
    numba = None
    _NUMBA_ERROR = exc

BACKENDS = ("auto", "torch", "compiled")


def available() -> bool:
    """True when numba imports (the compiled attention can run)."""
    return numba is not None


def _features(pts, fi, use_f, rebase, o, d, idx, s, feat):
    """Key geometry of rays o, d [R, 3] over neighbours idx [R, K] (-1 = empty) of points pts [N, 3], inverse
    gradients fi [N, 9] (row-major 3 × 3; used when use_f): feat [R * K, 2] float32 (distance, depth in spacings
    s, clamped), row r·K + j, as PointModel.attend builds them (empty slots measured from point 0, like its clamped
    indices); rebase (with use_f): depths from the nearest foot of the ray's valid neighbours (attend's
    rebase_depth)."""
    f32 = np.float32
    r_n, k = idx.shape
    lim = f32(64.0)
    tt = np.empty(k, dtype=np.float32)
    dep = np.empty(k, dtype=np.float32)
    rh = np.empty(k, dtype=np.float32)
    gn = np.ones(k, dtype=np.float32)
    for r in range(r_n):
        ox, oy, oz = o[r, 0], o[r, 1], o[r, 2]
        dx, dy, dz = d[r, 0], d[r, 1], d[r, 2]
        tmin = f32(np.inf)
        nvalid = 0
        for j in range(k):
            q = idx[r, j]
            qq = q if q >= 0 else 0
            t = (pts[qq, 0] - ox) * dx + (pts[qq, 1] - oy) * dy + (pts[qq, 2] - oz) * dz
            tt[j] = t
            if q >= 0:
                nvalid += 1
                if t < tmin:
                    tmin = t
        if nvalid == 0:
            tmin = f32(0.0)
        for j in range(k):
            q = idx[r, j]
            if q < 0:
                q = 0
            rx = pts[q, 0] - ox
            ry = pts[q, 1] - oy
            rz = pts[q, 2] - oz
            t = tt[j]
            if use_f:
                ex = rx - tmin * dx
                ey = ry - tmin * dy
                ez = rz - tmin * dz
                ux = fi[q, 0] * ex + fi[q, 1] * ey + fi[q, 2] * ez
                uy = fi[q, 3] * ex + fi[q, 4] * ey + fi[q, 5] * ez
                uz = fi[q, 6] * ex + fi[q, 7] * ey + fi[q, 8] * ez
                cx = fi[q, 0] * dx + fi[q, 1] * dy + fi[q, 2] * dz
                cy = fi[q, 3] * dx + fi[q, 4] * dy + fi[q, 5] * dz
                cz = fi[q, 6] * dx + fi[q, 7] * dy + fi[q, 8] * dz
                cn = f32(math.sqrt(cx * cx + cy * cy + cz * cz))
                if cn < f32(1e-12):
                    cn = f32(1e-12)
                gn[j] = cn
                cx = cx / cn
                cy = cy / cn
                cz = cz / cn
                depth = ux * cx + uy * cy + uz * cz
                px = ux - depth * cx
                py = uy - depth * cy
                pz = uz - depth * cz
            else:
                px = rx - t * dx
                py = ry - t * dy
                pz = rz - t * dz
                depth = t - tmin
            rh[j] = f32(math.sqrt(px * px + py * py + pz * pz))
            dep[j] = depth
        fmin = f32(0.0)
        if use_f and rebase:  # the nearest foot: where a neighbour's canonical depth is 0 along the deformed ray
            fmin = f32(np.inf)
            for j in range(k):
                if idx[r, j] >= 0:
                    ft = dep[j] / gn[j]
                    if ft < fmin and math.isfinite(ft):
                        fmin = ft
            if nvalid == 0 or not math.isfinite(fmin):
                fmin = f32(0.0)
            for j in range(k):
                dep[j] = dep[j] - fmin * gn[j]
        for j in range(k):
            f0 = rh[j] / s
            if f0 > lim:
                f0 = lim
            f1 = dep[j] / s
            if f1 > lim:
                f1 = lim
            elif f1 < -lim:
                f1 = -lim
            row = r * k + j
            feat[row, 0] = f0
            feat[row, 1] = f1


def _softmax(key, infl, pts, o, idx, bg_logit, temp, out_w, out_fg, out_bg, out_x):
    """From the key MLP's logits key [R, K]: the softmax with the background slot (weights out_w [R, K], out_bg
    [R]), the one over the neighbour slots alone (out_fg [R, K]; uniform where none is valid, as the torch path's
    masked fill) and the surface point out_x [R, 3] (the ray origin o [R, 3] where no neighbour is valid)."""
    f32 = np.float32
    r_n, k = idx.shape
    logit = np.empty(k + 1, dtype=np.float32)
    e = np.empty(k + 1, dtype=np.float32)
    ninf = f32(-np.inf)
    big = f32(1e30)
    for r in range(r_n):
        nvalid = 0
        for j in range(k):
            q = idx[r, j]
            if q < 0:
                logit[j] = ninf
                continue
            nvalid += 1
            iv = infl[q]
            if iv > big:
                iv = big
            elif iv < -big:
                iv = -big
            logit[j] = (key[r, j] + iv) / temp
        logit[k] = bg_logit / temp
        mx = logit[k]
        for j in range(k):
            if logit[j] > mx:
                mx = logit[j]
        tot = f32(0.0)
        for j in range(k + 1):
            e[j] = math.exp(logit[j] - mx) if logit[j] != ninf else f32(0.0)
            tot += e[j]
        for j in range(k):
            out_w[r, j] = e[j] / tot
        out_bg[r] = e[k] / tot
        if nvalid == 0:
            for j in range(k):
                out_fg[r, j] = f32(1.0) / f32(k)
            out_x[r, 0] = o[r, 0]
            out_x[r, 1] = o[r, 1]
            out_x[r, 2] = o[r, 2]
            continue
        mx = ninf
        for j in range(k):
            if logit[j] > mx:
                mx = logit[j]
        tot = f32(0.0)
        for j in range(k):
            e[j] = math.exp(logit[j] - mx) if logit[j] != ninf else f32(0.0)
            tot += e[j]
        sx = f32(0.0)
        sy = f32(0.0)
        sz = f32(0.0)
        for j in range(k):
            a = e[j] / tot
            out_fg[r, j] = a
            q = idx[r, j]
            if q < 0:
                q = 0
            sx += a * pts[q, 0]
            sy += a * pts[q, 1]
            sz += a * pts[q, 2]
        out_x[r, 0] = sx
        out_x[r, 1] = sy
        out_x[r, 2] = sz


_compiled = None


def _get_kernels():
    global _compiled
    if _compiled is None:
        if numba is None:
            raise RuntimeError(f"the compiled attention needs numba ({_NUMBA_ERROR}); install it (pip install numba) "
                               "or use attention='torch'")
        try:  # cached next to the module (or numba's user cache) so later processes skip the compile
            _compiled = tuple(numba.njit(cache=True, nogil=True, fastmath=False)(f) for f in (_features, _softmax))
        except RuntimeError:  # no writable cache location (read-only install): compile per process
            _compiled = tuple(numba.njit(cache=False, nogil=True, fastmath=False)(f) for f in (_features, _softmax))
    return _compiled


def supported(model, device: torch.device) -> bool:
    """The compiled kernel covers this model on this device: CPU, numba present, the standard key MLP
    (Linear, ReLU, Linear, ReLU, Linear to one logit)."""
    seq = getattr(model, "key_mlp", None)
    return (device.type == "cpu" and available() and isinstance(seq, nn.Sequential) and len(seq) == 5
            and isinstance(seq[0], nn.Linear) and isinstance(seq[1], nn.ReLU) and isinstance(seq[2], nn.Linear)
            and isinstance(seq[3], nn.ReLU) and isinstance(seq[4], nn.Linear) and seq[4].out_features == 1
            and seq[0].in_features == 2 * (1 + 2 * model.cfg.key_freqs))


def _np32(t: torch.Tensor) -> np.ndarray:
    return np.ascontiguousarray(t.detach().to("cpu", torch.float32).numpy())


@torch.no_grad()
def attend_compiled(model, points: torch.Tensor, influence: torch.Tensor, origins: torch.Tensor,
                    dirs: torch.Tensor, idx: torch.Tensor, temperature: float | None = None,
                    inv_f: torch.Tensor | None = None, chunk: int = 1024, rebase_depth: bool = False) -> dict:
    """PointModel.attend's render outputs: the key features and the softmaxes by the compiled kernels, the key MLP
    by torch in between (see `supported`), `chunk` rays at a time (keeps the MLP's activations in cache). Args as
    attend: points [N, 3], influence [N], origins/dirs [R, 3], idx [R, K] (-1 = empty), inv_f [N, 3, 3] or None,
    rebase_depth (with inv_f).
    Returns dict(weights [R, K], fg_weights [R, K], bg [R], x [R, 3]) float32 CPU tensors."""
    features, softmax = _get_kernels()
    r, k = idx.shape
    out_w = np.zeros((r, k), dtype=np.float32)
    out_fg = np.zeros((r, k), dtype=np.float32)
    out_bg = np.ones(r, dtype=np.float32)
    out_x = np.zeros((r, 3), dtype=np.float32)
    temp = np.float32(max(float(model.cfg.temperature if temperature is None else temperature), 1e-3))
    pts = _np32(points)
    infl = _np32(influence)
    fi = np.zeros((1, 9), dtype=np.float32) if inv_f is None else _np32(inv_f.reshape(-1, 9))
    o, d = _np32(origins), _np32(dirs)
    ix = np.ascontiguousarray(idx.to("cpu", torch.int64).numpy())
    s = np.float32(float(model.spacing.clamp_min(1e-12)))
    freqs = int(model.cfg.key_freqs)
    bg_logit = np.float32(float(model.bg_logit))
    feat = np.empty((min(chunk, r) * k, 2), dtype=np.float32)
    for a in range(0, r, chunk):
        b = min(a + chunk, r)
        f = feat[: (b - a) * k]
        features(pts, fi, inv_f is not None, bool(rebase_depth), o[a:b], d[a:b], ix[a:b], s, f)
        key = model.key_mlp(fourier(torch.from_numpy(f), freqs)).view(b - a, k).numpy()
        softmax(key, infl, pts, o[a:b], ix[a:b], bg_logit, temp, out_w[a:b], out_fg[a:b], out_bg[a:b], out_x[a:b])
    return {"weights": torch.from_numpy(out_w), "fg_weights": torch.from_numpy(out_fg),
            "bg": torch.from_numpy(out_bg), "x": torch.from_numpy(out_x)}
