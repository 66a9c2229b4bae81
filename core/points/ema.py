"""An exponential moving average of a point model's trainable parameters (`TrainConfig.ema`).

Stage 1 keeps, beside the parameters the optimiser moves, their running average over the last steps; the average
is what the fit returns and saves. It follows the point set through pruning and cloning (`resize`): a kept or
cloned point's average is its source point's (a clone's shifted by the clone's own offset), so the averaged model
has the same points as the trained one.
"""
from __future__ import annotations

import torch

from core.points.model import PointModel


class ParamEMA:
    """Running average of every parameter of a model: ema ← d·ema + (1 − d)·param after each step, with
    d = min(decay, (1 + n) / (10 + n)) at the n-th update (a warm-up: the first updates follow the parameters
    closely, so the average does not remember the random initialisation). decay 0 = the parameters themselves."""

    def __init__(self, model: PointModel, decay: float):
        if not 0.0 <= decay < 1.0:
            raise ValueError(f"EMA decay must be in [0, 1), got {decay}")
        self.decay = float(decay)
        self.updates = 0
        self.shadow = {n: p.detach().clone() for n, p in model.named_parameters()}

    def rate(self) -> float:
        """The decay d of the next update."""
        return min(self.decay, (1.0 + self.updates) / (10.0 + self.updates))

    @torch.no_grad()
    def update(self, model: PointModel) -> None:
        """Fold the model's current parameters into the average (after an optimiser step)."""
        d = self.rate()
        for n, p in model.named_parameters():
            s = self.shadow[n]
            if s.shape != p.shape:  # a parameter replaced without `resize` (cannot happen in fit_points): restart it
                self.shadow[n] = p.detach().clone()
            else:
                s.mul_(d).add_(p.detach(), alpha=1.0 - d)
        self.updates += 1

    @torch.no_grad()
    def resize(self, names, src: torch.Tensor, jitter: torch.Tensor | None = None) -> None:
        """The point set changed as `resize_points` changes it: the averages of the point parameters `names`
        become ema[src] (src [N'] int64 indices of the old points), xyz's plus jitter [N', 3] when given."""
        for n in names:
            data = self.shadow[n][src].clone()
            if n == "xyz" and jitter is not None:
                data += jitter
            self.shadow[n] = data

    @torch.no_grad()
    def reset(self, model: PointModel, prefix: str = "") -> None:
        """Restart the average of the parameters whose name starts with prefix ("" = all) from their current
        values (after the collapse guard reset them)."""
        for n, p in model.named_parameters():
            if n.startswith(prefix):
                self.shadow[n] = p.detach().clone()

    @torch.no_grad()
    def swap(self, model: PointModel) -> None:
        """Exchange the model's parameters and their averages (twice = unchanged): the model then holds the
        average and this object the trained parameters."""
        for n, p in model.named_parameters():
            tmp = p.detach().clone()
            p.copy_(self.shadow[n])
            self.shadow[n] = tmp
