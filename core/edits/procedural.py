"""Procedural 3-D textures of REST-pose coordinates, defined once and evaluated two ways.

Each texture is a small expression over Blender's Generated coordinates g [N, 3] (the rest bounding box mapped
to [0, 1]^3), written against an `ExprOps` backend: `TorchOps` evaluates it on tensors here (no bpy), and
`tools.scenes.nodes.NodeOps` turns the *same* expression into shader Math nodes. One definition for both sides is
what makes a Blender render of a texture an exact ground truth for the same texture baked into a model's atlas.

Colours are display space (sRGB encoded) in [0, 1]; Blender emission needs linear colour, so the node backend
appends `srgb_to_linear` (the same formula as here). Compositing a decal over a base colour happens in display
space, like painting an atlas image.

Pattern cell edges are offset by a quarter cell (`+ 0.25`) so that faces lying exactly on the bounding box
(g = 0 or 1, e.g. a box's sides) never sit on a floor() discontinuity.
"""
from __future__ import annotations

import dataclasses
import math
from typing import Callable

import torch

from core.util.errors import InputError

Scalar = object  # a float constant, a tensor [N] or a Blender node socket, depending on the backend
RGB = tuple  # three Scalars


class ExprOps:
    """Scalar operations with constant folding; backends implement `_bin(op, a, b)` and `_un(op, a)`.

    op names are Blender Math node operations: ADD SUBTRACT MULTIPLY DIVIDE POWER MINIMUM MAXIMUM LESS_THAN
    FLOORED_MODULO, and FLOOR SINE ABSOLUTE SQRT for unary ones.
    """

    _PY_BIN = {
        "ADD": lambda a, b: a + b, "SUBTRACT": lambda a, b: a - b, "MULTIPLY": lambda a, b: a * b,
        "DIVIDE": lambda a, b: a / b if b != 0 else 0.0, "POWER": lambda a, b: a ** b if a > 0 else 0.0,
        "MINIMUM": min, "MAXIMUM": max, "LESS_THAN": lambda a, b: float(a < b),
        "FLOORED_MODULO": lambda a, b: a - math.floor(a / b) * b if b != 0 else 0.0,
    }
    _PY_UN = {"FLOOR": math.floor, "SINE": math.sin, "ABSOLUTE": abs, "SQRT": lambda a: math.sqrt(max(a, 0.0))}

    @staticmethod
    def _is_const(x) -> bool:
        return isinstance(x, (int, float))

    def binary(self, op: str, a, b):
        if self._is_const(a) and self._is_const(b):
            return float(self._PY_BIN[op](float(a), float(b)))
        return self._bin(op, a, b)

    def unary(self, op: str, a):
        if self._is_const(a):
            return float(self._PY_UN[op](float(a)))
        return self._un(op, a)

    # the vocabulary textures are written in
    def add(self, a, b): return self.binary("ADD", a, b)
    def sub(self, a, b): return self.binary("SUBTRACT", a, b)
    def mul(self, a, b): return self.binary("MULTIPLY", a, b)
    def div(self, a, b): return self.binary("DIVIDE", a, b)
    def pow(self, a, b): return self.binary("POWER", a, b)
    def min(self, a, b): return self.binary("MINIMUM", a, b)
    def max(self, a, b): return self.binary("MAXIMUM", a, b)
    def lt(self, a, b): return self.binary("LESS_THAN", a, b)  # 1.0 where a < b else 0.0
    def mod(self, a, b): return self.binary("FLOORED_MODULO", a, b)
    def floor(self, a): return self.unary("FLOOR", a)
    def sin(self, a): return self.unary("SINE", a)
    def abs(self, a): return self.unary("ABSOLUTE", a)

    def fract(self, a): return self.sub(a, self.floor(a))
    def clamp01(self, a): return self.min(self.max(a, 0.0), 1.0)

    def mix(self, f, a, b):
        """a + f (b - a): f = 0 gives a, f = 1 gives b."""
        return self.add(a, self.mul(f, self.sub(b, a)))

    def mix_rgb(self, f, a: RGB, b: RGB) -> RGB:
        return tuple(self.mix(f, x, y) for x, y in zip(a, b))

    def srgb_to_linear(self, c):
        """The sRGB decoding curve (IEC 61966-2-1), the inverse of what Cycles' Standard view applies."""
        low = self.div(c, 12.92)
        high = self.pow(self.div(self.add(c, 0.055), 1.055), 2.4)
        return self.mix(self.lt(c, 0.04045), high, low)

    def _bin(self, op, a, b):  # pragma: no cover - abstract
        raise NotImplementedError

    def _un(self, op, a):  # pragma: no cover - abstract
        raise NotImplementedError


