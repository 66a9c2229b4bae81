"""Paint on the preview, land in the atlas: every preview pixel on the object knows the canonical surface point
it shows (x_can), hence its chart and texel; strokes painted there are written into those texels.

Two passes, both vectorised:
- splat: each painted pixel writes its colour into the bilinear footprint of t_c(x_can) in every chart c the
  atlas blends there (P(c|x) above a floor), so a re-render from the same view shows the stroke again;
- fill: atlas texels whose canonical surface point (the atlas' texel map) lies within a pixel's footprint of a
  painted pixel's x_can take that pixel's colour, so a closer camera (more texels per pixel) shows no holes.
Texels are compared in canonical space, so the transfer is correct whatever pose the preview showed.
No bpy here (tested with plain arrays); imports torch.
"""
from __future__ import annotations

import numpy as np
import torch
from scipy.spatial import cKDTree

from core.util.errors import InputError

CHART_FLOOR = 0.05  # charts blended with less probability than this keep their texels


@torch.no_grad()
def canonical_surface(state, result: dict, min_alpha: float = 0.5) -> np.ndarray:
    """x_can [H, W, 3] float32 for every pixel of a `render_edited` result whose coverage exceeds `min_alpha`
    (NaN elsewhere), using the state's correspondence (render_edited fills x_can only where it textured)."""
    tr = result["trace"]
    h, w = tr["shape"]
    fg = 1.0 - tr["bg"]
    hit = tr["active"] & (fg > min_alpha)
    out = torch.full((h * w, 3), float("nan"), device=fg.device)
    sel = torch.nonzero(hit).squeeze(1)
    if sel.numel():
        xc = state.canonical(tr, sel) if state.moved else tr["x"][sel]
        out[sel] = torch.where(torch.isfinite(xc).all(1, keepdim=True), xc, torch.full_like(xc, float("nan")))
    return out.reshape(h, w, 3).cpu().numpy().astype(np.float32)


def painted_pixels(painted: np.ndarray, rendered: np.ndarray, x_can: np.ndarray, threshold: float) -> np.ndarray:
    """Mask [H, W] of preview pixels an artist changed (colour moved by more than `threshold`, L2 in display
    space) that show the object (finite x_can)."""
    if painted.shape != rendered.shape or painted.shape[:2] != x_can.shape[:2]:
        raise InputError(f"preview image is {painted.shape[1]}x{painted.shape[0]} but it was rendered at "
                         f"{rendered.shape[1]}x{rendered.shape[0]}; re-render the preview, then paint again")
    diff = np.linalg.norm(np.nan_to_num(painted - rendered, nan=0.0), axis=-1)
    return (diff > threshold) & np.isfinite(x_can).all(-1)


def _pixel_footprint(x_can: np.ndarray) -> float:
    """Median canonical distance between horizontally/vertically adjacent object pixels (one pixel's size)."""
    d = [np.linalg.norm(x_can[:, 1:] - x_can[:, :-1], axis=-1).ravel(),
         np.linalg.norm(x_can[1:] - x_can[:-1], axis=-1).ravel()]
    d = np.concatenate(d)
    d = d[np.isfinite(d)]
    return float(np.median(d)) if d.size else 0.0


@torch.no_grad()
def transfer(atlas, atlas_image: np.ndarray, painted: np.ndarray, rendered: np.ndarray, x_can: np.ndarray,
             threshold: float = 0.02, fill: bool = True) -> tuple[np.ndarray, np.ndarray, int]:
    """Write strokes painted on a preview into the atlas.

    atlas: core Atlas; atlas_image [A, B, 3] display space (row 0 = top), the current (maybe painted) atlas;
    painted / rendered [H, W, 3] the preview as the artist left it / as it was rendered; x_can [H, W, 3]
    (canonical_surface). Returns (new atlas [A, B, 3] float32, changed texels [A, B] bool, painted pixel count).
    """
    layout = atlas.layout
    if tuple(atlas_image.shape[:2]) != tuple(layout.shape):
        raise InputError(f"atlas image is {atlas_image.shape[1]}x{atlas_image.shape[0]} but the model's atlas is "
                         f"{layout.shape[1]}x{layout.shape[0]}; re-import the model")
    mask = painted_pixels(painted, rendered, x_can, threshold)
    out = np.array(atlas_image[..., :3], dtype=np.float32, copy=True)
    changed = np.zeros(layout.shape, dtype=bool)
    n_px = int(mask.sum())
    if n_px == 0:
        return out, changed, 0
    colours = np.clip(painted[mask], 0.0, 1.0).astype(np.float32)   # [P, 3]
    xs = x_can[mask]                                                  # [P, 3]

    if fill:
        tex_pts = atlas.texel_points().detach().cpu().numpy().reshape(-1, 3)
        ok = np.isfinite(tex_pts).all(1)
        visible = np.isfinite(x_can).all(-1)
        vis_pts = x_can[visible]
        vis_painted = mask[visible]
        vis_colour = np.clip(painted[visible], 0.0, 1.0)
        tol = 1.0 * _pixel_footprint(x_can)
        if tol > 0 and ok.any():
            dist, j = cKDTree(vis_pts).query(tex_pts[ok], k=1)
            take = (dist <= tol) & vis_painted[j]
            flat_idx = np.nonzero(ok)[0][take]
            out.reshape(-1, 3)[flat_idx] = vis_colour[j[take]]
            changed.reshape(-1)[flat_idx] = True

    # splat: bilinear footprints in every chart that contributes, colours averaged by weight
    probs, uv = atlas.chart_uv(torch.from_numpy(xs))
    probs, uv = probs.cpu().numpy(), uv.cpu().numpy()
    R = layout.R
    origins = layout.origins(torch.device("cpu")).numpy().astype(np.int64)          # [n, 2] (row, col)
    acc = np.zeros((*layout.shape, 3), dtype=np.float64)
    wsum = np.zeros(layout.shape, dtype=np.float64)
    for c in range(layout.n):  # a few charts; everything inside is vectorised over pixels
        # uvs outside the chart are clamped to its edge texels by the lookup; painting those would smear the
        # stroke over every point clamped there
        inside = ((uv[:, c] > 0.0) & (uv[:, c] < 1.0)).all(-1)
        use = (probs[:, c] >= CHART_FLOOR) & inside
        if not use.any():
            continue
        t = uv[use, c] * R - 0.5                  # texel-centre coordinates in the chart
        base = np.floor(t)
        frac = t - base
        for dc, dr in ((0, 0), (1, 0), (0, 1), (1, 1)):
            wgt = (frac[:, 0] if dc else 1 - frac[:, 0]) * (frac[:, 1] if dr else 1 - frac[:, 1])
            col = np.clip(base[:, 0] + dc, 0, R - 1).astype(np.int64) + origins[c, 1]
            row = np.clip(base[:, 1] + dr, 0, R - 1).astype(np.int64) + origins[c, 0]
            np.add.at(acc, (row, col), wgt[:, None] * colours[use])
            np.add.at(wsum, (row, col), wgt)
    hit = wsum > 1e-6
    out[hit] = (acc[hit] / wsum[hit, None]).astype(np.float32)
    changed |= hit
    return out, changed, n_px
