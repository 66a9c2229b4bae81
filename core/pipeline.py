"""Glue between the stages: stage 2 (atlas) from a trained stage-1 model and its training images."""
from __future__ import annotations

import time

import torch

from core.atlas.config import AtlasConfig
from core.atlas.fit import fit_atlas
from core.atlas.footprint import FootprintView, refit_texture_footprint
from core.atlas.samples import extract_surface_samples
from core.images.cameras import focal_scale, project_points
from core.points.neighbors.select import select_neighbors


def surface_samples(model, split, max_samples: int = 200_000, seed: int = 0, colour: str = "image"):
    """Stage-2 input from a stage-1 model: xyz [S, 3], rgb [S, 3] over all views of `split` (SplitData).
    colour: "image" pairs each surface point with its pixel's colour, "render" with the model's own colour there
    (the same colour the point render shows; measured in docs/atlas.md, "Sample colour")."""
    current = {}

    def views():
        for i in range(len(split)):
            current["c2w"] = split.c2w[i].to(model.xyz.device)
            yield split.c2w[i], split.height, split.width, split.focal, split.images[i], split.alphas[i]

    @torch.no_grad()
    def render_fn(o, d):
        c2w = current["c2w"]
        o, d = o.to(model.xyz.device), d.to(model.xyz.device)
        px, _ = project_points(o + d, c2w, split.height, split.width, split.focal)  # back to pixel coordinates
        idx = select_neighbors(model.xyz, model.cfg.neighbors, model.cfg.k, c2w, split.height, split.width,
                               split.focal, px, o, d, model.cfg.neighbor_radius_px)
        att = model.attend(model.xyz, model.influence, o, d, idx)
        out = {"x": att["x"], "fg": 1.0 - att["bg"]}
        if colour == "render":
            out["rgb"] = model.shade(att, d, idx, torch.ones(3, device=d.device))["rgb"].clamp(0, 1)
        return out

    return extract_surface_samples(render_fn, views(), max_samples=max_samples, seed=seed, colour=colour)


@torch.no_grad()
def footprint_views(model, split) -> list[FootprintView]:
    """Per training view: the model's surface points (projected on their rays), which rays hit, their depths, and
    the ground truth — the input of the footprint texture refit."""
    from core.points.render import trace_frame
    from core.edits.correspondence import ray_canonical_points

    views = []
    dev = model.xyz.device
    for i in range(len(split)):
        tr = trace_frame(model, split.c2w[i].to(dev), split.height, split.width, split.focal)
        h, w = tr.shape
        x = ray_canonical_points(tr)  # where render_edited looks the atlas up (nothing moved)
        depth = tr.depth.clamp_min(0.0)  # of x, the surface point moved onto its ray
        views.append(FootprintView(points=x.view(h, w, 3), valid=(tr.fg > 0.5).view(h, w),
                                   depth=depth.view(h, w), image=split.images[i].to(dev),
                                   alpha=split.alphas[i].to(dev), focal=float(focal_scale(split.focal))))
    return views