class TorchOps(ExprOps):
    """Evaluates expressions on tensors [N] (the same float formulas as Blender's Math node)."""

    def _bin(self, op, a, b):
        if op == "ADD": return a + b
        if op == "SUBTRACT": return a - b
        if op == "MULTIPLY": return a * b
        if op == "DIVIDE":  # Blender's Math node returns 0 for a division by zero
            a, b = _tensors(a, b)
            nonzero = b != 0
            return torch.where(nonzero, a / torch.where(nonzero, b, torch.ones_like(b)), torch.zeros_like(a))
        if op == "POWER":  # only used with a positive base; Blender gives 0 for a <= 0 and fractional b
            a, b = _tensors(a, b)
            return torch.where(a > 0, a.clamp_min(1e-30) ** b, torch.zeros_like(a))
        if op == "MINIMUM": return torch.minimum(*_tensors(a, b))
        if op == "MAXIMUM": return torch.maximum(*_tensors(a, b))
        if op == "LESS_THAN":
            a, b = _tensors(a, b)
            return (a < b).to(a.dtype)
        if op == "FLOORED_MODULO":
            a, b = _tensors(a, b)
            return torch.where(b != 0, a - torch.floor(a / torch.where(b != 0, b, torch.ones_like(b))) * b,
                               torch.zeros_like(a))
        raise ValueError(op)

    def _un(self, op, a):
        if op == "FLOOR": return torch.floor(a)
        if op == "SINE": return torch.sin(a)
        if op == "ABSOLUTE": return torch.abs(a)
        if op == "SQRT": return torch.sqrt(a.clamp_min(0.0))
        raise ValueError(op)


def _dtype(a, b):
    return a.dtype if torch.is_tensor(a) else b.dtype


def _device(a, b):
    return a.device if torch.is_tensor(a) else b.device


def _tensors(a, b):
    dt, dev = _dtype(a, b), _device(a, b)
    return torch.as_tensor(a, dtype=dt, device=dev), torch.as_tensor(b, dtype=dt, device=dev)


# ---------------------------------------------------------------------------------------------------------------
# Textures: fn(g, ops, **params) -> (rgb, mask). g = (gx, gy, gz) Generated coordinates; rgb in display space;
# mask = None for a global texture (it replaces the colour everywhere), or a Scalar in [0, 1] for a local decal.

def _checker(g, o: ExprOps, scale=6.0, color_a=(0.92, 0.92, 0.88), color_b=(0.12, 0.16, 0.35)):
    cells = [o.floor(o.add(o.mul(c, scale), 0.25)) for c in g]
    parity = o.mod(o.add(o.add(cells[0], cells[1]), cells[2]), 2.0)
    return o.mix_rgb(parity, color_a, color_b), None


def _stripes(g, o: ExprOps, scale=8.0, axis=0, color_a=(0.95, 0.85, 0.2), color_b=(0.1, 0.45, 0.3)):
    band = o.mod(o.floor(o.add(o.mul(g[int(axis)], scale), 0.25)), 2.0)
    return o.mix_rgb(band, color_a, color_b), None


