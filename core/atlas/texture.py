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

from core.atlas.packing import dilate_unused


def splat(probs: torch.Tensor, uv: torch.Tensor, rgb: torch.Tensor, R: int, min_prob: float = 1e-3,
          box: tuple[int, int, int, int] | None = None) -> tuple[torch.Tensor, torch.Tensor]:
    """Bilinear splat of sample colours into chart textures.

    probs [S, n] chart probabilities, uv [S, n, 2] texture coordinates (u -> column, v -> row), rgb [S, C] (any C).
    Returns (colour sums [n, C, R, R], weights [n, R, R]); the weights use the same bilinear footprint as
    `packing.sample_charts` (texel centres at (j + 0.5) / R, clamp to edge) scaled by P(c|x).
    box (r0, r1, c0, c1): only that window of the R x R textures ([n, C, r1 - r0, c1 - c0], [n, r1 - r0, c1 - c0]);
    it must hold every texel a sample with P(c|x) > min_prob reaches (`splat_box`).
    """
    S, n = probs.shape
    r0, r1, c0, c1 = (0, R, 0, R) if box is None else box
    h, wd = r1 - r0, c1 - c0
    f = uv.clamp(0, 1) * R - 0.5  # continuous texel index [S, n, 2]
    base = f.floor()
    frac = f - base
    base = base.long()
    w_all, idx_all = [], []
    for dr in (0, 1):  # the four bilinear corners
        for dc in (0, 1):
            wc = frac[..., 0] if dc else 1 - frac[..., 0]
            wr = frac[..., 1] if dr else 1 - frac[..., 1]
            col = (base[..., 0] + dc).clamp(0, R - 1) - c0
            row = (base[..., 1] + dr).clamp(0, R - 1) - r0
            w = wc * wr * probs * (probs > min_prob)  # [S, n]
            if box is not None:  # a sample outside the window must carry no weight into it
                w = torch.where((row >= 0) & (row < h) & (col >= 0) & (col < wd), w, torch.zeros_like(w))
                row, col = row.clamp(0, h - 1), col.clamp(0, wd - 1)
            w_all.append(w)
            idx_all.append(torch.arange(n, device=uv.device) * h * wd + row * wd + col)  # [S, n] flat texel ids
    w = torch.stack(w_all).reshape(-1)
    idx = torch.stack(idx_all).reshape(-1)
    C = rgb.shape[1]
    w = w.to(rgb.dtype)
    col = rgb[None, :, None, :].expand(4, S, n, C).reshape(-1, C)
    wsum = torch.zeros(n * h * wd, device=uv.device, dtype=rgb.dtype).index_add_(0, idx, w)
    csum = torch.zeros(n * h * wd, C, device=uv.device, dtype=rgb.dtype).index_add_(0, idx, col * w[:, None])
    return csum.T.reshape(C, n, h, wd).transpose(0, 1).contiguous(), wsum.view(n, h, wd)


def splat_box(uv: torch.Tensor, R: int, margin: int) -> tuple[int, int, int, int]:
    """The window (r0, r1, c0, c1) of an R x R texture that holds every texel the bilinear splat of uv [M, 2]
    (one chart's coordinates) reaches, grown by margin texels (a blur's reach) and clipped to the texture; the
    whole texture when uv is empty."""
    if uv.shape[0] == 0:
        return 0, R, 0, R
    f = (torch.nan_to_num(uv, nan=0.0).clamp(0, 1) * R - 0.5).floor()  # NaN: where splat's clamp puts it, texel 0
    lo = (f.amin(0).long() - margin).clamp(0, R - 1).tolist()
    hi = (f.amax(0).long() + 2 + margin).clamp(1, R).tolist()
    return lo[1], hi[1], lo[0], hi[0]


def blur_reach(sigma: float) -> int:
    """Texels a `gaussian_blur` of std sigma reaches on each side (0 when it does not blur)."""
    return max(1, int(math.ceil(3 * sigma))) if sigma > 0 else 0


def gaussian_blur(img: torch.Tensor, sigma: float) -> torch.Tensor:
    """Separable Gaussian blur with zero padding (so blurred weights fall off at the chart edge, and the ratio
    colour / weight stays an average). img [B, C, H, W], sigma in texels (<= 0: unchanged)."""
    if sigma <= 0:
        return img
    r = blur_reach(sigma)
    x = torch.arange(-r, r + 1, device=img.device, dtype=img.dtype)
    k = torch.exp(-0.5 * (x / sigma) ** 2)
    k = k / k.sum()
    B, C, H, W = img.shape
    y = img.reshape(B * C, 1, H, W)
    y = F.conv2d(y, k.view(1, 1, 1, -1), padding=(0, r))
    y = F.conv2d(y, k.view(1, 1, -1, 1), padding=(r, 0))
    return y.view(B, C, H, W)


