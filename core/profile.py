"""Scene profile: leave out what a scene does not need, decided from the training images before stage 1.

Measured from the data (all numbers are returned with the choices, JSON-able):
- view dependence: the colour of the same surface point seen from different views. Surface points are visual-hull
  points (core/points/init.py) that survive a coarse z-buffer depth test in a view; each contributes the pixel it
  lands on where the object is opaque. `view_variation` = mean over points of the RGB standard deviation across
  the views that see the point, minus the local contrast of the image there (a busy texture, where a hull point a
  pixel off the surface samples a different colour per view, does not read as view dependence). It is reported
  (with a hint above VIEW_DEPENDENT_ABOVE on a solid object) but never switches view-dependent values on by
  itself: on concave objects with a busy texture the visual hull lies off the surface and the measure grows with
  the texture (the unlit Suzanne of the scene library measures above the lit blob), while view-dependent values
  halve the steps a time budget buys and gained at most 0.15 dB on the library at 10 minutes (docs/results.md,
  "Scene profile"). `--view-dependent` turns them on.
- the decoder: the residual UNet (core/points/decoders.py) on every scene. It starts as the decoder-free render,
  so choosing it risks no collapse, and at the default 10-minute budget it is ahead of no decoder, or within
  0.2 dB of it, on every scene of the library (docs/results.md, "Scene library": `python -m tools.bench.scenes`).
  Leaving it out where there are few foreground pixels per point measured worse: the thin `stick` (0.09) lost
  5.5 dB without it (the decoder-free fit peaks in its first minute and then declines on the test views).
  Foreground pixels per point (per view / the number of points) is still measured and reported.
- thin sheets: the mean out-of-plane spread of the visual hull's clusters (`flatness` of core/atlas/fit.py, on the
  hull's volume points): a sheet's hull is a thin slab (low), a solid's hull is chunky (high). Thin → K = 40
  (the reference's cloth setting), else K = 20.
- atlas charts: the atlas's own auto rule (`choose_chart_count`, core/atlas/fit.py) applied to the visible
  surface points.
`apply_profile` writes the choices into ModelConfig / AtlasConfig without touching fields the user set.
"""
from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass, field

import torch
import torch.nn.functional as F

from core.atlas.config import AtlasConfig
from core.atlas.fit import choose_chart_count, flatness
from core.images.cameras import focal_scale, project_points
from core.points.init import visual_hull_points
from core.points.model import ModelConfig, mean_spacing
from core.util.errors import DataError

VIEW_DEPENDENT_ABOVE = 0.025  # view_variation above this on a solid object: the hint that colours may depend on the
# view (analytic test scenes: unlit ≤ 0.013, glossy ≥ 0.04; tests/core/test_profile.py). Only a hint: see above.
THIN_SHEET_BELOW = 0.3  # hull flatness below this: a thin sheet
K_DEFAULT, K_THIN = 20, 40


@dataclass
class SceneProfile:
    """Choices (decoder, view_dependent, k, charts) and the measurements behind them (all JSON-able)."""

    decoder: str
    view_dependent: bool
    k: int
    charts: str
    measured: dict = field(default_factory=dict)

    def to_dict(self) -> dict:
        return dataclasses.asdict(self)


