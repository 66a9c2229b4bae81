"""Charts split by side: one island set per orientation of a chart's map on the surface.

A chart map t_c that lays two sides of a part over each other (the ring's outer and inner wall, docs/atlas.md "Why
the texel maps fold") is locally smooth but two-to-one; the two sides have opposite orientation against the
surface's normals given one side (`SurfaceProjection.orient`). Splitting every chart c into two sub-charts, 2c (the
chart's majority orientation) and 2c + 1 (reversed), by the sign of that orientation at the point gives each side
its own islands and its own texels.

The orientation at a point x with unit normal n (tangent basis t1, t2 with t1 x t2 = n) is

    rho_c(x) = det[a b] / (|du| |dv|),  a = (t_c(x + h t1) - t_c(x)) / h,  b = (t_c(x + h t2) - t_c(x)) / h,

with du = (a_u, b_u) and dv = (a_v, b_v) the gradients of u and v along the surface: (du x dv) . n over |du| |dv|,
as `core.atlas.fit.fold_report` measures it (|rho| small: a crease, where the map turns over), by forward differences of
width h (a few sample spacings: a smoothed orientation, which keeps the sub-chart a point picks stable where the
map is noisy). A point is reversed in chart c when majority_c * rho_c(x) < -crease: creases (|rho| small) and
points without a normal (no anchor plane nearby: rho = 0) stay in the majority sub-chart. The same function of the
point decides baking (the texel map, the texture) and every lookup, so a texel's point maps back to its own
sub-chart. Finite for any finite input: degenerate differences (a map constant along the surface) and zero normals
give rho = 0.
"""
from __future__ import annotations

import numpy as np
import torch

from core.atlas.surface import SurfaceProjection
from core.util.errors import InputError


