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


def score_frame(rgb: torch.Tensor, gt: torch.Tensor, gt_alpha: torch.Tensor, alpha: torch.Tensor | None = None,
                also: dict | None = None) -> dict:
    """PSNR on the full frame and on the object's pixels, and SSIM, of one rendered frame.

    rgb [H, W, 3] and gt [H, W, 3] in [0, 1]; gt_alpha [H, W]; alpha [H, W] the render's coverage (None: the
    object is the ground truth's foreground alone). also: {"name_{}": rgb [H, W, 3]} more renders of the same view,
    scored on the same object pixels as rgb; "{}" becomes psnr / psnr_object in their keys.
    Returns {psnr, psnr_object, ssim, plus the also keys}; psnr_object is NaN when the frame has no object pixel.
    """
    gt = gt.to(rgb.device)
    m = object_mask(gt_alpha.to(rgb.device), None if alpha is None else alpha.to(rgb.device))
    row = {"psnr": psnr(rgb, gt), "psnr_object": psnr(rgb, gt, m), "ssim": float(ssim(rgb, gt))}
    for name, img in (also or {}).items():
        img = img.to(rgb.device)
        row[name.format("psnr")] = psnr(img, gt)
        row[name.format("psnr_object")] = psnr(img, gt, m)
    return row


def score_views(render, images: torch.Tensor, alphas: torch.Tensor, views=None) -> list[dict]:
    """The evaluation loop: render each view and score it against its ground truth (`score_frame`).

    render(i) -> dict with rgb [H, W, 3], optional alpha [H, W] (the render's coverage), optional also (see
    `score_frame`) and optional extra: a dict of per-view values copied into the row (timings, diagnostics).
    images [V, H, W, 3], alphas [V, H, W]; views: the view indices (default all). Returns one row per view.
    """
    rows = []
    for i in (range(images.shape[0]) if views is None else views):
        out = render(i)
        row = score_frame(out["rgb"], images[i], alphas[i], out.get("alpha"), out.get("also"))
        row.update(out.get("extra", {}))
        rows.append(row)
    return rows


def mean_scores(rows: list[dict], keys=None) -> dict:
    """Mean of each key over the rows of `score_views`, NaN (a view without object pixels) left out.
    keys: the keys to average (default: every key of the first row)."""
    keys = list(rows[0]) if keys is None else keys
    out = {}
    for k in keys:
        vals = [float(r[k]) for r in rows if not math.isnan(float(r[k]))]
        out[k] = sum(vals) / len(vals) if vals else float("nan")
    return out


def blank_floor(images: torch.Tensor, alphas: torch.Tensor, views=None, value=1.0) -> dict:
    """The floor every figure is read against: a blank frame of `value` (a grey level or an RGB triple; white)
    scored like a render without coverage. images [V, H, W, 3], alphas [V, H, W]. Returns the mean
    {psnr, psnr_object} over the views."""
    blank = torch.as_tensor(value, dtype=images.dtype, device=images.device).expand_as(images[0])
    return mean_scores(score_views(lambda i: {"rgb": blank}, images, alphas, views), ("psnr", "psnr_object"))
