"""Texture edits: which atlas texels were painted, and how the painted texture enters a render.

mask: texel changed by L2 > `threshold` between the original and the edited atlas image (reference rule).
blend 'threshold' (paper): use the edited texture where the bilinearly sampled mask m > 0.95, else the point render.
blend 'soft': m · T'(u) + (1 − m) · render.
"""
from __future__ import annotations

import torch

from core.util.errors import InputError

BLENDS = ("soft", "threshold")


def check_atlas_image(image, shape: tuple[int, int], name: str = "atlas image") -> torch.Tensor:
    """An edited atlas as float32 [H, W, 3] in [0, 1]; RGBA is accepted (alpha dropped). Wrong sizes and
    non-finite values raise InputError with the expected size."""
    img = torch.as_tensor(image)
    if img.dim() != 3 or img.shape[2] not in (3, 4):
        raise InputError(f"{name}: expected an RGB(A) image [H, W, 3|4], got shape {tuple(img.shape)}")
    if tuple(img.shape[:2]) != tuple(shape):
        raise InputError(f"{name}: is {img.shape[1]}x{img.shape[0]} pixels but this model's atlas is "
                         f"{shape[1]}x{shape[0]}; paint on the atlas exported from this model (pointgt export --atlas)")
    img = img[..., :3].float()
    if not bool(torch.isfinite(img).all()):
        raise InputError(f"{name}: contains NaN or infinite values")
    return img.clamp(0.0, 1.0)


def edit_mask(original: torch.Tensor, edited: torch.Tensor, threshold: float = 0.01) -> torch.Tensor:
    """Texels that changed: [H, W] float32 in {0, 1}. original/edited [H, W, 3]."""
    return ((edited.float() - original.float()).norm(dim=-1) > threshold).float()


BLEND_THRESHOLD = 0.95  # the paper's rule: use the edit where the bilinearly sampled mask exceeds this


def blend(render_rgb: torch.Tensor, texture_rgb: torch.Tensor, mask: torch.Tensor, mode: str = "soft") -> torch.Tensor:
    """render_rgb/texture_rgb [R, 3], mask [R] sampled mask in [0, 1] -> [R, 3]."""
    if mode not in BLENDS:
        raise InputError(f"texture blend must be one of {BLENDS}, got {mode!r}")
    m = (mask > BLEND_THRESHOLD).float() if mode == "threshold" else mask.clamp(0.0, 1.0)
    return m[:, None] * texture_rgb + (1.0 - m[:, None]) * render_rgb
