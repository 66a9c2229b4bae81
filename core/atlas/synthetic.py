"""Analytic test surfaces with known colours, sampled uniformly by area: stand-ins for PAPR surface samples
when developing, testing and benchmarking stage 2 without a trained model."""
from __future__ import annotations

import math

import torch

from core.util.errors import InputError

SURFACES = ("strip", "sphere", "torus")


def _strip(n: int, g: torch.Generator) -> torch.Tensor:
    # A 2 x 1 rectangle bent around a cylinder of radius 0.8 through 135 degrees (bending is an isometry,
    # so uniform (s, t) is uniform by area).
    s, t = torch.rand(n, generator=g), torch.rand(n, generator=g)
    phi = (s - 0.5) * 0.75 * math.pi
    return torch.stack([0.8 * torch.sin(phi), 0.8 * torch.cos(phi) - 0.5, t - 0.5], dim=-1)


def _sphere(n: int, g: torch.Generator) -> torch.Tensor:
    v = torch.randn(n, 3, generator=g)
    return 0.8 * v / v.norm(dim=-1, keepdim=True).clamp_min(1e-12)


def _torus(n: int, g: torch.Generator, R: float = 0.7, r: float = 0.28) -> torch.Tensor:
    # Area density of the tube angle theta is proportional to R + r cos(theta): rejection sampling.
    out = []
    while sum(len(o) for o in out) < n:
        th = torch.rand(2 * n, generator=g) * 2 * math.pi
        keep = torch.rand(2 * n, generator=g) * (R + r) < R + r * torch.cos(th)
        th = th[keep]
        ph = torch.rand(len(th), generator=g) * 2 * math.pi
        out.append(torch.stack([(R + r * torch.cos(th)) * torch.cos(ph), (R + r * torch.cos(th)) * torch.sin(ph),
                                r * torch.sin(th)], dim=-1))
    return torch.cat(out)[:n]


def surface_colour(xyz: torch.Tensor) -> torch.Tensor:
    """A smooth, position-dependent colour in [0, 1]. xyz [S, 3] -> rgb [S, 3]."""
    x, y, z = xyz.unbind(-1)
    return torch.stack([0.5 + 0.4 * torch.sin(3.0 * x + 1.0), 0.5 + 0.4 * torch.sin(4.0 * y - 2.0 * z),
                        0.5 + 0.4 * torch.cos(2.5 * z + x)], dim=-1).clamp(0, 1)


def synthetic_samples(name: str, n: int, seed: int = 0) -> tuple[torch.Tensor, torch.Tensor]:
    """Uniform-by-area samples of an analytic surface ('strip', 'sphere' or 'torus').

    Returns xyz [n, 3] float32 and rgb [n, 3] float32 in [0, 1] (from `surface_colour`).
    """
    g = torch.Generator().manual_seed(seed)
    fns = {"strip": _strip, "sphere": _sphere, "torus": _torus}
    if name not in fns:
        raise InputError(f"unknown synthetic surface {name!r}; choose one of {', '.join(SURFACES)}")
    xyz = fns[name](n, g).float()
    return xyz, surface_colour(xyz).float()