def blur_within(img: torch.Tensor, sigma: float, labels: torch.Tensor | None) -> torch.Tensor:
    """gaussian_blur of img [B, C, H, W] that never mixes pixels of different labels: each label's pixels are
    blurred with the others zeroed, in a crop around them. labels [H, W] long (-1 = none: left 0); None = one label."""
    if labels is None or sigma <= 0:
        return gaussian_blur(img, sigma) if labels is None else img * (labels >= 0)
    out = torch.zeros_like(img)
    r = blur_reach(sigma)
    H, W = labels.shape
    active = torch.unique(labels[(img != 0).flatten(0, 1).any(0) & (labels >= 0)])
    for lab in active.tolist():
        mine = labels == lab
        rows, cols = torch.nonzero(mine, as_tuple=True)
        r0, r1 = max(int(rows.min()) - r, 0), min(int(rows.max()) + r + 1, H)
        c0, c1 = max(int(cols.min()) - r, 0), min(int(cols.max()) + r + 1, W)
        m = mine[r0:r1, c0:c1]
        blurred = gaussian_blur(img[:, :, r0:r1, c0:c1] * m, sigma)
        out[:, :, r0:r1, c0:c1] += blurred * m
    return out


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
                   min_prob: float = 1e-3, min_weight: float = 1e-3, labels: torch.Tensor | None = None
                   ) -> tuple[torch.Tensor, torch.Tensor, float]:
    """Chart textures as the Gaussian-weighted mean colour of the samples around each texel.

    probs [S, n], uv [S, n, 2], rgb [S, 3]; sigma: kernel std in units of the samples' mean spacing in texel
    space (`texel_spacing` of the samples whose most probable chart is c), so the kernel holds about the same
    number of samples whatever the chart's scale. labels [R, R] (island layouts: the island each pixel belongs
    to) keeps the kernel inside one island. Returns (textures [n, 3, R, R] (0.5 where no sample is near),
    covered [n, R, R] bool (blurred weight > min_weight), sigma_texels (the mean kernel std in texels)).
    """
    n = probs.shape[1]
    owner = probs.argmax(-1)
    out = torch.full((n, rgb.shape[1], R, R), 0.5, dtype=rgb.dtype, device=rgb.device)
    covered = torch.zeros(n, R, R, dtype=torch.bool, device=rgb.device)
    sig_used = []
    for c in range(n):  # each chart has its own texel density
        spacing = texel_spacing(uv[owner == c, c] * R)
        s = sigma * spacing
        sig_used.append(s)
        sel = probs[:, c] > min_prob
        if not bool(sel.any()):
            continue
        # the window the chart's samples reach, grown by the blur's reach: outside it every sum is zero (an island
        # layout's charts each cover a small part of the image)
        r0, r1, c0, c1 = box = splat_box(uv[sel, c], R, blur_reach(s))
        csum, wsum = splat(probs[sel, c:c + 1], uv[sel, c:c + 1], rgb[sel], R, min_prob, box=box)
        lab = None if labels is None else labels[r0:r1, c0:c1]
        num = blur_within(csum, s, lab)[0]
        den = blur_within(wsum[:, None], s, lab)[0, 0]
        ok = den > min_weight * max(float(den.max()), 1e-30)
        out[c, :, r0:r1, c0:c1] = torch.where(ok[None], num / den.clamp_min(1e-30)[None], torch.full_like(num, 0.5))
        covered[c, r0:r1, c0:c1] = ok
    return out, covered, float(sum(sig_used) / len(sig_used))


def filled_kernel_texture(probs: torch.Tensor, uv: torch.Tensor, rgb: torch.Tensor, R: int, sigma: float,
                          labels: torch.Tensor | None = None) -> tuple[torch.Tensor, torch.Tensor, float]:
    """The atlas texture from samples in one step: `kernel_texture` clamped to [0, 1], then its gutters filled —
    texels no sample reaches take their nearest covered texel's colour (`packing.dilate_unused`), so bilinear
    lookups at the edge of the covered region never read the placeholder grey.

    probs [S, n], uv [S, n, 2], rgb [S, 3], sigma, labels as `kernel_texture`. Returns (textures [n, 3, R, R] in
    [0, 1], covered [n, R, R] bool, sigma_texels).
    """
    tex, covered, sigma_texels = kernel_texture(probs, uv, rgb, R, sigma, labels=labels)
    return dilate_unused(tex.clamp(0, 1), covered), covered, sigma_texels


