"""Shading that follows the pose, for lit models (EditConfig.reshade; docs/editing.md "Lit scenes").

A model fitted to a lit scene carries its rest pose's light in its colours: a part the pose turns keeps the light
it had, where the scene's light would shade it by its new normal. No light is known, so the shading is estimated
from the model itself as a function of the surface normal, S(n) = exp(b · Y(n)), Y the real spherical harmonics of
orders 1 and 2 (8 terms; the constant cancels): over canonical neighbour pairs of one chromaticity (every channel's
log colour minus their mean within `chroma`: the same paint, so a brightness change between them is shading) the
log luminance difference is fitted robustly (Huber, iteratively reweighted) by the difference of b · Y. Pairs across
a paint edge of another chromaticity do not enter; a texture of one chromaticity in several brightnesses (dark
lines on white) is an outlier the robust fit mostly ignores.

`atlas_shading` takes the colours from the model's own atlas (each canonical point: the mean colour its nearest
stored surface samples read) and orients each point's normal (its neighbourhood's least-spread direction) away from
the centre of its 64 nearest points; `reshade_factor` gives a posed ray's S(posed normal) / S(rest normal).
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch

from core.edits.deformation import field_for

HUBER = 1.345  # the Huber threshold in robust standard deviations
RATIO_RANGE = (0.2, 5.0)  # the re-shading factor's bounds
ORIENT_POINTS = 64  # nearest canonical points whose centre a point's normal is turned away from
RESHADE_MIN_RANGE = 0.12  # reshade auto: the fitted log S range (5–95 %) from which a model counts as lit


def sh_basis(n: torch.Tensor) -> torch.Tensor:
    """Real spherical harmonics of orders 1 and 2 (unnormalised) of unit vectors n [M, 3] -> [M, 8]."""
    x, y, z = n[:, 0], n[:, 1], n[:, 2]
    return torch.stack([x, y, z, x * y, y * z, x * z, x * x - y * y, 3 * z * z - 1], 1)


def fit_shading(colour: torch.Tensor, normals: torch.Tensor, pairs: torch.Tensor, chroma: float = 0.1,
                iterations: int = 10) -> tuple[torch.Tensor, int]:
    """The log-shading coefficients b [8] float64 (log S(n) = b · sh_basis(n)) from per-point linear colours [N, 3]
    (> 0 where seen), oriented unit normals [N, 3] and neighbour pairs [P, 2] long (module doc). Returns (b, the
    number of pairs used); b = 0 below 16 pairs of one chromaticity."""
    lc = torch.log(colour.double().clamp_min(1e-3))
    lum = lc.mean(1)
    chrom = lc - lum[:, None]
    i, j = pairs[:, 0], pairs[:, 1]
    same = (chrom[i] - chrom[j]).abs().max(1).values < chroma
    i, j = i[same], j[same]
    n = normals.double()
    nj = torch.where(((n[i] * n[j]).sum(1, keepdim=True) < 0), -n[j], n[j])  # the neighbour's normal, same side
    if i.numel() < 16:
        return torch.zeros(8, dtype=torch.float64), int(i.numel())
    dl = lum[i] - lum[j]
    dy = sh_basis(n[i]) - sh_basis(nj)
    w = torch.ones_like(dl)
    b = torch.zeros(8, dtype=torch.float64)
    for _ in range(iterations):
        sw = w.sqrt()
        b = torch.linalg.lstsq(dy * sw[:, None], dl * sw).solution
        r = dl - dy @ b
        scale = 1.4826 * r.abs().median().clamp_min(1e-6)
        w = torch.where(r.abs() <= HUBER * scale, torch.ones_like(r), HUBER * scale / r.abs())
    return b, int(i.numel())


def reshade_factor(f: torch.Tensor, normals: torch.Tensor, dirs: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
    """S(posed) / S(rest) [M] float64 for rays with the local gradient f [M, 3, 3] and canonical normal [M, 3] of
    their most-attended neighbour and directions dirs [M, 3]: the posed normal F⁻ᵀ n turned towards the camera, the
    rest normal Fᵀ of that; within RATIO_RANGE, 1 where F is singular or the ratio not finite."""
    fd, n = f.double(), normals.double()
    posed, info = torch.linalg.solve_ex(fd.transpose(1, 2), n[..., None])
    posed = torch.nn.functional.normalize(posed.squeeze(-1), dim=-1)
    posed = torch.where(((posed * dirs.double()).sum(1, keepdim=True) > 0), -posed, posed)  # facing the camera
    rest = torch.nn.functional.normalize((fd.transpose(1, 2) @ posed[..., None]).squeeze(-1), dim=-1)
    ratio = torch.exp(sh_basis(posed) @ b.double() - sh_basis(rest) @ b.double()).clamp(*RATIO_RANGE)
    ok = (info == 0) & torch.isfinite(ratio)
    return torch.where(ok, ratio, torch.ones_like(ratio))


@dataclass
class Shading:
    """A fitted shading: coefficients b [8] float64, `log_range` the 5–95 % range of log S over the model's seen
    points (0: no shading found), `pairs` the neighbour pairs of one chromaticity the fit used."""

    b: torch.Tensor
    log_range: float
    pairs: int


def atlas_shading(bundle) -> Shading | None:
    """The model's shading fitted to its atlas's colours (module doc), once per atlas (cached on it); None when the
    model has no atlas or its atlas keeps no surface samples."""
    from scipy.spatial import cKDTree

    from core.atlas.sample_lookup import keeps_samples, sample_lookup
    from core.images.colour import srgb_to_linear

    atlas = bundle.atlas
    if not keeps_samples(atlas):
        return None
    cached = getattr(atlas, "_shading", None)
    if cached is not None and cached[0] is atlas.bake_samples:
        return cached[1]
    lk = sample_lookup(atlas)
    colour = srgb_to_linear(lk.read(atlas.chart_textures.detach().clamp(0, 1).cpu()).clamp(0, 1)).double()
    xyz = bundle.model.xyz.detach().cpu().double()
    samples = lk.samples.double()
    _, around = cKDTree(xyz.numpy()).query(samples.numpy(), k=min(ORIENT_POINTS, xyz.shape[0]))
    around = torch.from_numpy(np.asarray(around)).long().reshape(len(samples), -1)  # nearest first
    nearest = around[:, 0]
    outward = samples - xyz[around].mean(1)
    n_pts = xyz.shape[0]
    count = torch.zeros(n_pts, dtype=torch.float64).index_add_(0, nearest, torch.ones(len(nearest),
                                                                                      dtype=torch.float64))
    mean = torch.zeros(n_pts, 3, dtype=torch.float64).index_add_(0, nearest, colour) / count.clamp_min(1)[:, None]
    side = torch.zeros(n_pts, 3, dtype=torch.float64).index_add_(0, nearest, outward)
    fld = field_for(bundle.model)
    normals = fld.normals().cpu().double()
    normals = torch.where(((normals * side).sum(1, keepdim=True) < 0), -normals, normals)
    seen = count > 0
    nbr = fld.nbr.cpu()
    rows = torch.arange(n_pts)[:, None].expand_as(nbr)
    ok = (nbr >= 0) & seen[:, None] & seen[nbr.clamp_min(0)]
    b, used = fit_shading(mean, normals, torch.stack([rows[ok], nbr[ok]], 1))
    log_s = sh_basis(normals[seen]) @ b
    spread = float(log_s.quantile(0.95) - log_s.quantile(0.05)) if log_s.numel() else 0.0
    shading = Shading(b=b, log_range=spread, pairs=used)
    atlas._shading = (atlas.bake_samples, shading)
    return shading