def _decal(g, o: ExprOps, center=(0.5, 0.5, 0.5), radius=0.2, weights=(1.0, 1.0, 1.0),
           color_a=(0.98, 0.1, 0.55), color_b=(0.1, 0.85, 0.95)):
    """A ball (weights select the axes: (1, 1, 0) makes a cylinder along z, a disc on a flat object) of two
    halves split at its centre along x, so rotations of the decal are visible."""
    d2 = 0.0
    for c, cc, w in zip(g, center, weights):
        if w:
            diff = o.sub(c, cc)
            d2 = o.add(d2, o.mul(w, o.mul(diff, diff)))
    mask = o.lt(d2, radius * radius)
    half = o.lt(g[0], center[0])
    return o.mix_rgb(half, color_a, color_b), mask


def _flag(g, o: ExprOps):
    """Three bands across the strip, a gold disc near one end and fine dark pinstripes along it."""
    red, white, blue, gold = (0.8, 0.15, 0.15), (0.95, 0.95, 0.9), (0.15, 0.25, 0.7), (0.95, 0.75, 0.1)
    low, high = o.lt(g[1], 1.0 / 3.0), o.sub(1.0, o.lt(g[1], 2.0 / 3.0))
    rgb = o.mix_rgb(high, o.mix_rgb(low, white, red), blue)
    dx, dy = o.sub(g[0], 0.25), o.sub(g[1], 0.5)
    disc = o.lt(o.add(o.mul(dx, dx), o.mul(dy, dy)), 0.15 * 0.15)
    rgb = o.mix_rgb(disc, rgb, gold)
    pin = o.lt(o.fract(o.add(o.mul(g[0], 16.0), 0.25)), 0.12)
    return tuple(o.mul(c, o.sub(1.0, o.mul(pin, 0.45))) for c in rgb), None


def _tiger(g, o: ExprOps):
    """Wavy bands over a front-to-back colour gradient (organic, and tells front from back)."""
    wave = o.add(o.mul(o.sin(o.mul(g[0], 9.0)), 0.6), o.mul(o.sin(o.mul(g[1], 7.0)), 0.4))
    band = o.lt(o.fract(o.add(o.mul(g[2], 7.0), wave)), 0.3)
    base = o.mix_rgb(g[1], (0.95, 0.55, 0.12), (0.95, 0.9, 0.45))
    return o.mix_rgb(band, base, (0.12, 0.08, 0.07)), None


def _planks(g, o: ExprOps, cells=12.0):
    """A fine two-tone wood checker with dark seams (the fine detail case)."""
    q = [o.add(o.mul(c, cells), 0.25) for c in g]
    parity = o.mod(o.add(o.add(o.floor(q[0]), o.floor(q[1])), o.floor(q[2])), 2.0)
    grain = o.mul(o.add(o.sin(o.mul(o.add(g[0], g[2]), 40.0)), 1.0), 0.5)  # in [0, 1]
    wood = o.mix_rgb(parity, (0.72, 0.5, 0.28), (0.55, 0.34, 0.16))
    wood = tuple(o.mul(c, o.add(0.85, o.mul(grain, 0.15))) for c in wood)
    seam = 0.0
    for c in q:
        f = o.fract(c)
        seam = o.max(seam, o.lt(o.abs(o.sub(f, 0.5)), 0.06))  # within 0.06 cell of a mid-cell seam line
    return o.mix_rgb(seam, wood, (0.18, 0.1, 0.05)), None


def _hash(o: ExprOps, a, b=0.0, c=0.0, seed=0.0):
    """A pseudo-random value in [0, 1) per integer lattice cell (a, b, c): fract(sin(dot) · 437.5453). The
    arguments stay small (cells index < ~40), so float32 sines agree between torch and Blender to ~1e-3."""
    dot = o.add(o.add(o.mul(a, 1.29898), o.mul(b, 7.8233)), o.add(o.mul(c, 3.7719), seed))
    return o.fract(o.mul(o.sin(dot), 437.5453))


def _flat(g, o: ExprOps, color_a=(0.78, 0.32, 0.18), color_b=(0.2, 0.42, 0.62), split=0.72):
    """Flat colours: one colour below Generated z = split, another above (a part's top in its own colour)."""
    return o.mix_rgb(o.lt(split, g[2]), color_a, color_b), None


