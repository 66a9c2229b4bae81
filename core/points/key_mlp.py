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
them, then forms the gradients of the weights, biases and key features by hand.
Plain torch on any device. Equality with the autograd path: tests/core/points/test_key_mlp.py; speed:
`python -m tools.bench.train_step` (docs/benchmarks.md, "Stage-1 step").

"""
from __future__ import annotations

import torch
import torch.nn as nn
from torch.autograd.function import once_differentiable

KEY_PATHS = ("auto", "torch", "chunked")
CHUNK = 4096  # slots per chunk: [4096, 64] float32 arrays are 1 MB, the L2 cache per core of the AMD EPYC it was
# tuned on; 2048 measured the same, 8192 +10 %, 16384 +35 % (key MLP forward + backward, one thread)


def standard_key_mlp(seq) -> bool:
    """True when seq is the model's standard key MLP: Linear, ReLU, Linear, ReLU, Linear to one logit."""
    return (isinstance(seq, nn.Sequential) and len(seq) == 5 and isinstance(seq[0], nn.Linear)
            and isinstance(seq[1], nn.ReLU) and isinstance(seq[2], nn.Linear) and isinstance(seq[3], nn.ReLU)
            and isinstance(seq[4], nn.Linear) and seq[4].out_features == 1)


class _Chunk:
    """Work arrays for chunks of up to `rows` slots, allocated once per call and reused by every chunk (fresh
    arrays per chunk cost page faults on their first write, more than the arithmetic): the Fourier features
    transposed, xt [D·(1 + 2F), rows] (each feature a contiguous row, so the sines and cosines are written in
    one pass), the scaled inputs xst [D·F, rows], activations h1, h2 and their gradients g1, g2 [rows, width],
    the features' gradient gxt [D·(1 + 2F), rows]."""

    def __init__(self, rows: int, dim: int, freqs: int, width1: int, width2: int, like: torch.Tensor,
                 grads: bool):
        kw = dict(dtype=like.dtype, device=like.device)
        self.dim, self.freqs = dim, freqs
        self.scales = 2.0 ** torch.arange(freqs, **kw) if freqs > 0 else None
        d_in = dim * (1 + 2 * freqs)
        self.xt = torch.empty(d_in, rows, **kw)
        self.xst = torch.empty(dim * freqs, rows, **kw)
        self.h1, self.h2 = torch.empty(rows, width1, **kw), torch.empty(rows, width2, **kw)
        if grads:
            self.g1, self.g2 = torch.empty(rows, width1, **kw), torch.empty(rows, width2, **kw)
            self.gxt = torch.empty(d_in, rows, **kw)

    def features(self, f: torch.Tensor) -> torch.Tensor:
        """core.points.model.fourier of f [c, D] -> x [c, D·(1 + 2F)] (a transposed view of xt[:, :c]; raw
        values, sines, cosines, d major and f minor); xst[:, :c] holds the scaled inputs."""
        c, dim, freqs = f.shape[0], self.dim, self.freqs
        xt = self.xt[:, :c]
        xt[:dim] = f.t()
        if freqs > 0:
            nf = dim * freqs
            xst = self.xst[:, :c]
            torch.mul(xt[:dim, None, :], self.scales[:, None], out=xst.view(dim, freqs, c))
            torch.sin(xst, out=xt[dim:dim + nf])
            torch.cos(xst, out=xt[dim + nf:])
        return xt.t()

    def activations(self, x: torch.Tensor, w1t, b1, w2t, b2) -> tuple[torch.Tensor, torch.Tensor]:
        """The two hidden layers of x [c, ·] into h1[:c], h2[:c] (Linear then ReLU, each)."""
        c = x.shape[0]
        h1 = torch.addmm(b1, x, w1t, out=self.h1[:c]).clamp_min_(0.0)
        h2 = torch.addmm(b2, h1, w2t, out=self.h2[:c]).clamp_min_(0.0)
        return h1, h2


def _relu_backward_(grad: torch.Tensor, out: torch.Tensor) -> torch.Tensor:
    """grad [c, width] zeroed in place where the ReLU's output out [c, width] is not > 0 (autograd's own ReLU
    backward, threshold_backward: one pass; multiplying by a bool mask converts the mask first, 6x slower)."""
    return torch.ops.aten.threshold_backward.grad_input(grad, out, 0.0, grad_input=grad)


