"""Surface samples for stage 2: render every training view with the stage-1 model, keep foreground pixels,
project the predicted surface point onto its ray, pair it with a colour, drop statistical outliers.

The colour is the ground-truth pixel (`colour="image"`, the paper) or the stage-1 model's own object colour for
that ray (`colour="render"`, distillation). On the cloth scene the rendered colour fits an atlas better: one
surface point is seen in many pixels whose true colours differ (footprints, noisy x), while the model's colour is
already a consistent function of the ray; measured in docs/atlas.md (`tools/bench/atlas_vs_papr.py`)."""
from __future__ import annotations

from typing import Callable, Iterable

import numpy as np
import torch
from scipy.spatial import cKDTree

from core.images.cameras import Intrinsics, pixel_rays
from core.util.errors import InputError


def remove_outliers(xyz: np.ndarray, k: int = 8, std_ratio: float = 2.0) -> np.ndarray:
    """Statistical outlier removal. xyz [S, 3] -> keep mask [S] bool.

    A point is an outlier when its mean distance to its k nearest neighbours exceeds mean + std_ratio * std
    of that statistic over all points.
    """
    if len(xyz) <= k + 1:
        return np.ones(len(xyz), dtype=bool)
    d, _ = cKDTree(xyz).query(xyz, k=k + 1)  # first neighbour is the point itself
    mean_d = d[:, 1:].mean(axis=1)
    return mean_d <= mean_d.mean() + std_ratio * mean_d.std()


def extract_surface_samples(render_fn: Callable[[torch.Tensor, torch.Tensor], dict], views: Iterable,
                            max_samples: int = 200_000, outlier_std: float = 2.0, alpha_threshold: float = 0.5,
                            fg_threshold: float = 0.5, chunk: int = 65536, seed: int = 0,
                            device: str | torch.device = "cpu", colour: str = "image",
                            background=(1.0, 1.0, 1.0)) -> tuple[torch.Tensor, torch.Tensor]:
    """Collect (surface point, colour) pairs from rendered views.

    views: iterable of (c2w [4, 4], height, width, focal, image [H, W, 3] in [0, 1], alpha [H, W]).
    render_fn(origins [R, 3], dirs [R, 3]) -> dict(x=[R, 3] surface point, fg=[R] foreground weight in [0, 1],
    and for colour="render" rgb=[R, 3] the rendered display colour fg * c + (1 - fg) * background).
    Keeps pixels with alpha > alpha_threshold and fg > fg_threshold; x is projected onto its ray.
    colour: "image" pairs x with the pixel colour, "render" with the model's object colour
    c = (rgb - (1 - fg) * background) / fg (what an atlas lookup replaces when a frame is coloured from the atlas).
    Returns xyz [S, 3] float32 and rgb [S, 3] float32 (S <= max_samples), on `device`.
    """
    if colour not in ("image", "render"):
        raise InputError(f"surface samples: colour must be 'image' or 'render', got {colour!r}")
    bg = torch.as_tensor(background, dtype=torch.float32).reshape(3)
    xs, cs = [], []
    for i, view in enumerate(views):
        try:
            c2w, h, w, focal, image, alpha = view
        except (TypeError, ValueError) as e:
            raise InputError(f"view {i}: expected (c2w, height, width, focal, image, alpha), got {view!r:.80}") from e
        image = torch.as_tensor(image, dtype=torch.float32)
        alpha = torch.as_tensor(alpha, dtype=torch.float32)
        if image.shape != (h, w, 3) or alpha.shape != (h, w):
            raise InputError(f"view {i}: image {tuple(image.shape)} / alpha {tuple(alpha.shape)} do not match "
                             f"{h}x{w} (expected [H, W, 3] and [H, W])")
        o, d = pixel_rays(torch.as_tensor(c2w, dtype=torch.float32), h, w,
                          focal if isinstance(focal, Intrinsics) else float(focal))
        sel = alpha.reshape(-1) > alpha_threshold
        o, d, rgb = o.reshape(-1, 3)[sel], d.reshape(-1, 3)[sel], image.reshape(-1, 3)[sel]
        for s in range(0, len(o), chunk):
            with torch.no_grad():
                out = render_fn(o[s:s + chunk], d[s:s + chunk])
            x = torch.as_tensor(out["x"], dtype=torch.float32).reshape(-1, 3)
            fg = torch.as_tensor(out["fg"], dtype=torch.float32).reshape(-1)
            oc, dc = o[s:s + chunk], d[s:s + chunk]
            x = oc + ((x - oc) * dc).sum(-1, keepdim=True) * dc  # orthogonal projection onto the ray
            keep = (fg > fg_threshold) & torch.isfinite(x).all(-1)
            if colour == "render":
                if "rgb" not in out:
                    raise InputError("surface samples: colour='render' needs the render function to return 'rgb'")
                f = fg.clamp_min(1e-6)[:, None]
                c = (torch.as_tensor(out["rgb"], dtype=torch.float32).reshape(-1, 3) - (1 - f) * bg) / f
                keep &= torch.isfinite(c).all(-1)
            else:
                c = rgb[s:s + chunk]
            xs.append(x[keep])
            cs.append(c[keep])
    if not xs or sum(len(x) for x in xs) == 0:
        raise InputError("no surface samples: no pixel had both alpha > "
                         f"{alpha_threshold} and a rendered foreground weight > {fg_threshold}")
    xyz, rgb = torch.cat(xs), torch.cat(cs).clamp(0, 1)
    keep = torch.from_numpy(remove_outliers(xyz.numpy().astype(np.float64), std_ratio=outlier_std))
    xyz, rgb = xyz[keep], rgb[keep]
    if len(xyz) > max_samples:
        g = torch.Generator().manual_seed(seed)
        idx = torch.randperm(len(xyz), generator=g)[:max_samples]
        xyz, rgb = xyz[idx], rgb[idx]
    return xyz.to(device), rgb.to(device)