def _gradient(g, o: ExprOps):
    """A smooth three-colour gradient along Generated z with a gentle ramp across x (no edges at all)."""
    t = o.clamp01(o.add(o.mul(g[2], 0.85), o.mul(g[0], 0.15)))
    low = o.mix_rgb(o.clamp01(o.mul(t, 2.0)), (0.85, 0.2, 0.35), (0.95, 0.75, 0.3))
    return o.mix_rgb(o.clamp01(o.sub(o.mul(t, 2.0), 1.0)), low, (0.2, 0.55, 0.85)), None


def _noise_field(g, o: ExprOps, freq=9.0):
    """A smooth pseudo-noise in [0, 1]: three octaves of products of sines along skewed directions."""
    total, amp = 0.0, 0.5
    for k, (a, b, c) in enumerate(((1.0, 0.6, 0.3), (-0.4, 1.0, 0.7), (0.5, -0.8, 1.0))):
        f = freq * (1.9 ** k)
        u = o.add(o.add(o.mul(g[0], a * f), o.mul(g[1], b * f)), o.add(o.mul(g[2], c * f), 0.7 * k))
        v = o.add(o.add(o.mul(g[1], a * f), o.mul(g[2], b * f)), o.add(o.mul(g[0], c * f), 1.3 * k))
        total = o.add(total, o.mul(o.mul(o.sin(u), o.sin(v)), amp))
        amp *= 0.55
    return o.clamp01(o.add(o.mul(total, 0.9), 0.5))


def _noise(g, o: ExprOps):
    """High-frequency pseudo-noise mapped through three colours (mossy / marbled)."""
    n = _noise_field(g, o)
    low = o.mix_rgb(o.clamp01(o.mul(n, 2.0)), (0.1, 0.25, 0.12), (0.45, 0.62, 0.2))
    return o.mix_rgb(o.clamp01(o.sub(o.mul(n, 2.0), 1.0)), low, (0.93, 0.88, 0.6)), None


def _cells(g, o: ExprOps, scale=5.0):
    """Voronoi cells: every point takes the colour of the nearest of one jittered seed per lattice cell, searched
    over the 2 × 2 × 2 cells nearest the point (8 instead of 27: the shader stays small enough for Cycles to
    compile quickly; the pattern is defined by this search, so torch and Blender still agree), with dark borders
    where the nearest two seeds are about as near."""
    q = [o.add(o.mul(c, scale), 0.25) for c in g]
    base = [o.floor(o.sub(c, 0.5)) for c in q]
    best, second, col = 9.0, 9.0, (0.0, 0.0, 0.0)
    for dx in (0.0, 1.0):
        for dy in (0.0, 1.0):
            for dz in (0.0, 1.0):
                cell = (o.add(base[0], dx), o.add(base[1], dy), o.add(base[2], dz))
                seed = [o.add(cell[i], o.add(0.15, o.mul(_hash(o, *cell, seed=float(i)), 0.7))) for i in range(3)]
                d2 = 0.0
                for i in range(3):
                    diff = o.sub(q[i], seed[i])
                    d2 = o.add(d2, o.mul(diff, diff))
                nearer = o.lt(d2, best)
                h = _hash(o, *cell, seed=5.0)
                c = (o.add(0.2, o.mul(h, 0.75)), o.add(0.25, o.mul(_hash(o, *cell, seed=6.0), 0.6)),
                     o.sub(0.95, o.mul(h, 0.7)))
                second = o.min(second, o.max(d2, best))
                col = o.mix_rgb(nearer, col, c)
                best = o.min(best, d2)
    border = o.lt(o.sub(second, best), 0.12)
    return o.mix_rgb(border, col, (0.08, 0.07, 0.1)), None


