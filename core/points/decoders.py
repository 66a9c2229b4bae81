"""Decoders from the ray-feature image to RGB. `none` (values are RGB) needs no module; `unet` is below.

Residual form (the default): the feature image's first three channels are the decoder-free render (the points' own
colours blended by attention, over the training background), the fourth the attention's coverage (1 − background
weight), and the UNet adds a correction to the colour, the mask head one to the coverage's logit. Both last layers
start at zero, so at initialisation the decoder render *is* the decoder-free render (colour and coverage), and the
colour output has no saturating non-linearity: a correction that overshoots [0, 1] still gets a gradient (frames
are clamped only when they are shown). The older form (sigmoid of the UNet's output) is kept for model files that use it; it can
saturate to the background colour and never recover.
"""
from __future__ import annotations

import torch
import torch.nn as nn
import torch.nn.functional as F


def _block(c_in: int, c_out: int) -> nn.Sequential:
    return nn.Sequential(nn.Conv2d(c_in, c_out, 3, padding=1), nn.ReLU(inplace=True),
                         nn.Conv2d(c_out, c_out, 3, padding=1), nn.ReLU(inplace=True))


class UNetDecoder(nn.Module):
    """A small two-level UNet: feature image [B, c_in, H, W] -> [B, 3, H, W] (RGB), or [B, 4, H, W] with the mask
    head (RGB + foreground alpha logit).

    residual: the input's channels 0-2 are a base colour and channel 3 a base coverage in [0, 1]; the RGB output is
    base + correction (no sigmoid) and the alpha logit logit(coverage) + correction; otherwise the RGB output is
    logits (the caller applies a sigmoid).

    The mask head is separate: a small conv net on the feature image with its gradient stopped, so learning alpha
    never takes capacity from the colours (an alpha channel sharing the trunk cost 0.5 dB of object PSNR on the
    cloth at equal steps).
    Any H, W work (odd sizes are padded to even and cropped back), so patches and full frames share it.
    """

    def __init__(self, c_in: int, width: int = 32, alpha: bool = False, residual: bool = False):
        super().__init__()
        self.residual = residual
        self.enc1 = _block(c_in, width)
        self.enc2 = _block(width, 2 * width)
        self.dec1 = _block(3 * width, width)
        self.out = nn.Conv2d(width, 3, 1)
        self.alpha_head = nn.Sequential(nn.Conv2d(c_in, 16, 3, padding=1), nn.ReLU(inplace=True),
                                        nn.Conv2d(16, 16, 3, padding=1), nn.ReLU(inplace=True),
                                        nn.Conv2d(16, 1, 1)) if alpha else None
        if residual:  # the corrections start at zero: the decoder render equals the decoder-free render
            self.reset_correction()

    def reset_correction(self) -> None:
        """Residual form: zero the last layers, so the output is the base colour and coverage again."""
        nn.init.zeros_(self.out.weight)
        nn.init.zeros_(self.out.bias)
        if self.alpha_head is not None:
            nn.init.zeros_(self.alpha_head[-1].weight)
            nn.init.zeros_(self.alpha_head[-1].bias)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        h, w = x.shape[-2:]
        ph, pw = h % 2, w % 2
        if ph or pw:
            x = F.pad(x, (0, pw, 0, ph), mode="replicate")
        e1 = self.enc1(x)
        e2 = self.enc2(F.avg_pool2d(e1, 2))
        up = F.interpolate(e2, scale_factor=2, mode="bilinear", align_corners=False)
        feat = self.dec1(torch.cat([e1, up], dim=1))
        y = self.out(feat)
        if self.residual:
            y = x[:, :3] + y
        if self.alpha_head is not None:
            a = self.alpha_head(x.detach())
            if self.residual:
                a = a + torch.logit(x[:, 3:4].detach().clamp(1e-6, 1.0 - 1e-6))
            y = torch.cat([y, a], dim=1)
        return y[..., :h, :w]
