"""Normal-free distortion loss (paper Sec. 4.2): singular values of J = du/dx in R^{2x3} from a closed form,
L_scaling = mean (s1 - s2)^2 and L_area = mean (log s1 s2)^2, with the Jacobian taken by autograd
(create_graph=True, so the loss itself can be differentiated: double backward).

Numerics, all in float32: each Jacobian is divided by its largest entry (detached; s is homogeneous of degree 1,
so gradients are unchanged) so squares cannot overflow, and the sigmas saturate at 1e4 (an absurd texel density)
so that (s1 - s2)^2 and its gradient stay within float32; s1 s2 is taken from the cross product of the two rows
(a Gram determinant that cannot go negative), s2^2 = det / s1^2 instead of the cancelling difference, and the
square root and logarithm see clamped arguments. Zero, rank-1 and huge Jacobians give finite losses and gradients.
"""
from __future__ import annotations

import math

import torch

_TINY = 1e-12      # guards the square roots of the normalised (entries <= 1) quantities
_MIN_AREA = 1e-8   # sigma1 * sigma2 floor before the log
_MIN_SCALE = 1e-12  # floor of the per-Jacobian normaliser
_MAX_SCALE = 1e4   # sigmas saturate here: beyond it (s1 - s2)^2 and its gradient would overflow float32


def singular_values_2x3(J: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """J [..., 2, 3] -> (sigma1 [...], sigma2 [...], log(sigma1 * sigma2) [...]), sigma1 >= sigma2 >= 0.
    sigma1, sigma2 saturate for Jacobians with entries beyond 1e4; log(sigma1 sigma2) is floored at log(1e-8).

    Closed form: a = |du|^2, b = du.dv, c = |dv|^2, lambda = (a + c +- sqrt((a - c)^2 + 4 b^2)) / 2, sigma = sqrt(lambda).
    """
    J = J.float()  # the guards below underflow in half precision; gradients flow back to a half input
    m = J.detach().abs().amax(dim=(-2, -1)).clamp_min(_MIN_SCALE)
    Jn = J / m[..., None, None]
    du, dv = Jn[..., 0, :], Jn[..., 1, :]
    a, b, c = (du * du).sum(-1), (du * dv).sum(-1), (dv * dv).sum(-1)
    det = torch.linalg.cross(du, dv).pow(2).sum(-1)  # = ac - b^2 >= 0 exactly as computed
    disc = torch.sqrt((a - c) ** 2 + 4 * b * b + _TINY)
    lam1 = 0.5 * (a + c + disc)
    lam2 = det / lam1
    m_eff = m.clamp_max(_MAX_SCALE)
    s1 = torch.sqrt(lam1 + _TINY) * m_eff
    s2 = torch.sqrt(lam2 + _TINY) * m_eff
    log_area = 0.5 * torch.log(det + _TINY) + 2 * torch.log(m)
    log_area = log_area.clamp_min(math.log(_MIN_AREA))
    return s1, s2, log_area


def distortion_terms(J: torch.Tensor, weights: torch.Tensor | None = None) -> tuple[torch.Tensor, torch.Tensor]:
    """J [G, n, 2, 3] (or [..., 2, 3]) -> (L_scaling, L_area) scalars.

    weights [G, n] (e.g. chart probabilities summing to 1 per sample): sum over charts, mean over samples.
    None: the paper's plain mean over samples and charts, 1/(G n) sum_i sum_k.
    """
    s1, s2, log_area = singular_values_2x3(J)
    scaling, area = (s1 - s2) ** 2, log_area ** 2
    if weights is None:
        return scaling.mean(), area.mean()
    w = weights.reshape(scaling.shape)
    lead = w.shape[0] if w.dim() else 1
    return (w * scaling).sum() / lead, (w * area).sum() / lead


def uv_jacobian(uv_fn, x: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """Jacobian of uv_fn at x by autograd, kept differentiable (create_graph=True).

    uv_fn: x [G, 3] -> uv [G, n, 2] (each row depends only on its own point). Returns (J [G, n, 2, 3], uv [G, n, 2]).
    A network with its own `jacobian` (TexCoordNet: forward mode, three directions) gives it that way.
    """
    if hasattr(uv_fn, "jacobian"):
        return uv_fn.jacobian(x.detach())
    x = x.detach().requires_grad_(True)
    uv = uv_fn(x)
    G, n, _ = uv.shape
    flat = uv.reshape(G, 2 * n)
    # One batched vector-Jacobian product per output channel: e_k summed over rows gives row-wise gradients.
    eye = torch.eye(2 * n, device=x.device, dtype=x.dtype)[:, None, :].expand(2 * n, G, 2 * n)
    (g,) = torch.autograd.grad(flat, x, grad_outputs=eye, create_graph=True, is_grads_batched=True)
    return g.permute(1, 0, 2).reshape(G, n, 2, 3), uv