def _bricks(g, o: ExprOps, rows=9.0, per_row=5.0):
    """Running-bond bricks around the object: rows along Generated z, every other row shifted by half a brick,
    light mortar, each brick's red varied by a hash."""
    zr = o.add(o.mul(g[2], rows), 0.25)
    row = o.floor(zr)
    shift = o.mul(o.mod(row, 2.0), 0.5)
    u = o.add(o.mul(o.add(g[0], g[1]), per_row), o.add(shift, 0.25))
    brick = o.floor(u)
    mortar = o.max(o.lt(o.fract(zr), 0.12), o.lt(o.fract(u), 0.08))
    h = _hash(o, brick, row, 0.0, seed=2.0)
    red = (o.add(0.55, o.mul(h, 0.3)), o.add(0.2, o.mul(h, 0.12)), o.add(0.12, o.mul(h, 0.06)))
    return o.mix_rgb(mortar, red, (0.85, 0.83, 0.78)), None


def _fine_lines(g, o: ExprOps, scale=28.0):
    """Fine dark lines on a light ground: 28 per Generated unit along z, a few pixels apart at 128²."""
    line = o.lt(o.fract(o.add(o.mul(g[2], scale), 0.25)), 0.3)
    return o.mix_rgb(line, (0.92, 0.9, 0.82), (0.15, 0.12, 0.3)), None


def _small_text(g, o: ExprOps, lines=16.0, chars=36.0, background=(0.96, 0.95, 0.92), ink=(0.12, 0.12, 0.16)):
    """Rows of tiny glyph-like marks (a 3 × 4 dot bitmap per character, dots set by a hash, gaps between words)
    on near-white paper: small text, near-white on a white background."""
    a, b = o.add(o.mul(g[0], chars), 0.25), o.add(o.mul(g[1], lines), 0.25)
    col, row = o.floor(a), o.floor(b)
    fa, fb = o.fract(a), o.fract(b)
    in_glyph = o.mul(o.mul(o.lt(0.1, fa), o.lt(fa, 0.85)), o.mul(o.lt(0.2, fb), o.lt(fb, 0.8)))
    sx, sy = o.floor(o.mul(o.sub(fa, 0.1), 4.0)), o.floor(o.mul(o.sub(fb, 0.2), 6.6666))
    dot = o.lt(_hash(o, o.add(o.mul(col, 3.0), sx), o.add(o.mul(row, 4.0), sy), 0.0, seed=3.0), 0.35)
    word = o.lt(0.18, _hash(o, col, row, 1.0, seed=4.0))  # ~1 in 6 characters is a space
    return o.mix_rgb(o.mul(o.mul(in_glyph, dot), word), background, ink), None


def _near_black(g, o: ExprOps):
    """Near-black rubber with a dark-grey tread of diagonal ribs (detail that is hard to see)."""
    rib = o.lt(o.fract(o.add(o.mul(o.add(g[0], g[2]), 10.0), 0.25)), 0.35)
    return o.mix_rgb(rib, (0.05, 0.05, 0.06), (0.2, 0.2, 0.22)), None


def _multi(g, o: ExprOps):
    """A rich multi-colour mix: Voronoi cells in one band, bricks in another, noise between (the kind of texture a
    decoder must not flatten)."""
    cells, _ = _cells(g, o, scale=4.0)
    bricks, _ = _bricks(g, o, rows=12.0, per_row=7.0)
    noise, _ = _noise(g, o)
    band = o.fract(o.mul(g[0], 3.0))
    first, second = o.lt(band, 0.34), o.lt(band, 0.67)
    return o.mix_rgb(first, o.mix_rgb(second, noise, bricks), cells), None


@dataclasses.dataclass(frozen=True)
class Texture:
    name: str
    fn: Callable
    local: bool  # True: a decal with a mask, composited over the base colour
    help: str


