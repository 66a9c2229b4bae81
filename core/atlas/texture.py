"""Chart textures by kernel regression: every sample splats its colour into its chart's texels (bilinear weights
times P(c|x)), numerator and weight are blurred by the same Gaussian, and their ratio is the texel colour.

Why not per-sample gradient descent alone: on real samples one surface point is seen from many views with different
colours (pixel footprints, noisy PAPR surface points), and the texture has about as many texels as samples, so an
MSE fit reproduces that noise texel by texel (a speckled atlas). The weighted mean is the MSE optimum of a constant
colour per kernel footprint, costs one pass over the samples, and gives every texel with nearby samples a value.
"""
from __future__ import annotations

import math

import numpy as np
import torch
import torch.nn.functional as F


def splat(probs: torch.Tensor, uv: torch.Tensor, rgb: torch.Tensor, R: int, min_prob: float = 1e-3
          ) -> tuple[torch.Tensor, torch.Tensor]:
    """Bilinear splat of sample colours into chart textures.

    probs [S, n] chart probabilities, uv [S, n, 2] texture coordinates (u -> column, v -> row), rgb [S, 3].
    Returns (colour sums [n, 3, R, R], weights [n, R, R]); the weights use the same bilinear footprint as
    `packing.sample_charts` (texel centres at (j + 0.5) / R, clamp to edge) scaled by P(c|x).
    """
    S, n = probs.shape
    f = uv.clamp(0, 1) * R - 0.5  # continuous texel index [S, n, 2]
    base = f.floor()
    frac = f - base
    base = base.long()
    w_all, idx_all = [], []
    for dr in (0, 1):  # the four bilinear corners
        for dc in (0, 1):
            wc = frac[..., 0] if dc else 1 - frac[..., 0]
            wr = frac[..., 1] if dr else 1 - frac[..., 1]
            col = (base[..., 0] + dc).clamp(0, R - 1)
            row = (base[..., 1] + dr).clamp(0, R - 1)
            w_all.append(wc * wr * probs * (probs > min_prob))  # [S, n]
            idx_all.append(torch.arange(n, device=uv.device) * R * R + row * R + col)  # [S, n] flat texel ids
    w = torch.stack(w_all).reshape(-1)
    idx = torch.stack(idx_all).reshape(-1)
    col = rgb[None, :, None, :].expand(4, S, n, 3).reshape(-1, 3)
    wsum = torch.zeros(n * R * R, device=uv.device, dtype=rgb.dtype).index_add_(0, idx, w)
    csum = torch.zeros(n * R * R, 3, device=uv.device, dtype=rgb.dtype).index_add_(0, idx, col * w[:, None])
    return csum.T.reshape(3, n, R, R).transpose(0, 1).contiguous(), wsum.view(n, R, R)


def gaussian_blur(img: torch.Tensor, sigma: float) -> torch.Tensor:
    """Separable Gaussian blur with zero padding (so blurred weights fall off at the chart edge, and the ratio
    colour / weight stays an average). img [B, C, H, W], sigma in texels (<= 0: unchanged)."""
    if sigma <= 0:
        return img
    r = max(1, int(math.ceil(3 * sigma)))
    x = torch.arange(-r, r + 1, device=img.device, dtype=img.dtype)
    k = torch.exp(-0.5 * (x / sigma) ** 2)
    k = k / k.sum()
    B, C, H, W = img.shape
    y = img.reshape(B * C, 1, H, W)
    y = F.conv2d(y, k.view(1, 1, 1, -1), padding=(0, r))
    y = F.conv2d(y, k.view(1, 1, -1, 1), padding=(r, 0))
    return y.view(B, C, H, W)


def texel_spacing(pts: torch.Tensor, k: int = 8, max_points: int = 20000) -> float:
    """Mean sample spacing 1 / sqrt(density) of 2-D points pts [M, 2] (texel units), from the median distance r_k
    to the k-th neighbour (a disc of radius r_k holds k samples: density = k / (pi r_k^2)). 1.0 if M <= k."""
    from scipy.spatial import cKDTree

    if len(pts) <= k:
        return 1.0
    pick = torch.randperm(len(pts), generator=torch.Generator().manual_seed(0))[:max_points]  # fixed, unstructured
    p = pts[pick.to(pts.device)].double().cpu().numpy()
    d, _ = cKDTree(p).query(p, k=k + 1)
    r = float(np.median(d[:, k]))
    # A subset of m of the M points is sparser by sqrt(M / m).
    return max(r * math.sqrt(math.pi / k) * math.sqrt(len(p) / len(pts)), 1e-6)


def kernel_texture(probs: torch.Tensor, uv: torch.Tensor, rgb: torch.Tensor, R: int, sigma: float,
                   min_prob: float = 1e-3, min_weight: float = 1e-3) -> tuple[torch.Tensor, torch.Tensor, float]:
    """Chart textures as the Gaussian-weighted mean colour of the samples around each texel.

    probs [S, n], uv [S, n, 2], rgb [S, 3]; sigma: kernel std in units of the samples' mean spacing in texel
    space (`texel_spacing` of the samples whose most probable chart is c), so the kernel holds about the same
    number of samples whatever the chart's scale. Returns (textures [n, 3, R, R] (0.5 where no sample is near),
    covered [n, R, R] bool (blurred weight > min_weight), sigma_texels (the mean kernel std in texels)).
    """
    csum, wsum = splat(probs, uv, rgb, R, min_prob)
    n = probs.shape[1]
    owner = probs.argmax(-1)
    out, covered, sig_used = [], [], []
    for c in range(n):  # n <= 8 charts; each chart has its own texel density
        spacing = texel_spacing(uv[owner == c, c] * R)
        s = sigma * spacing
        num = gaussian_blur(csum[c][None], s)[0]
        den = gaussian_blur(wsum[c][None, None], s)[0, 0]
        ok = den > min_weight * max(float(den.max()), 1e-30)
        out.append(torch.where(ok[None], num / den.clamp_min(1e-30)[None], torch.full_like(num, 0.5)))
        covered.append(ok)
        sig_used.append(s)
    return torch.stack(out), torch.stack(covered), float(sum(sig_used) / len(sig_used))
