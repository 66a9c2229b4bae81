"""Image metrics: PSNR (full frame and on the object's pixels) and SSIM, in plain torch."""
from __future__ import annotations

import math

import torch
import torch.nn.functional as F


def psnr(pred: torch.Tensor, target: torch.Tensor, mask: torch.Tensor | None = None) -> float:
    """PSNR in dB of images in [0, 1]. pred/target [..., H, W, 3]; mask [..., H, W] bool selects pixels."""
    err = (pred.float() - target.float()) ** 2
    if mask is not None:
        m = mask[..., None].expand_as(err)
        if not bool(m.any()):
            return float("nan")
        mse = err[m].mean()
    else:
        mse = err.mean()
    mse = float(mse)
    return 99.0 if mse <= 1e-10 else -10.0 * math.log10(mse)


def object_mask(gt_alpha: torch.Tensor, pred_alpha: torch.Tensor | None, thresh: float = 0.5) -> torch.Tensor:
    """The object's pixels: ground-truth foreground ∪ rendered foreground. [..., H, W] bool."""
    m = gt_alpha > thresh
    if pred_alpha is not None:
        m = m | (pred_alpha > thresh)
    return m


def _gaussian(size: int, sigma: float, device, dtype) -> torch.Tensor:
    x = torch.arange(size, device=device, dtype=dtype) - (size - 1) / 2
    g = torch.exp(-(x**2) / (2 * sigma**2))
    return g / g.sum()


def ssim(pred: torch.Tensor, target: torch.Tensor, window: int = 11, sigma: float = 1.5,
         reduce: bool = True) -> torch.Tensor:
    """SSIM of images in [0, 1]: pred/target [H, W, 3] or [B, H, W, 3] -> scalar (or map [B, H', W'])."""
    if pred.dim() == 3:
        pred, target = pred[None], target[None]
    x = pred.permute(0, 3, 1, 2).float()
    y = target.permute(0, 3, 1, 2).float()
    c = x.shape[1]
    win = min(window, x.shape[-1], x.shape[-2])
    g = _gaussian(win, sigma, x.device, x.dtype)
    k = (g[:, None] * g[None, :]).expand(c, 1, win, win)

    def filt(z):
        return F.conv2d(z, k, groups=c)

    mx, my = filt(x), filt(y)
    sxx = filt(x * x) - mx * mx
    syy = filt(y * y) - my * my
    sxy = filt(x * y) - mx * my
    c1, c2 = 0.01**2, 0.03**2
    s = ((2 * mx * my + c1) * (2 * sxy + c2)) / ((mx * mx + my * my + c1) * (sxx + syy + c2))
    s = s.mean(1)
    return s.mean() if reduce else s