TEXTURES: dict[str, Texture] = {t.name: t for t in [
    Texture("checker", _checker, False, "global retexture: 3-D checker of two colours, 6 cells per box side"),
    Texture("stripes", _stripes, False, "global retexture: stripes of two colours along Generated x, 8 per side"),
    Texture("decal", _decal, True, "local edit: a two-tone ball/disc at a Generated centre over the base texture"),
    Texture("flag", _flag, False, "base texture of `cloth`: bands, a disc and fine pinstripes"),
    Texture("tiger", _tiger, False, "base texture of `suzanne`: wavy bands over a gradient"),
    Texture("planks", _planks, False, "base texture of `crate`: fine checker with seams and grain"),
    Texture("flat", _flat, False, "flat colours: one below Generated z = 0.72, another above"),
    Texture("gradient", _gradient, False, "a smooth three-colour gradient (no edges)"),
    Texture("noise", _noise, False, "high-frequency pseudo-noise through three colours"),
    Texture("cells", _cells, False, "Voronoi cells with hashed colours and dark borders"),
    Texture("bricks", _bricks, False, "running-bond bricks with mortar, hashed reds"),
    Texture("fine_lines", _fine_lines, False, "fine dark lines, 28 per Generated unit along z"),
    Texture("small_text", _small_text, False, "rows of tiny glyph-like marks on near-white paper"),
    Texture("near_black", _near_black, False, "near-black with dark-grey diagonal ribs"),
    Texture("multi", _multi, False, "cells, bricks and noise in three bands (rich multi-colour)"),
]}


def get_texture(name: str) -> Texture:
    if name not in TEXTURES:
        raise InputError(f"unknown texture '{name}'; choose one of {', '.join(TEXTURES)}")
    return TEXTURES[name]


def build_expression(name: str, g, ops: ExprOps, params: dict | None = None):
    """Run texture `name` on Generated coordinates `g` (3 Scalars) with a backend; returns (rgb, mask|None)."""
    tex = get_texture(name)
    return tex.fn(tuple(g), ops, **(params or {}))


def generated_coords(points: torch.Tensor, center, half_size) -> torch.Tensor:
    """Blender's Generated coordinates of rest-pose points.

    Args: points [N, 3] rest-pose object/world coordinates; center [3], half_size [3] of the rest bounding box
    (Blender's mesh texture space). A zero (or tiny) half size counts as 1, as in Blender. Returns [N, 3].
    """
    if points.ndim != 2 or points.shape[-1] != 3:
        raise InputError(f"points must be [N, 3], got {tuple(points.shape)}")
    c = torch.as_tensor(center, dtype=points.dtype, device=points.device).reshape(3)
    h = torch.as_tensor(half_size, dtype=points.dtype, device=points.device).reshape(3)
    h = torch.where(h.abs() > 1e-6, h, torch.ones_like(h))
    return ((points - c) / h + 1.0) * 0.5


def evaluate(name: str, points: torch.Tensor, center, half_size, params: dict | None = None):
    """Colour of texture `name` at rest-pose points.

    Args: points [N, 3] rest-pose coordinates; center [3], half_size [3] the rest bounding box; params override
    the texture's defaults (e.g. a decal's center/radius, in Generated units).
    Returns rgb [N, 3] display-space (sRGB) in [0, 1] and mask [N] in [0, 1] (all ones for a global texture).
    Non-finite input points get mask 0 and a finite colour.
    """
    finite = torch.isfinite(points).all(dim=-1)
    pts = torch.where(finite[:, None], points, torch.zeros_like(points))
    g = generated_coords(pts, center, half_size)
    rgb, mask = build_expression(name, g.unbind(-1), TorchOps(), params)
    n = points.shape[0]
    rgb = torch.stack([torch.as_tensor(c, dtype=points.dtype).expand(n) if not torch.is_tensor(c) else c
                       for c in rgb], dim=-1).clamp(0.0, 1.0)
    if mask is None:
        mask = torch.ones(n, dtype=points.dtype, device=points.device)
    elif not torch.is_tensor(mask):
        mask = torch.full((n,), float(mask), dtype=points.dtype, device=points.device)
    return rgb, mask * finite.to(points.dtype)


def composite(base_rgb: torch.Tensor, rgb: torch.Tensor, mask: torch.Tensor) -> torch.Tensor:
    """Decal over base in display space: base [N, 3], rgb [N, 3], mask [N] -> [N, 3]."""
    m = mask[..., None]
    return base_rgb + m * (rgb - base_rgb)
