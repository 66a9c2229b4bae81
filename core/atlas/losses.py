"""The Nuvo loss terms (method.md Sec. 2), each a plain function of tensors with documented shapes.
The normal-free distortion term lives in distortion.py."""
from __future__ import annotations

import torch
import torch.nn.functional as F


def cycle_3d(x: torch.Tensor, x_rec: torch.Tensor, probs: torch.Tensor) -> torch.Tensor:
    """3D->2D->3D: mean_i sum_c P(c|x_i) |x_i - s_c(t_c(x_i))|^2. x [B, 3], x_rec [B, n, 3], probs [B, n]."""
    return (probs * (x[:, None] - x_rec).pow(2).sum(-1)).sum(-1).mean()


def cycle_2d(u: torch.Tensor, u_rec: torch.Tensor) -> torch.Tensor:
    """2D->3D->2D: mean |u - t_c(s_c(u))|^2. u, u_rec [n, U, 2] (chart c in row c)."""
    return (u - u_rec).pow(2).sum(-1).mean()


def chart_consistency(logits: torch.Tensor) -> torch.Tensor:
    """-log c_c(s_c(u)): logits [n, U, n] of the chart net at s_c(u) for chart c in row c."""
    n, U, _ = logits.shape
    target = torch.arange(n, device=logits.device).repeat_interleave(U)
    return F.cross_entropy(logits.reshape(n * U, n), target)


@torch.no_grad()
def nearest_pairs(x: torch.Tensor, y: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """(index into y of each x's nearest point [B], index into x of each y's nearest point [K]) for x [B, 3] and
    y [K, 3]. On the CPU both come from the squared distances up to a per-row constant (|y|^2 - 2 x.y for each x,
    one matrix product per direction, about the two sets' common centre), each searched along its contiguous rows
    by numpy (torch's argmin along a dimension of such a matrix is many times slower on one thread: it was the
    map step's largest single cost); elsewhere torch.cdist's argmins. Rounding may pick another point whose squared distance is within float32
    rounding of the squared size of the sets (~1e-7 of it) from the nearest one's."""
    if x.device.type != "cpu" or x.dtype != torch.float32 or y.dtype != torch.float32:
        d = torch.cdist(x, y)
        return d.argmin(dim=1), d.argmin(dim=0)
    c = 0.5 * (x.mean(0) + y.mean(0))
    x, y = x - c, y - c
    xx, yy = x.pow(2).sum(-1), y.pow(2).sum(-1)
    to_y = torch.addmm(yy, x, y.T, alpha=-2).numpy().argmin(1)  # [B, K] -> [B]
    to_x = torch.addmm(xx, y, x.T, alpha=-2).numpy().argmin(1)  # [K, B] -> [K]
    return torch.from_numpy(to_y), torch.from_numpy(to_x)


def chamfer(x: torch.Tensor, y: torch.Tensor) -> torch.Tensor:
    """Symmetric squared Chamfer distance between samples x [B, 3] and generated surface points y [K, 3].
    The nearest pairs are picked on a distance matrix without gradient and only their squared distances are
    differentiated: the gradient of the min over the full matrix (it reaches the nearest pair alone), without
    back-propagating through all B x K distances (half the time of the term at B 512, K 1024)."""
    to_y, to_x = nearest_pairs(x.detach(), y.detach())  # [B], [K]
    return (x - y[to_y]).pow(2).sum(-1).mean() + (x[to_x] - y).pow(2).sum(-1).mean()


def compactness(x: torch.Tensor, probs: torch.Tensor) -> torch.Tensor:
    """Cluster compactness: mean over charts of the P-weighted spread around the P-weighted centroid.
    x [B, 3], probs [B, n]."""
    mass = probs.sum(0).clamp_min(1e-6)  # [n]
    mu = (probs.T @ x) / mass[:, None]  # [n, 3]
    spread = (probs * (x[:, None] - mu[None]).pow(2).sum(-1)).sum(0) / mass
    return spread.mean()


def uv_range(uv: torch.Tensor) -> torch.Tensor:
    """Hinge keeping texture coordinates in [0, 1]^2: mean of squared excess. uv [B, n, 2]."""
    return (F.relu(-uv) + F.relu(uv - 1)).pow(2).sum(-1).mean()


_MAX_RATE = 1e4  # normal_flatness: |J n| saturates here (its square and gradient stay within float32)


def normal_flatness(J: torch.Tensor, normals: torch.Tensor, weights: torch.Tensor | None = None) -> torch.Tensor:
    """How fast the texture coordinates change across the surface: mean_i sum_c w_ic |J_ic n_i|^2.
    J [G, n, 2, 3] (du/dx, in the frame where the tangent derivatives should be 1), normals [G, 3] (unit),
    weights [G, n] (chart probabilities; None: mean over charts). Non-finite normals count as 0; each derivative
    saturates at 1e4 (as the distortion's sigmas do), so absurd Jacobians give a finite loss and gradient."""
    nrm = torch.nan_to_num(normals.to(J.dtype), nan=0.0, posinf=0.0, neginf=0.0)
    jn = (J * nrm[:, None, None, :]).sum(-1).clamp(-_MAX_RATE, _MAX_RATE).pow(2).sum(-1)  # [G, n]
    if weights is None:
        return jn.mean()
    return (weights * jn).sum(-1).mean()


def fold_barrier(J: torch.Tensor, normals: torch.Tensor, probs: torch.Tensor, margin: float = 0.25) -> torch.Tensor:
    """Folds of the texture coordinates along the surface: rho = det of J restricted to the surface / (|du| |dv|),
    in [-1, 1] (its sign: the map's orientation against the oriented normal; 0: the map is singular along the
    surface, a crease). Each chart's side is the sign of its P-weighted mean rho (no gradient); samples whose rho is
    below margin on that side are penalised: mean_i sum_c P_ic relu(margin - side_c rho_ic)^2. A chart that lays a
    tube's front and back over each other (locally fine, globally two-to-one) has the back reversed, so the term
    pushes those samples' maps to turn or their chart probability down.
    J [G, n, 2, 3] (du/dx), normals [G, 3] (unit and consistently oriented; zero or non-finite: not counted),
    probs [G, n]. Finite for zero and huge Jacobians."""
    nrm = normals.to(J.dtype)
    use = (torch.isfinite(nrm).all(-1) & (nrm.norm(dim=-1) > 0.5)).to(J.dtype)            # [G]
    nrm = torch.where(use[:, None] > 0, nrm, torch.zeros_like(nrm))
    m = J.detach().abs().amax(dim=(-2, -1), keepdim=True).clamp_min(1e-12)                # scale-free: no overflow
    Jn = J / m
    du, dv = Jn[..., 0, :], Jn[..., 1, :]
    det = (torch.linalg.cross(du, dv) * nrm[:, None, :]).sum(-1)                          # [G, n]
    rho = det / (du.norm(dim=-1) * dv.norm(dim=-1)).clamp_min(1e-12)
    w = probs * use[:, None]
    side = torch.where((w * rho).sum(0).detach() >= 0, 1.0, -1.0).to(J.dtype)             # [n]
    return (w * F.relu(margin - side * rho).pow(2)).sum(-1).mean()