def local_linear_points(pix: torch.Tensor, xyz: torch.Tensor, R: int, sigma: float, ridge: float = 0.05,
                        min_weight: float = 1e-3, labels: torch.Tensor | None = None, with_slope: bool = False):
    """The 3-D point that the forward map sends to each texel centre, by kernel-weighted local linear regression of
    the samples' positions on their texel coordinates: x(p) ~ a + B (p - c) around each texel centre c, and the
    texel's point is a. Unlike the kernel mean of the positions (which lands where the samples are dense, up to a
    sample spacing off the texel), it is exact for a locally affine map, so t_c(point) returns to the texel.

    pix [S, 2] continuous texel coordinates (col, row) of one chart's samples in an R x R image, xyz [S, 3];
    sigma: kernel std in sample spacings (as kernel_texture). ridge: shrinks B (in units of the kernel variance)
    where the samples around a texel do not span two directions (edges), towards the kernel mean. labels [R, R]:
    as kernel_texture (the kernel stays inside one island).
    Returns (points [R, R, 3] float32 (NaN where no sample is near), covered [R, R] bool); with_slope also the
    local slope [R, R, 2, 3] (dx/d col, dx/d row: the surface's tangent plane in texel units)."""
    dev = pix.device
    if len(pix) == 0:
        empty = (torch.full((R, R, 3), float("nan"), device=dev), torch.zeros(R, R, dtype=torch.bool, device=dev))
        return empty + (torch.zeros(R, R, 2, 3, device=dev),) if with_slope else empty
    p = pix.double()
    ref = R / 2.0
    q = (p - ref)  # centred texel coordinates (float64 moments stay exact)
    x = xyz.double()
    feats = torch.cat([q, q[:, :1] * q, q[:, 1:] * q[:, 1:], x, q[:, :1] * x, q[:, 1:] * x], 1)  # [S, 2+3+3+6]
    ones = torch.ones(len(p), 1, dtype=torch.float64, device=dev)
    s = sigma * texel_spacing(pix.float())
    # the window the samples reach, grown by the blur's reach (outside it every moment is zero)
    r0, r1, c0, c1 = box = splat_box((p / R).float(), R, blur_reach(s))
    csum, wsum = splat(ones, (p / R)[:, None], feats, R, 0.0, box=box)
    lab = None if labels is None else labels[r0:r1, c0:c1]
    num = blur_within(csum, s, lab)[0]                  # [14, h, w]
    W = blur_within(wsum[:, None], s, lab)[0, 0]        # [h, w]
    covered = torch.zeros(R, R, dtype=torch.bool, device=dev)
    covered[r0:r1, c0:c1] = W > min_weight * max(float(W.max()), 1e-30)
    rows, cols = torch.nonzero(covered, as_tuple=True)
    m = num[:, rows - r0, cols - c0].T / W[rows - r0, cols - c0, None]  # normalised moments [K, 14]
    c = torch.stack([cols + 0.5, rows + 0.5], -1).double() - ref  # texel centres, same frame as q
    mu, x_mean = m[:, 0:2], m[:, 5:8]
    Suu = torch.stack([torch.stack([m[:, 2], m[:, 3]], -1), torch.stack([m[:, 3], m[:, 4]], -1)], -2)  # E[q q^T]
    Sux = torch.stack([m[:, 8:11], m[:, 11:14]], 1)     # E[q x^T] [K, 2, 3]
    # covariance form around the weighted mean: x(c) = x_mean + Cov(x, q) Cov(q)^-1 (c - mu)
    cov_qq = Suu - mu[:, :, None] * mu[:, None, :]
    cov_qx = Sux - mu[:, :, None] * x_mean[:, None, :]
    eye = torch.eye(2, dtype=torch.float64, device=dev)
    B = torch.linalg.solve(cov_qq + ridge * s * s * eye, cov_qx)  # [K, 2, 3]
    pts = x_mean + ((c - mu)[:, None, :] @ B)[:, 0]
    out = torch.full((R, R, 3), float("nan"), dtype=torch.float32, device=dev)
    out[rows, cols] = pts.float()
    if not with_slope:
        return out, covered
    slope = torch.zeros(R, R, 2, 3, dtype=torch.float32, device=dev)
    slope[rows, cols] = B.float()
    return out, covered, slope