def surface_colour_samples(images: torch.Tensor, alphas: torch.Tensor, c2w: torch.Tensor, focal: float,
                           points: torch.Tensor, depth_tol: float, cell_px: int, min_alpha: float = 0.99):
    """Which points each view sees, and the colour it sees them with.

    images [V, H, W, 3], alphas [V, H, W], c2w [V, 4, 4], points [M, 3]. A point is visible in a view when it lies
    within depth_tol of the nearest point projecting into the same cell_px × cell_px cell (a coarse z-buffer) and
    its pixel is opaque (alpha ≥ min_alpha). Returns point index [S], view index [S], rgb [S, 3] and the local
    contrast [S] (RGB std over the sample's 3 × 3 pixel neighbourhood) per sample.
    """
    v, h, w = alphas.shape
    im = images.permute(0, 3, 1, 2).float()
    mu = F.avg_pool2d(im, 3, 1, 1, count_include_pad=False)
    mu2 = F.avg_pool2d(im * im, 3, 1, 1, count_include_pad=False)
    contrast = (mu2 - mu * mu).clamp_min(0).sum(1).sqrt()  # [V, H, W]
    pid, vid, rgb, loc = [], [], [], []
    ch, cw = math.ceil(h / cell_px), math.ceil(w / cell_px)
    for i in range(v):
        px, depth = project_points(points, c2w[i].float(), h, w, focal)
        col, row = px[:, 0].floor().long(), px[:, 1].floor().long()
        ok = (depth > 0) & (col >= 0) & (col < w) & (row >= 0) & (row < h)
        idx = torch.nonzero(ok).squeeze(1)
        if idx.numel() == 0:
            continue
        r, c, z = row[idx], col[idx], depth[idx]
        cell = (r // cell_px) * cw + (c // cell_px)
        zbuf = torch.full((ch * cw,), float("inf")).scatter_reduce(0, cell, z, "amin")
        vis = (z <= zbuf[cell] + depth_tol) & (alphas[i, r, c] >= min_alpha)
        idx, r, c = idx[vis], r[vis], c[vis]
        pid.append(idx)
        vid.append(torch.full_like(idx, i))
        rgb.append(images[i, r, c].float())
        loc.append(contrast[i, r, c])
    if not pid:
        return torch.zeros(0, dtype=torch.long), torch.zeros(0, dtype=torch.long), torch.zeros(0, 3), torch.zeros(0)
    return torch.cat(pid), torch.cat(vid), torch.cat(rgb), torch.cat(loc)


def view_variation(pid: torch.Tensor, rgb: torch.Tensor, contrast: torch.Tensor, n_points: int,
                   min_views: int = 3) -> dict:
    """Cross-view colour spread beyond what the texture explains: pid [S], rgb [S, 3], contrast [S] -> dict(
    view_std (median over points seen in ≥ min_views views of the RGB std across those views), local_contrast
    (median over the same points of their mean local contrast), view_variation (mean over points of
    max(0, view_std − local contrast)), points_compared). A point position off by about a pixel changes an
    unlit colour by about the local contrast; what exceeds it comes from the viewing direction."""
    count = torch.bincount(pid, minlength=n_points).float()
    s1 = torch.zeros(n_points, 3).index_add_(0, pid, rgb.float())
    s2 = torch.zeros(n_points, 3).index_add_(0, pid, rgb.float() ** 2)
    sc = torch.zeros(n_points).index_add_(0, pid, contrast.float())
    seen = count >= min_views
    if not bool(seen.any()):
        return {"view_std": 0.0, "local_contrast": 0.0, "view_variation": 0.0, "points_compared": 0}
    mean = s1[seen] / count[seen, None]
    std = (s2[seen] / count[seen, None] - mean ** 2).clamp_min(0).sum(1).sqrt()  # RGB std summed over channels
    local = sc[seen] / count[seen]
    return {"view_std": float(std.median()), "local_contrast": float(local.median()),
            "view_variation": float((std - local).clamp_min(0).mean()), "points_compared": int(seen.sum())}


def scene_profile(train, hull_points: int = 3000, seed: int = 0, device: str = "cpu",
                  num_points: int | None = None) -> SceneProfile:
    """Measure a training split (SplitData: images [V, H, W, 3], alphas [V, H, W], c2w [V, 4, 4], focal) and
    choose decoder, K and the atlas chart count (view dependence: measured, a hint only). num_points: the model's
    point count (default: ModelConfig's). Deterministic for a given seed."""
    views = int(train.images.shape[0])
    if views < 2:
        raise DataError(f"scene profile: needs at least 2 training views to compare, got {views}")
    pts = visual_hull_points(train.alphas, train.c2w, train.focal, hull_points, seed=seed, batch=50_000)
    spacing = mean_spacing(pts)
    dist = float(train.c2w[:, :3, 3].norm(dim=1).median())
    spacing_px = spacing * focal_scale(train.focal) / max(dist, 1e-9)
    cell = max(1, math.ceil(2.0 * spacing_px))  # a few hull points per cell: its front one is found
    pid, _, rgb, contrast = surface_colour_samples(train.images, train.alphas, train.c2w, train.focal, pts,
                                                   2.0 * spacing, cell)
    var = view_variation(pid, rgb, contrast, pts.shape[0])
    hull_flat = flatness(pts)
    visible = torch.unique(pid)
    surface = pts[visible] if visible.numel() >= 64 else pts
    n_charts, surface_flat = choose_chart_count(surface, AtlasConfig())
    thin = hull_flat < THIN_SHEET_BELOW
    # On a thin folded sheet the visual hull lies off the surface, so "the same hull point" seen from two views
    # is two different surface points: the cross-view colour spread then measures texture, not view dependence
    # (the emission cloth scene measures 0.099). Trust the measure only on solid objects.
    hint = var["view_variation"] > VIEW_DEPENDENT_ABOVE and not thin
    points = int(num_points) if num_points else ModelConfig().num_points
    pixels_per_point = float((train.alphas > 0.5).float().sum(dim=(1, 2)).mean()) / max(points, 1)
    measured = {**var, "pixels_per_point": pixels_per_point, "hull_flatness": hull_flat,
                "surface_flatness": surface_flat, "hull_points": pts.shape[0],
                "surface_points": int(visible.numel()), "point_spacing": spacing, "zbuffer_cell_px": cell,
                "thresholds": {"view_variation": VIEW_DEPENDENT_ABOVE, "hull_flatness": THIN_SHEET_BELOW},
                "view_variation_trusted": not thin, "view_dependent_hint": hint}
    # K: the reference uses 40 for thin cloth. Doubling K doubles the attention cost per step; on a CPU under a
    # fixed time budget that loses more than it gains (cloth, 10 min: K = 40 reached 23.0 dB object PSNR in 772
    # steps, K = 20 passed that in its first 3 minutes), so thin sheets get K = 40 only on a GPU.
    gpu = str(device).startswith("cuda")
    measured["k_rule"] = "thin sheet on a GPU: 40; otherwise 20"
    measured["decoder_rule"] = "unet (residual) on every scene"
    measured["view_dependent_rule"] = "off unless --view-dependent (the measure is a hint only)"
    return SceneProfile(decoder="unet", view_dependent=False,
                        k=K_THIN if (thin and gpu) else K_DEFAULT, charts=str(n_charts), measured=measured)


def explicit_fields(args, cls, prefix: str = "") -> set[str]:
    """Field names of config class `cls` the user set on the command line (core.config flags default to None)."""
    return {f.name for f in dataclasses.fields(cls)
            if getattr(args, (f"{prefix}_" if prefix else "") + f.name, None) is not None}


def _defaults(cls) -> dict:
    return {f.name: (f.default if f.default is not dataclasses.MISSING else f.default_factory())
            for f in dataclasses.fields(cls)}


def apply_profile(profile: SceneProfile, model_cfg: ModelConfig, atlas_cfg: AtlasConfig,
                  explicit: set[str] | None = None) -> tuple[ModelConfig, AtlasConfig, dict]:
    """Configs with the profile's choices, except fields the user set explicitly.

    explicit: names of fields the user set (e.g. `explicit_fields(args, ModelConfig) | explicit_fields(args,
    AtlasConfig)`); None = treat every field that differs from its dataclass default as set by the user.
    Returns (model_cfg, atlas_cfg, applied) where applied maps each changed field to its new value.
    """
    model_choice = {"decoder": profile.decoder, "view_dependent": profile.view_dependent, "k": profile.k}
    atlas_choice = {"charts": profile.charts}
    applied = {}

    def pick(cfg, choice):
        defaults = _defaults(type(cfg))
        changes = {}
        for name, val in choice.items():
            user_set = name in explicit if explicit is not None else getattr(cfg, name) != defaults[name]
            if not user_set and getattr(cfg, name) != val:
                changes[name] = val
        applied.update(changes)
        return dataclasses.replace(cfg, **changes)

    return pick(model_cfg, model_choice), pick(atlas_cfg, atlas_choice), applied
