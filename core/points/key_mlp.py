"""The attention key MLP of training, evaluated in chunks of slots with a hand-written backward.

`PointModel.attend` scores every (ray, neighbour) slot by the key MLP over the Fourier features of its two key
numbers (distance to the ray, depth; `fourier`, then Linear, ReLU, Linear, ReLU, Linear to one logit). In a
training step that is R·K = 4096 · 20 slots: through autograd every layer keeps an [R·K, width] activation (20 MB
each at width 64), and its backward makes a fresh array of that size for every ReLU mask, transpose copy and
gradient — memory traffic and first-touch page faults that cost more than the matrix products.

`key_logits` gives the same numbers (to float rounding: the same float32 operations, only the order of the sums over
slots in the weight gradients differs) with three changes: empty slots (index -1, masked out of the softmax
anyway, so their logits and gradients are unused) are left out; the slots run in chunks small enough for the
activations to stay in the CPU's cache; and the backward recomputes each chunk's activations instead of storing
them, then forms the gradients of the weights, biases and key features by hand (ReLU masks applied in place).
Plain torch on any device. Equality with the autograd path: tests/core/points/test_key_mlp.py; speed:
`python -m tools.bench.train_step` (docs/benchmarks.md, "Stage-1 step").
"""
from __future__ import annotations

import torch
import torch.nn as nn

KEY_PATHS = ("auto", "torch", "chunked")
CHUNK = 4096  # slots per chunk: [4096, 64] float32 activations are 1 MB, the EPYC's L2 per core is 512 kB – 1 MB


def standard_key_mlp(seq) -> bool:
    """True when seq is the model's standard key MLP: Linear, ReLU, Linear, ReLU, Linear to one logit."""
    return (isinstance(seq, nn.Sequential) and len(seq) == 5 and isinstance(seq[0], nn.Linear)
            and isinstance(seq[1], nn.ReLU) and isinstance(seq[2], nn.Linear) and isinstance(seq[3], nn.ReLU)
            and isinstance(seq[4], nn.Linear) and seq[4].out_features == 1)


def _fourier(f: torch.Tensor, scales: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """core.points.model.fourier of f [M, D] with its octave scales [F] (F ≥ 1): (features [M, D·(1 + 2F)],
    the scaled inputs xs [M, D·F]), column order as there: raw values, sines, cosines (d major, f minor)."""
    xs = (f[:, :, None] * scales).flatten(1)
    return torch.cat([f, torch.sin(xs), torch.cos(xs)], dim=1), xs


class _ChunkedKeyMLP(torch.autograd.Function):
    """logits [M] = key_mlp(fourier(feats [M, D])) chunk by chunk; the backward recomputes the activations."""

    @staticmethod
    def forward(ctx, feats, freqs, chunk, w1, b1, w2, b2, w3, b3):
        m = feats.shape[0]
        out = torch.empty(m, dtype=feats.dtype, device=feats.device)
        scales = 2.0 ** torch.arange(freqs, device=feats.device, dtype=feats.dtype) if freqs > 0 else None
        w1t, w2t, w3t = w1.t(), w2.t(), w3.t()
        for a in range(0, m, chunk):
            f = feats[a:a + chunk]
            x = _fourier(f, scales)[0] if freqs > 0 else f
            h = torch.addmm(b1, x, w1t).clamp_min_(0.0)
            h = torch.addmm(b2, h, w2t).clamp_min_(0.0)
            out[a:a + chunk] = torch.addmm(b3, h, w3t).squeeze(1)
        ctx.save_for_backward(feats, w1, b1, w2, b2, w3)
        ctx.freqs, ctx.chunk = freqs, chunk
        return out

    @staticmethod
    def backward(ctx, g):
        feats, w1, b1, w2, b2, w3 = ctx.saved_tensors
        freqs, chunk = ctx.freqs, ctx.chunk
        m, dim = feats.shape
        need_f = ctx.needs_input_grad[0]
        g = g.contiguous()
        gw1, gb1 = torch.zeros_like(w1), torch.zeros_like(b1)
        gw2, gb2 = torch.zeros_like(w2), torch.zeros_like(b2)
        gw3 = torch.zeros_like(w3)
        gb3 = g.sum().reshape(1)
        gf = torch.empty_like(feats) if need_f else None
        scales = 2.0 ** torch.arange(freqs, device=feats.device, dtype=feats.dtype) if freqs > 0 else None
        w1t, w2t = w1.t(), w2.t()
        for a in range(0, m, chunk):
            f = feats[a:a + chunk]
            gy = g[a:a + chunk, None]                                           # [c, 1]
            if freqs > 0:
                x, xs = _fourier(f, scales)
            else:
                x, xs = f, None
            h1 = torch.addmm(b1, x, w1t).clamp_min_(0.0)
            h2 = torch.addmm(b2, h1, w2t).clamp_min_(0.0)
            gw3.addmm_(gy.t(), h2)
            gz = (gy * w3).mul_(h2 > 0)                                         # [c, width] grad of layer 2's output
            gw2.addmm_(gz.t(), h1)
            gb2 += gz.sum(0)
            gz = (gz @ w2).mul_(h1 > 0)                                         # grad of layer 1's output
            gw1.addmm_(gz.t(), x)
            gb1 += gz.sum(0)
            if need_f:
                gx = gz @ w1                                                    # [c, D·(1 + 2F)]
                if freqs > 0:
                    c = f.shape[0]
                    nf = dim * freqs
                    g_sin, g_cos = gx[:, dim:dim + nf], gx[:, dim + nf:]
                    d_xs = g_sin * torch.cos(xs) - g_cos * torch.sin(xs)        # [c, D·F]
                    gf[a:a + chunk] = gx[:, :dim] + (d_xs.view(c, dim, freqs) * scales).sum(-1)
                else:
                    gf[a:a + chunk] = gx
        return gf, None, None, gw1, gb1, gw2, gb2, gw3, gb3


def key_logits(seq: nn.Sequential, feats: torch.Tensor, freqs: int, valid: torch.Tensor | None = None,
               chunk: int = CHUNK) -> torch.Tensor:
    """The standard key MLP (`standard_key_mlp`) over the Fourier features of feats [R, K, D] -> logits [R, K],
    equal to seq(fourier(feats, freqs)).squeeze(-1) to float rounding, gradients included (to feats and seq's
    weights). valid [R, K] bool: only those slots are evaluated, the others get logit 0 and no gradient (for
    slots the caller masks out). chunk: slots per chunk (≥ 1)."""
    r, k, dim = feats.shape
    flat = feats.reshape(r * k, dim)
    rows = None
    if valid is not None:
        rows = torch.nonzero(valid.reshape(-1)).squeeze(1)
        flat = flat.index_select(0, rows)
    flat = flat.contiguous()
    l1, l2, l3 = seq[0], seq[2], seq[4]
    out = _ChunkedKeyMLP.apply(flat, int(freqs), max(int(chunk), 1), l1.weight, l1.bias, l2.weight, l2.bias,
                               l3.weight, l3.bias)
    if rows is None:
        return out.reshape(r, k)
    return torch.zeros(r * k, dtype=out.dtype, device=out.device).index_put((rows,), out).reshape(r, k)