def tangent_basis(normals: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """Unit normals [M, 3] -> (t1, t2) [M, 3] each, orthonormal with t1 x t2 = n; zero where n is zero or not
    finite."""
    n = torch.nan_to_num(normals, nan=0.0, posinf=0.0, neginf=0.0)
    unit = n.norm(dim=-1, keepdim=True) > 0.5
    # the coordinate axis least aligned with n, so the cross product is never small
    axis = torch.nn.functional.one_hot(n.abs().argmin(-1), 3).to(n.dtype)
    t1 = torch.linalg.cross(n, axis)
    t1 = t1 / t1.norm(dim=-1, keepdim=True).clamp_min(1e-12)
    t2 = torch.linalg.cross(n, t1)
    zero = torch.zeros_like(n)
    return torch.where(unit, t1, zero), torch.where(unit, t2, zero)


def orientation(tex, xn: torch.Tensor, normals: torch.Tensor, h: float,
                uv0: torch.Tensor | None = None) -> torch.Tensor:
    """rho [M, n] of every chart's map at network-frame points xn [M, 3] with unit normals [M, 3] (world frame
    directions; zero: rho 0), by forward differences of width h (network units). tex: xn [M, 3] -> uv [M, n, 2];
    uv0: tex(xn) when the caller has it already. In [-1, 1]; 0 where the differences are degenerate or not finite."""
    t1, t2 = tangent_basis(normals.to(xn.dtype))
    uv0 = tex(xn) if uv0 is None else uv0
    a = (tex(xn + h * t1) - uv0) / h                                       # [M, n, 2]
    b = (tex(xn + h * t2) - uv0) / h
    det = a[..., 0] * b[..., 1] - a[..., 1] * b[..., 0]
    du, dv = torch.stack([a[..., 0], b[..., 0]], -1), torch.stack([a[..., 1], b[..., 1]], -1)
    norm = du.norm(dim=-1) * dv.norm(dim=-1)
    rho = det / norm.clamp_min(1e-30)
    ok = torch.isfinite(rho) & (norm > 1e-20)
    return torch.where(ok, rho.clamp(-1.0, 1.0), torch.zeros_like(rho))


class ChartSides:
    """The side rule of a split atlas: surface (a SurfaceProjection whose normals have one side; used for normals
    only, never to move points), majority [n] +-1 (the orientation most of chart c's samples have; 0: chart c is
    not split, every point stays on 2c), step h
    (network units), crease (reversed only where majority * rho < -crease).

    reversed(tex, xn [M, 3], world [M, 3]) -> [M, n] bool; expand(probs [M, n], uv [M, n, 2], rev [M, n]) ->
    (probs [M, 2n], uv [M, 2n, 2]) over the sub-charts 2c (majority side) and 2c + 1 (reversed).
    """

    def __init__(self, surface: SurfaceProjection, majority, step: float, crease: float = 0.0):
        m = np.asarray(majority, dtype=np.float32).reshape(-1)
        if not (len(m) >= 1 and np.isin(m, (-1.0, 0.0, 1.0)).all()):
            raise InputError(f"chart sides: majority must hold +1, -1 or 0 (not split) per chart, got "
                             f"{m.tolist()[:8]}")
        if not (0 < float(step) < float("inf")) or not (0 <= float(crease) < 1):
            raise InputError(f"chart sides: step must be positive and finite and 0 <= crease < 1, got {step!r}, "
                             f"{crease!r}")
        self.surface, self.majority = surface, torch.from_numpy(m.copy())
        self.step, self.crease = float(step), float(crease)

    @property
    def n(self) -> int:
        return len(self.majority)

    def rho(self, tex, xn: torch.Tensor, world: torch.Tensor, uv0: torch.Tensor | None = None) -> torch.Tensor:
        """Orientation [M, n] of every chart at xn (network frame) / world (the same points in world units);
        uv0: tex(xn) when the caller has it."""
        normals = self.surface.normals_at(world).to(xn.device)
        return orientation(tex, xn, normals, self.step, uv0)

    def reversed(self, tex, xn: torch.Tensor, world: torch.Tensor, uv0: torch.Tensor | None = None) -> torch.Tensor:
        """[M, n] bool: the point lies on chart c's reversed side (uv0: tex(xn) when the caller has it)."""
        if not bool((self.majority != 0).any()):
            return torch.zeros(xn.shape[0], self.n, dtype=torch.bool, device=xn.device)
        rho = self.rho(tex, xn, world, uv0)
        return rho * self.majority.to(rho.device, rho.dtype) < -self.crease

    @staticmethod
    def expand(probs: torch.Tensor, uv: torch.Tensor, rev: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """Network outputs over n charts -> over 2n sub-charts: P(2c) = P(c) on the majority side, P(2c + 1) = P(c)
        on the reversed side (0 on the other), both with chart c's coordinates."""
        r = rev.to(probs.dtype)
        p2 = torch.stack([probs * (1 - r), probs * r], -1).reshape(probs.shape[0], -1)
        return p2, uv.repeat_interleave(2, dim=1)

    @staticmethod
    def majority_of(rho: torch.Tensor, probs: torch.Tensor) -> np.ndarray:
        """The P-weighted majority sign [n] of rho [S, n] over samples with chart probabilities probs [S, n] (each
        sample counted in its most probable chart); +1 where a chart has no samples or a tie."""
        chart = probs.argmax(-1)
        out = np.ones(probs.shape[1], np.float32)
        for c in range(probs.shape[1]):
            m = chart == c
            if bool(m.any()) and float(torch.sign(rho[m, c]).sum()) < 0:
                out[c] = -1.0
        return out

    # --- storage ---------------------------------------------------------------------------------------------------
    def to_arrays(self) -> dict[str, np.ndarray]:
        return {"atlas/sides/centres": self.surface.centres.astype(np.float32),
                "atlas/sides/normals": self.surface.normals.astype(np.float32),
                "atlas/sides/majority": self.majority.numpy().astype(np.float32)}

    def meta(self) -> dict:
        return {"bandwidth": self.surface.bandwidth, "k": self.surface.k, "step": self.step, "crease": self.crease}

    @classmethod
    def from_arrays(cls, arrays: dict, meta: dict) -> "ChartSides":
        surf = SurfaceProjection(arrays["atlas/sides/centres"], arrays["atlas/sides/normals"],
                                 float(meta["bandwidth"]), int(meta.get("k", 8)))
        return cls(surf, arrays["atlas/sides/majority"], float(meta["step"]), float(meta.get("crease", 0.0)))
