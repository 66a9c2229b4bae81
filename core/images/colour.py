"""Colour space: the sRGB encoding curve (IEC 61966-2-1) between display values and linear light.

Images, atlases and frames hold display (sRGB-encoded) values in [0, 1]; filtering (pixel filters, texture refits)
happens in linear light, as Cycles filters radiance.
"""
from __future__ import annotations

import torch


def srgb_to_linear(c: torch.Tensor) -> torch.Tensor:
    """Display (sRGB) [..., C] in [0, 1] -> linear."""
    return torch.where(c < 0.04045, c / 12.92, ((c.clamp_min(0.0) + 0.055) / 1.055) ** 2.4)


def linear_to_srgb(c: torch.Tensor) -> torch.Tensor:
    """Linear [..., C] -> display (sRGB) encoding, clamped to [0, 1]."""
    c = c.clamp(0.0, 1.0)
    return torch.where(c < 0.0031308, c * 12.92, 1.055 * c.clamp_min(1e-12) ** (1.0 / 2.4) - 0.055)