def fit_atlas_stage(bundle, split, cfg: AtlasConfig, show_progress: bool = True, progress_callback=None):
    """Fit stage 2 into `bundle` (sets bundle.atlas and bundle.meta['atlas_fit']); returns the fit history
    (stage_seconds: the whole stage; total_seconds: the atlas fit alone; sample_seconds; footprint.seconds)."""
    lambdas = cfg.lambda_candidates()  # a bad list fails here, before the fit
    t0 = time.perf_counter()
    # Model colours need direct RGB values; with a UNet decoder the per-ray colour needs whole images: use pixels.
    colour = cfg.sample_colour if bundle.model.decoder is None else "image"
    xyz, rgb = surface_samples(bundle.model, split, seed=cfg.seed, colour=colour)
    t_samples = time.perf_counter() - t0
    from core.atlas.fit import pixel_footprint

    pixel = pixel_footprint(xyz, split.c2w[:, :3, 3], float(focal_scale(split.focal)))  # island atlas resolution
    atlas, history = fit_atlas(xyz, rgb, cfg, progress=progress_callback, quiet=not show_progress, pixel_size=pixel)
    bundle.atlas = atlas
    history = {**history, "samples": int(xyz.shape[0]), "sample_seconds": round(t_samples, 2)}
    if cfg.footprint:
        t1 = time.perf_counter()
        info = refit_texture_footprint(atlas, footprint_views(bundle.model, split), lam=cfg.footprint_lambda,
                                       iters=cfg.footprint_iters, lambdas=lambdas, lookup=cfg.footprint_lookup)
        history["footprint"] = {**info, "seconds": round(time.perf_counter() - t1, 2)}
        if show_progress and info.get("pixels"):
            print(f"texture refit for pixel-filtered lookups: {info['pixels']} pixels, RMSE (linear) "
                  f"{info['rmse_before']:.4f} -> {info['rmse_after']:.4f} (lambda {info['lambda']:g}"
                  + (f", chosen by held-out views: {info['holdout_psnr']} dB" if info.get("holdout_psnr") else "")
                  + f") in {history['footprint']['seconds']:.1f} s",
                  flush=True)
    history["stage_seconds"] = round(time.perf_counter() - t0, 2)  # samples, fit and refit: the whole of stage 2
    bundle.meta["atlas_fit"] = {k: v for k, v in history.items() if not isinstance(v, list)}
    return history


def stage_time_text(hist: dict) -> str:
    """'X s (surface samples a s, atlas b s, texture refit c s)' from fit_atlas_stage's history."""
    parts = [f"surface samples {hist.get('sample_seconds', 0.0):.0f} s", f"atlas {hist['total_seconds']:.0f} s"]
    if "seconds" in hist.get("footprint", {}):
        parts.append(f"texture refit {hist['footprint']['seconds']:.0f} s")
    total = hist.get("stage_seconds", hist["total_seconds"])
    return f"{total:.0f} s ({', '.join(parts)})"


def refresh_texel_map(bundle, split, cfg: AtlasConfig) -> dict:
    """Recompute the texel->surface map of a fitted atlas with the current rules (cfg.texel_map, texel_max_dist,
    texel_max_cycle or, for island atlases, island_texel_max_cycle), keeping charts, maps and texture: surface
    samples from `split`, no refit. Models made before the forward-splat map (whose map came from the
    surface-coordinate net) gain the accurate map this way."""
    from core.util.errors import InputError

    if bundle.atlas is None:
        raise InputError("this model has no atlas to refresh; run `pointgt atlas MODEL DATA` to fit one")
    t0 = time.perf_counter()
    xyz, _ = surface_samples(bundle.model, split, seed=cfg.seed)
    spacing = bundle.meta.get("atlas_fit", {}).get("spacing")
    if not spacing:
        from core.atlas.fit import sample_spacing

        spacing = sample_spacing(xyz.cpu().double().numpy())[0]
    tp = bundle.atlas.compute_texel_points(xyz, cfg.texel_max_dist * spacing, cfg.max_cycle(bundle.atlas.islands),
                                           cfg.texel_map, cfg.texture_sigma)
    ok = torch.isfinite(tp).all(-1)
    _, pix = bundle.atlas.atlas_pixel_coords(tp[ok])
    rows, cols = torch.nonzero(ok, as_tuple=True)
    miss = (pix - torch.stack([cols + 0.5, rows + 0.5], -1)).norm(dim=-1)  # texels from t_c(point) to the texel
    bundle.meta.setdefault("atlas_fit", {})["texel_map"] = cfg.texel_map
    info = {"samples": int(xyz.shape[0]), "valid_texels": int(ok.sum()), "seconds": round(time.perf_counter() - t0, 2)}
    if miss.numel():
        info.update(miss_median=float(miss.median()), miss_p90=float(miss.quantile(0.9)))
    return info
