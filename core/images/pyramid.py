"""Image pyramids of a split: the same views area-averaged by integer factors, cameras scaled to match.

Multi-scale training (`TrainConfig.train_scales`) keeps the images at the size they were loaded and trains on
patches of several levels; level s is every image area-averaged over s x s blocks with the intrinsics scaled by
1/s — the split `load_split(..., downscale=s)` reads from the same files (area averaging is linear, so averaging
the composited images equals compositing the averaged premultiplied ones, as the loader does).
"""
from __future__ import annotations

import dataclasses

import torch

from core.images.cameras import simplest
from core.util.errors import InputError


def parse_scales(text: str, flag: str = "--train-scales") -> list[int]:
    """"1,2,4" -> [1, 2, 4] (sorted, distinct, each >= 1); "" or "off" -> []. A malformed list raises InputError
    naming `flag`."""
    if str(text).strip().lower() == "off":
        return []
    if str(text).strip().lower() == "auto":
        raise InputError(f"{flag} auto: `pointgt fit` turns it into factors from --downscale; give the factors "
                         "here (e.g. 1,2,4)")
    parts = [p.strip() for p in str(text).split(",") if p.strip()]
    try:
        vals = [int(p) for p in parts]
    except ValueError:
        raise InputError(f"{flag}: comma-separated positive integers (downscale factors, e.g. 1,2,4), "
                         f"got {text!r}") from None
    if any(v < 1 or v > 64 for v in vals):
        raise InputError(f"{flag}: every factor must be 1-64, got {text!r}")
    if len(set(vals)) != len(vals):
        raise InputError(f"{flag}: a factor is listed twice in {text!r}")
    return sorted(vals)


def parse_weights(text: str, n: int, flag: str = "--train-scale-weights") -> list[float]:
    """Relative shares of n levels: "" -> n equal shares; else n comma-separated finite numbers >= 0, not all 0.
    Returns n floats summing to 1; a malformed list raises InputError naming `flag`."""
    parts = [p.strip() for p in str(text).split(",") if p.strip()]
    if not parts:
        return [1.0 / n] * n
    try:
        vals = [float(p) for p in parts]
    except ValueError:
        raise InputError(f"{flag}: comma-separated numbers, one per level, got {text!r}") from None
    if len(vals) != n:
        raise InputError(f"{flag}: {len(vals)} weight(s) for {n} level(s) in --train-scales; give one per level")
    if any(not (v >= 0 and v < float("inf")) for v in vals) or sum(vals) <= 0:
        raise InputError(f"{flag}: weights must be finite, >= 0 and not all 0, got {text!r}")
    total = sum(vals)
    return [v / total for v in vals]


def check_divides(height: int, width: int, scales: list[int], flag: str = "--train-scales", where: str = "") -> None:
    """InputError unless every factor of `scales` divides height and width (naming the factors that do)."""
    bad = [s for s in scales if height % s or width % s]
    if bad:
        ok = [d for d in range(1, 65) if height % d == 0 and width % d == 0]
        raise InputError(f"{flag}: the {where + ' ' if where else ''}images are {width}x{height}, which "
                         f"{', '.join(map(str, bad))} do(es) not divide; use factors among {ok}")


def area_downscale(x: torch.Tensor, s: int) -> torch.Tensor:
    """Average s x s blocks of x [V, H, W] or [V, H, W, C] (H and W divisible by s) -> [V, H/s, W/s(, C)]."""
    if s == 1:
        return x
    v, h, w = x.shape[:3]
    y = x.reshape(v, h // s, s, w // s, s, *x.shape[3:])
    return y.mean(dim=(2, 4), dtype=torch.float32)


def downscale_split(split, s: int, flag: str = "--train-scales"):
    """Level s of a split (`core.images.dataset.SplitData`): images [V, H/s, W/s, 3] and alphas [V, H/s, W/s]
    area-averaged, intrinsics scaled by 1/s (focal a float for the centred camera, as the loader hands it), same
    c2w. s = 1 returns the split itself; a factor that does not divide the size raises InputError naming `flag`."""
    if s == 1:
        return split
    check_divides(split.height, split.width, [s], flag)
    h, w = split.height // s, split.width // s
    k = split.intrinsics.scaled(1.0 / s)
    return dataclasses.replace(split, images=area_downscale(split.images, s).clamp_(0.0, 1.0),
                               alphas=area_downscale(split.alphas, s).clamp_(0.0, 1.0), focal=simplest(k, h, w),
                               height=h, width=w, intrinsics=k,
                               meta={**split.meta, "pyramid_level": s})


def pyramid(split, scales: list[int], flag: str = "--train-scales") -> dict:
    """{s: downscale_split(split, s)} for every factor of `scales` (checked first: all must divide the size)."""
    check_divides(split.height, split.width, scales, flag)
    return {s: downscale_split(split, s, flag) for s in scales}


# `pointgt fit --downscale N --train-scales auto` (N > 1): the finest level is at most
# this many times the training size (the factor measured in docs/results.md#resolution), so the images held in
# memory are at most AUTO_MAX_FACTOR² times the training size's.
AUTO_MAX_FACTOR = 4


def ladder(factor: int) -> list[int]:
    """The pyramid factors from a level `factor` x the coarsest down to it: the powers of two below it that divide
    it, and the factor itself (so every level divides the images): [1, 2, 4] for 4, [1, 2, 6] for 6, [1, 3] for
    3, [1] for 1."""
    out, s = [], 1
    while s < factor:
        if factor % s == 0:
            out.append(s)
        s *= 2
    return out + [factor]


def auto_train_scales(downscale: int, max_factor: int = AUTO_MAX_FACTOR) -> tuple[int, str, str]:
    """The multi-scale training of `pointgt fit --downscale N --train-scales auto`.

    The training size is the images / N either way. For N > 1 the images are read at a finer size — divided by L,
    the smallest divisor of N with N / L <= max_factor — and trained as the pyramid `ladder(N / L)` of that size,
    two thirds of the steps on the coarsest level (the training size), the other third in equal shares on the
    finer ones (weights 1,1,4 for three levels, 1,2 for two: the weights measured best over the library scenes,
    docs/results.md#resolution).
    Returns (L, train_scales, train_scale_weights) as the flags spell them; N = 1 returns (1, "", ""): nothing
    finer than the training size, no pyramid."""
    n = int(downscale)
    if n <= 1:
        return 1, "", ""
    load = next(d for d in range(1, n + 1) if n % d == 0 and n // d <= max_factor)
    scales = ladder(n // load)
    if len(scales) == 1:
        return load, "", ""
    fine = len(scales) - 1
    weights = [1] * fine + [2 * fine]  # coarsest: twice the steps of all finer levels together
    return load, ",".join(map(str, scales)), ",".join(map(str, weights))