def _forward_span(feats, out, a, b, freqs, chunk, w1, b1, w2, b2, w3, b3) -> None:
    """Logits of slots [a, b) into out[a:b], chunk by chunk."""
    dim = feats.shape[1]
    buf = _Chunk(min(chunk, b - a), dim, freqs, w1.shape[0], w2.shape[0], feats, grads=False)
    w1t, w2t, w3t = w1.t(), w2.t(), w3.t()
    for s in range(a, b, chunk):
        e = min(s + chunk, b)
        _, h2 = buf.activations(buf.features(feats[s:e]), w1t, b1, w2t, b2)
        torch.addmm(b3, h2, w3t, out=out[s:e, None])


def _backward_span(feats, g, gf, a, b, freqs, chunk, w1, b1, w2, b2, w3):
    """Gradients of slots [a, b): the key features' into gf[a:b] (gf None: not needed); returns this span's sums
    (gw1, gb1, gw2, gb2, gw3)."""
    dim = feats.shape[1]
    gw1, gb1 = torch.zeros_like(w1), torch.zeros_like(b1)
    gw2, gb2 = torch.zeros_like(w2), torch.zeros_like(b2)
    gw3 = torch.zeros_like(w3)
    buf = _Chunk(min(chunk, b - a), dim, freqs, w1.shape[0], w2.shape[0], feats, grads=True)
    w1t, w2t = w1.t(), w2.t()
    nf = dim * freqs
    for s in range(a, b, chunk):
        e = min(s + chunk, b)
        c = e - s
        gy = g[s:e, None]                                                   # [c, 1]
        x = buf.features(feats[s:e])
        h1, h2 = buf.activations(x, w1t, b1, w2t, b2)
        gw3.addmm_(gy.t(), h2)
        g2 = _relu_backward_(torch.mul(gy, w3, out=buf.g2[:c]), h2)         # grad of layer 2's output
        gw2.addmm_(g2.t(), h1)
        gb2 += g2.sum(0)
        g1 = _relu_backward_(torch.mm(g2, w2, out=buf.g1[:c]), h1)          # grad of layer 1's output
        gw1.addmm_(g1.t(), x)
        gb1 += g1.sum(0)
        if gf is not None:
            gxt = torch.mm(w1.t(), g1.t(), out=buf.gxt[:, :c])            # [D·(1 + 2F), c]
            if freqs > 0:  # the features' own sines and cosines (still in xt) are the derivatives' factors
                sin_xs, cos_xs = buf.xt[dim:dim + nf, :c], buf.xt[dim + nf:, :c]
                d_xs = gxt[dim:dim + nf] * cos_xs - gxt[dim + nf:] * sin_xs  # [D·F, c]
                gf[s:e] = (gxt[:dim] + (d_xs.view(dim, freqs, c) * buf.scales[:, None]).sum(1)).t()
            else:
                gf[s:e] = gxt.t()
    return gw1, gb1, gw2, gb2, gw3


class _ChunkedKeyMLP(torch.autograd.Function):
    """logits [M] = key_mlp(fourier(feats [M, D])) chunk by chunk; the backward recomputes the activations."""

    @staticmethod
    def forward(ctx, feats, freqs, chunk, w1, b1, w2, b2, w3, b3):
        m = feats.shape[0]
        out = torch.empty(m, dtype=feats.dtype, device=feats.device)
        if m:
            _forward_span(feats, out, 0, m, freqs, chunk, w1, b1, w2, b2, w3, b3)
        ctx.save_for_backward(feats, w1, b1, w2, b2, w3)
        ctx.freqs, ctx.chunk = freqs, chunk
        return out

    @staticmethod
    @once_differentiable
    def backward(ctx, g):
        feats, w1, b1, w2, b2, w3 = ctx.saved_tensors
        g = g.contiguous()
        gb3 = g.sum().reshape(1)
        gf = torch.empty_like(feats) if ctx.needs_input_grad[0] else None
        if feats.shape[0] == 0:  # no slot
            return (gf, None, None, *(torch.zeros_like(t) for t in (w1, b1, w2, b2, w3)), gb3)
        gw1, gb1, gw2, gb2, gw3 = _backward_span(feats, g, gf, 0, feats.shape[0], ctx.freqs, ctx.chunk, w1, b1,
                                                 w2, b2, w3)
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
