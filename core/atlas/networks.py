"""The three Nuvo MLPs: chart assignment c(x), texture coordinates t_c(x), surface coordinates s_c(u).

All take points in the atlas's normalised frame (roughly [-1, 1]). Shapes are documented per forward.
"""
from __future__ import annotations

import math

import torch
from torch import nn


def fourier_freqs(degree: int, like: torch.Tensor) -> torch.Tensor:
    """The encoding's frequencies 2^k * pi, k < degree: [degree], on like's device and dtype."""
    return (2.0 ** torch.arange(degree, device=like.device, dtype=like.dtype)) * math.pi


def fourier_encode(x: torch.Tensor, degree: int) -> torch.Tensor:
    """x [M, d] -> [M, d * (1 + 2 * degree)]: the raw input plus sin/cos at frequencies 2^k * pi."""
    if degree <= 0:
        return x
    freqs = fourier_freqs(degree, x)
    xf = x[..., None] * freqs  # [M, d, degree]
    return torch.cat([x, torch.sin(xf).flatten(-2), torch.cos(xf).flatten(-2)], dim=-1)


def _mlp(d_in: int, width: int, depth: int, d_out: int) -> nn.Sequential:
    layers, d = [], d_in
    for _ in range(depth):
        layers += [nn.Linear(d, width), nn.ReLU()]
        d = width
    layers.append(nn.Linear(d, d_out))
    return nn.Sequential(*layers)


def _run(seq: nn.Sequential, x: torch.Tensor) -> torch.Tensor:
    """seq(x); without gradients the ReLUs work in place on their Linear's fresh output (no new array per
    activation: the same numbers, less memory traffic on a frame's hundreds of thousands of lookups)."""
    if torch.is_grad_enabled():
        return seq(x)
    for layer in seq:
        x = x.relu_() if isinstance(layer, nn.ReLU) else layer(x)
    return x


class ChartNet(nn.Module):
    """c(x): logits over n charts. forward(x [M, 3]) -> logits [M, n]; encoded: fourier_encode(x, fourier) when
    the caller has it already (the texture-coordinate net of the same degree shares it)."""

    def __init__(self, n: int, width: int, depth: int, fourier: int):
        super().__init__()
        self.fourier = fourier
        self.mlp = _mlp(3 * (1 + 2 * fourier), width, depth, n)

    def forward(self, x: torch.Tensor, encoded: torch.Tensor | None = None) -> torch.Tensor:
        return _run(self.mlp, fourier_encode(x, self.fourier) if encoded is None else encoded)


class TexCoordNet(nn.Module):
    """t_c(x) for all charts with one shared trunk and n heads. forward(x [M, 3]) -> uv [M, n, 2].

    Outputs are unbounded (the UV range hinge keeps them in [0, 1]); they start near the chart centre.
    """

    def __init__(self, n: int, width: int, depth: int, fourier: int):
        super().__init__()
        self.n, self.fourier = n, fourier
        self.mlp = _mlp(3 * (1 + 2 * fourier), width, depth, 2 * n)

    def forward(self, x: torch.Tensor, encoded: torch.Tensor | None = None) -> torch.Tensor:
        """encoded: as ChartNet.forward's."""
        y = _run(self.mlp, fourier_encode(x, self.fourier) if encoded is None else encoded)
        return 0.5 + y.view(-1, self.n, 2)

    def jacobian(self, x: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """(J [M, n, 2, 3] = d t_c / dx, uv [M, n, 2]) at x [M, 3], by carrying the three input directions through
        the network beside the values (forward mode): three extra rows per point instead of one backward pass per
        output; differentiable with respect to the weights. The same derivative autograd gives."""
        h = fourier_encode(x, self.fourier)
        M, d = x.shape
        eye = torch.eye(d, device=x.device, dtype=x.dtype).expand(M, d, d)      # [M, 3 (direction), 3]
        if self.fourier > 0:
            freqs = fourier_freqs(self.fourier, x)
            xf = x[..., None] * freqs                                            # [M, 3, degree]
            ds, dc = torch.cos(xf) * freqs, -torch.sin(xf) * freqs               # d/dx_i of sin / cos(x_i f_k)
            # direction j moves feature (i, k) only when i == j: [M, 3 (j), 3 (i), degree]
            tan = torch.cat([eye, (eye[..., None] * ds[:, None]).flatten(-2),
                             (eye[..., None] * dc[:, None]).flatten(-2)], dim=-1)  # [M, 3, D]
        else:
            tan = eye
        for layer in self.mlp:
            if isinstance(layer, nn.ReLU):
                on = (h > 0).to(h.dtype)
                h, tan = h * on, tan * on[:, None, :]
            else:
                h, tan = layer(h), nn.functional.linear(tan, layer.weight)
        J = tan.permute(0, 2, 1).reshape(M, self.n, 2, d)
        return J, 0.5 + h.view(-1, self.n, 2)


class BatchedLinear(nn.Module):
    """n independent linear layers applied in one batched matmul: [n, M, d_in] -> [n, M, d_out]."""

    def __init__(self, n: int, d_in: int, d_out: int):
        super().__init__()
        bound = 1.0 / math.sqrt(d_in)  # same initialisation as nn.Linear
        self.weight = nn.Parameter(torch.empty(n, d_in, d_out).uniform_(-bound, bound))
        self.bias = nn.Parameter(torch.empty(n, 1, d_out).uniform_(-bound, bound))

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return torch.baddbmm(self.bias, x, self.weight)


class SurfaceNet(nn.Module):
    """s_c(u): one small MLP per chart, evaluated together. forward(u [n, M, 2]) -> x [n, M, 3] (chart c uses u[c])."""

    def __init__(self, n: int, width: int, depth: int, fourier: int):
        super().__init__()
        self.n, self.fourier = n, fourier
        dims = [2 * (1 + 2 * fourier)] + [width] * depth + [3]
        self.layers = nn.ModuleList(BatchedLinear(n, a, b) for a, b in zip(dims[:-1], dims[1:]))

    def forward(self, u: torch.Tensor) -> torch.Tensor:
        h = fourier_encode(u, self.fourier)
        for i, layer in enumerate(self.layers):
            h = layer(h)
            if i < len(self.layers) - 1:
                h = torch.relu(h)
        return h
