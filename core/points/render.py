"""Render whole frames from a point model: canonical or deformed points, any pinhole camera.

The edit path (correspondence + atlas lookup) builds on `trace_frame`, which returns everything a frame's rays
know: attention, surface points, neighbour indices.
"""
from __future__ import annotations

import torch

from core.images.cameras import pixel_rays, scaled_focal
from core.points.model import TRAIN_BACKGROUND, PointModel
from core.points.attention_compiled import BACKENDS as ATTENTION_BACKENDS
from core.points.attention_compiled import attend_compiled, supported
from core.points.neighbors.select import select_neighbors, select_neighbors_soft
from core.points.resolution import (MAX_SCALE, RENDER_MODES, check_mode, decode_at_scale, filter_sigma,
                                    decoder_scale, gate_coverage, gaussian_blur, interior_weight, low_size,
                                    interpolate_trace, scale_factor, upsample_frame)
from core.points.trace import Trace, held_rows
from core.util.errors import InputError

__all__ = ["RENDER_MODES", "pixel_grid", "trace_frame", "shade_frame", "render_frame", "straight_colour"]


def pixel_grid(height: int, width: int, device) -> torch.Tensor:
    """Pixel centres [H*W, 2] as (col, row), row-major, row 0 = top."""
    r, c = torch.meshgrid(torch.arange(height, device=device, dtype=torch.float32) + 0.5,
                          torch.arange(width, device=device, dtype=torch.float32) + 0.5, indexing="ij")
    return torch.stack([c.reshape(-1), r.reshape(-1)], dim=-1)


# shade_frame computes the point values only at the points a frame's rays hold when they are fewer than this share of
# all points (the gather and scatter cost more than they save above it)
HELD_TABLE = 0.75


@torch.no_grad()
def trace_frame(model: PointModel, c2w: torch.Tensor, height: int, width: int, focal: float,
                points: torch.Tensor | None = None, influence: torch.Tensor | None = None,
                k: int | None = None, temperature: float | None = None, chunk: int = 1024,
                inv_f=None, radius_scale: float = 1.0, attention: str = "auto",
                soft_scale: float = 1.0, index=None, reach: torch.Tensor | None = None,
                rebase_depth: bool = False, reach_gate: float = 0.0, reach_surround: bool = False,
                reach_gate_own: bool = False, reach_between: bool = False, reach_perspective: float = 0.0) -> Trace:
    """Neighbours + attention for every pixel of a frame.

    Args: c2w [4, 4]; points [M, 3] positions to render (default: the model's canonical points); chunk: rays per
    attention call (1024 keeps the [chunk·K, width] key-MLP activations in cache: 40 % faster than 16384 on a CPU,
    `python -m tools.bench.render`);
    influence [M] (default: the model's, which requires M == N);
    inv_f [M, 3, 3]: inverse deformation gradients of the points (attention keys in each point's canonical frame,
    `PointModel.attend`; rebase_depth: their depths from the ray's nearest neighbour in those frames), or a
    function rows [P] long -> [M, 3, 3] right at those rows at least (given the points the rays hold, the
    Trace's `held`: the attention reads no other);
    radius_scale: the screen neighbour search's pixel radius cap times this;
    attention: "torch" (PointModel.attend, chunk by chunk) | "compiled" (core/points/attention_compiled.py, CPU
    with numba; the same numbers to float rounding, all rays in one call) | "auto" (compiled where supported);
    soft_scale: the frame's scale factor F for anti-aliased neighbour footprints (> 1: the K-nearest rule and the
    radius cap fade over F − 1 pixels, core/points/resolution.py mode "footprint"; then K' = 2K slots, and the
    attention runs in torch, which takes the footprint's log-window);
    index: a ScreenIndex of these points and this camera (core/points/neighbors/select.py `screen_index` with the
    model's method, K, cap and radius_scale) to query instead of building one, so a caller can search some rays
    again without projecting the points twice (not used in footprint mode);
    reach [M] (>= 1) or None: point m is a neighbour candidate within the pixel radius cap × reach[m] (a point whose
    surroundings a deformation stretched; core/points/neighbors/index.py `ScreenIndex`; footprint mode uses the
    largest reach for every point); reach_gate > 0: with reach, a ray with no point within reach_gate × the plain
    cap gets no neighbours (1: the reach adds far points only to rays the plain cap already gives one; not in
    footprint mode), unless reach_surround and its candidates surround it (a hole inside the object's outline);
    reach_gate_own: each point's gate is at most its own reach; reach_between: beyond the plain cap the gate
    opens only for two points more than 120° apart as seen from the ray; reach_perspective: a near reaching point's
    reach widened by the perspective, at most this factor (`ScreenIndex`).
    Returns a Trace of flat per-ray tensors (R = H*W): origins/dirs [R, 3], idx [R, K], weights [R, K],
    fg_weights [R, K], bg [R], x [R, 3], active [R], plus shape (H, W) and depth [R] on demand.
    """
    dev = model.xyz.device
    c2w = c2w.to(dev, torch.float32)
    pts = model.xyz if points is None else points.to(dev, torch.float32)
    infl = model.influence if influence is None else influence.to(dev, torch.float32)
    k = k or model.cfg.k
    o, d = pixel_rays(c2w, height, width, focal)
    o, d = o.reshape(-1, 3), d.reshape(-1, 3)
    px = pixel_grid(height, width, dev)
    # Non-finite positions (a broken rig) are treated as absent by the neighbour search; zero them for the maths.
    finite = torch.isfinite(pts).all(dim=1)
    pts_search = torch.where(finite[:, None], pts, torch.full_like(pts, float("nan")))
    pts_math = torch.where(finite[:, None], pts, torch.zeros_like(pts))
    log_w = None
    if soft_scale > 1.0:
        soft_radius = radius_scale
        if reach is not None and reach.numel():
            soft_radius = radius_scale * max(1.0, float(torch.nan_to_num(reach.double(), 1.0, 1.0, 1.0).max()))
        idx, log_w = select_neighbors_soft(pts_search, model.cfg.neighbors, k, c2w, height, width, focal, px, o, d,
                                           model.cfg.neighbor_radius_px, width_px=soft_scale - 1.0,
                                           radius_scale=soft_radius)
        k = idx.shape[1]
    else:
        idx = select_neighbors(pts_search, model.cfg.neighbors, k, c2w, height, width, focal, px, o, d,
                               model.cfg.neighbor_radius_px, radius_scale=radius_scale, index=index,
                               reach=reach, reach_gate=reach_gate, reach_surround=reach_surround,
                               reach_gate_own=reach_gate_own, reach_between=reach_between,
                               reach_perspective=reach_perspective)
    held = None
    if callable(inv_f):
        held = held_rows(idx, pts.shape[0])
        inv_f = inv_f(held)
    fi = None if inv_f is None else inv_f.to(dev, torch.float32)
    r = o.shape[0]
    # Rays without a single neighbour cannot reach the object: background, no attention to evaluate.
    active = (idx >= 0).any(dim=1)
    res = {"weights": torch.zeros(r, k, device=dev), "fg_weights": torch.zeros(r, k, device=dev),
           "bg": torch.ones(r, device=dev), "x": o.clone()}
    act = torch.nonzero(active).squeeze(1)
    if attention not in ATTENTION_BACKENDS:
        raise InputError(f"attention must be one of {ATTENTION_BACKENDS}, got {attention!r}")
    compiled = supported(model, torch.device(dev))
    if attention == "compiled" and (not compiled or log_w is not None):
        raise InputError("attention 'compiled' needs numba, a CPU device, the standard key MLP and no footprint "
                         "mode; use 'auto' or 'torch'")
    use_compiled = attention != "torch" and compiled and log_w is None
    if use_compiled and act.numel():
        att = attend_compiled(model, pts_math, infl, o[act], d[act], idx[act], temperature=temperature, inv_f=fi,
                              chunk=chunk, rebase_depth=rebase_depth)
        for key in res:
            res[key][act] = att[key]
    for s in range(0, 0 if use_compiled else act.shape[0], chunk):
        sl = act[s:s + chunk]
        att = model.attend(pts_math, infl, o[sl], d[sl], idx[sl], temperature=temperature, inv_f=fi,
                           log_window=None if log_w is None else log_w[sl], rebase_depth=rebase_depth)
        for key in res:
            res[key][sl] = att[key]
    trace = Trace(origins=o, dirs=d, idx=idx, active=active, shape=(height, width),
                  non_finite_points=int((~finite).sum()), **res)
    if held is not None:
        trace.__dict__["held"] = held  # the cached_property's value, computed above for the keys
    return trace


DECODER_HALO = 16  # pixels: more than the UNet decoder's receptive radius (12), even (its pooling grid)


def _span(lo: int, hi: int, halo: int, n: int) -> tuple[int, int]:
    """[lo, hi) widened by halo, clipped to [0, n), ends on even pixels unless clipped (the UNet's pooling grid)."""
    a = max(lo - halo, 0) // 2 * 2
    b = hi + halo
    b = n if b >= n else b + (b % 2)
    return a, min(b, n)


@torch.no_grad()
def decode_where_active(model: PointModel, feat: torch.Tensor, active: torch.Tensor):
    """The decoder over a frame's feature image feat [1, C, H, W], run only around the rays that saw points
    (active [H, W] bool): model.decode_with_alpha's (rgb [1, 3, H, W], alpha [1, H, W] or None), equal to the whole
    frame's to float rounding. Rays with no neighbour all hold one background feature; the decoder's output for a
    frame made only of it is cached per model, size and weights, and the decoder runs on the active rays'
    bounding box widened by 2 · DECODER_HALO, of which the box widened by DECODER_HALO (beyond the receptive
    radius) is pasted into that cached frame. Falls back to the whole frame when the box covers most of it or the
    inactive rays' features are not all equal."""
    _, c, h, w = feat.shape
    inactive = ~active
    if not bool(inactive.any()):
        return model.decode_with_alpha(feat)
    rows = torch.nonzero(active.any(1)).squeeze(1)
    cols = torch.nonzero(active.any(0)).squeeze(1)
    if rows.numel() == 0:
        r0 = r1 = c0 = c1 = 0
    else:
        r0, r1, c0, c1 = int(rows[0]), int(rows[-1]) + 1, int(cols[0]), int(cols[-1]) + 1
    ir, ic = _span(r0, r1, 2 * DECODER_HALO, h), _span(c0, c1, 2 * DECODER_HALO, w)
    if (ir[1] - ir[0]) * (ic[1] - ic[0]) > 0.7 * h * w:
        return model.decode_with_alpha(feat)
    first = int(torch.nonzero(inactive.reshape(-1))[0])
    bg_feat = feat[0, :, first // w, first % w]                                           # [C]
    if not bool((feat[0][:, inactive] == bg_feat[:, None]).all()):
        return model.decode_with_alpha(feat)
    key = (h, w, feat.dtype, str(feat.device), bg_feat.cpu().numpy().tobytes(),
           tuple((p.data_ptr(), p._version) for p in model.decoder.parameters()))
    cache = model.__dict__.setdefault("_decoded_background", {})
    if key not in cache:
        cache.clear()  # one size at a time: the live preview and a render at another size alternate rarely
        rgb_bg, alpha_bg = model.decode_with_alpha(bg_feat.view(1, c, 1, 1).expand(1, c, h, w).contiguous())
        cache[key] = (rgb_bg, alpha_bg)
    rgb_bg, alpha_bg = cache[key]
    rgb_c, alpha_c = model.decode_with_alpha(feat[:, :, ir[0]:ir[1], ic[0]:ic[1]])
    orow, ocol = _span(r0, r1, DECODER_HALO, h), _span(c0, c1, DECODER_HALO, w)
    src = (slice(orow[0] - ir[0], orow[1] - ir[0]), slice(ocol[0] - ic[0], ocol[1] - ic[0]))
    dst = (slice(*orow), slice(*ocol))
    rgb = rgb_bg.clone()
    rgb[:, :, dst[0], dst[1]] = rgb_c[:, :, src[0], src[1]]
    alpha = None
    if alpha_bg is not None:
        alpha = alpha_bg.clone()
        alpha[:, dst[0], dst[1]] = alpha_c[:, src[0], src[1]]
    return rgb, alpha


@torch.no_grad()
def shade_frame(model: PointModel, trace: Trace, background=(1.0, 1.0, 1.0), chunk: int = 16384,
                features: torch.Tensor | None = None, with_alpha: bool = False, decoder_scale: float = 1.0,
                coverage_scale: float = 1.0, interior_scale: float = 1.0):
    """Colours of a traced frame from the point values: rgb [H, W, 3] in [0, 1].
    features [M, h]: per-point features of the traced points when they are not the model's own (ids).
    with_alpha: return (rgb, alpha [H, W] from the decoder's mask head, or None without one).
    decoder_scale: the frame's scale factor F for a UNet decoder run at the training scale
    (core/points/resolution.py `decode_at_scale`; 1 = decode the frame as it is, only around the object).
    coverage_scale: the decoder's scale factor F_dec for the `filtered` mode's coverage gate (`gate_coverage`: the
    mask head's coverage of the full-size frame limited by the one it gives at its training size; 1 = none; only
    with a frame decoded as it is, decoder_scale 1).
    interior_scale: the frame's scale factor F for the `interior` mode: the frame decoded as it is and at the
    training scale, blended per pixel by `interior_weight` of the training scale's coverage (1 = none; only with
    decoder_scale 1 and a residual UNet)."""
    h, w = trace.shape
    bg = torch.as_tensor(background, dtype=torch.float32, device=model.xyz.device)
    parts = []
    # per-point values, shared by the chunks (None: view-dependent); only the points the rays hold when they are
    # clearly fewer than all (a frame of part of the object, a posed frame's added points out of view)
    m = (model.features if features is None else features).shape[0]
    held = trace.held if not model.cfg.view_dependent else None
    table = model.point_table(features, rows=held if held is not None and held.numel() < HELD_TABLE * m else None)
    for s in range(0, trace.idx.shape[0], chunk):
        sl = slice(s, s + chunk)
        att = {"weights": trace.weights[sl], "bg": trace.bg[sl]}
        parts.append(model.shade(att, trace.dirs[sl], trace.idx[sl], bg, features=features, table=table))
    alpha = None
    if model.decoder is None:
        rgb = torch.cat([p["rgb"] for p in parts]).reshape(h, w, 3)
    else:
        feat = torch.cat([p["feature"] for p in parts]).reshape(h, w, -1).permute(2, 0, 1)[None]
        rgb, alpha = decode_at_scale(model, feat, decoder_scale) if decoder_scale > 1.0 \
            else decode_where_active(model, feat, trace.active.reshape(h, w))
        both = not decoder_scale > 1.0 and model.cfg.decoder_residual  # the frame was decoded as it is
        low = {}  # training-scale decodes by scale factor, shared by the interior blend and the coverage gate
        for sc in (interior_scale, coverage_scale):
            if both and sc > 1.0 and sc not in low:
                low[sc] = decode_at_scale(model, feat, sc)
        if interior_scale in low:  # the training scale's decode inside the object
            low_rgb, low_a = low[interior_scale]
            wgt = interior_weight(low_a if low_a is not None else feat[:, 3], interior_scale)  # [1, H, W]
            rgb = wgt[:, None] * low_rgb + (1.0 - wgt[:, None]) * rgb
            if alpha is not None and low_a is not None:
                alpha = wgt * low_a + (1.0 - wgt) * alpha
        rgb = rgb[0].permute(1, 2, 0)
        alpha = None if alpha is None else alpha[0]
        # The decoder paints the background it was trained on: its frame is a·c + (1 − a)·white, a the mask head
        # (else the attention's foreground weight, older models). Recover the object colour c (in [0, 1]) and
        # composite it with a over the requested background: the same frame over white, the white share moved
        # onto any other background, and no faint tint of the decoder where nothing is covered (a frame over
        # black then composites over white into the frame over white).
        cover = (alpha if alpha is not None else (1.0 - trace.bg).reshape(h, w)).clamp(0, 1)[..., None]
        white = torch.as_tensor(TRAIN_BACKGROUND, dtype=torch.float32, device=bg.device)
        c = ((rgb - (1.0 - cover) * white) / cover.clamp_min(1e-4)).clamp(0.0, 1.0)
        if alpha is not None and coverage_scale in low and low[coverage_scale][1] is not None:
            # the object colour c stays; only its coverage is gated (`training_scale_coverage`'s)
            alpha = gate_coverage(alpha, low[coverage_scale][1][0], coverage_scale)
            cover = alpha[..., None]
        rgb = cover * c + (1.0 - cover) * bg
    rgb = rgb.clamp(0.0, 1.0)
    return (rgb, alpha) if with_alpha else rgb


@torch.no_grad()
def render_frame(model: PointModel, c2w: torch.Tensor, height: int, width: int, focal: float,
                 background=(1.0, 1.0, 1.0), mode: str = "auto", scale: float | None = None, **kw) -> dict:
    """Canonical (or re-posed, via points=) render: dict(rgb [H, W, 3], alpha [H, W], x [H, W, 3], scale).
    alpha: the decoder's mask head when the model has one (the coverage its colours were composited with), else
    the attention's foreground weight 1 − bg.
    mode: how frames finer than the training pixels are rendered, one of RENDER_MODES or "auto" (the model's
    mode, `core.points.resolution.auto_mode`), see core/points/resolution.py; scale: the frame's scale factor F
    (default: from the model's training footprint and this camera, points= taken at their world size —
    `core.frames.edited.render_edited` corrects for scaled points; 1 for models without a footprint). F <= 1
    renders the same in every mode."""
    parts = set(check_mode(mode, model).split("+"))
    pts = model.xyz if kw.get("points") is None else kw["points"]
    fd = decoder_scale(model, scale, c2w, focal, pts.detach())  # the decoder's (a multi-scale fit's coarsest level)
    f = scale_factor(float(model.train_footprint), c2w, focal, pts.detach()) if scale is None else float(scale)
    f = min(f, MAX_SCALE) if f == f and f > 1.0 else 1.0  # NaN or F <= 1: the training scale
    if "upsampled" in parts and fd > 1.0:  # the training scale's frame, upsampled; its trace interpolated
        lh, lw, s = low_size(height, width, fd)
        low_focal = scaled_focal(focal, s)
        low = render_frame(model, c2w, lh, lw, low_focal, background, mode="pixels", scale=1.0, **kw)
        rgb, alpha = upsample_frame(low["rgb"], height, width), upsample_frame(low["alpha"], height, width)
        tr = interpolate_trace(low["trace"], c2w, height, width, focal, low_focal)
        return {"rgb": rgb, "alpha": alpha, "x": tr.x.reshape(height, width, 3), "trace": tr, "scale": f}
    tr = trace_frame(model, c2w, height, width, focal, soft_scale=f if "footprint" in parts else 1.0, **kw)
    rgb, alpha = shade_frame(model, tr, background, with_alpha=True,
                             decoder_scale=fd if "decoder" in parts else 1.0,
                             coverage_scale=fd if "filtered" in parts else 1.0,  # the decoder's own size
                             interior_scale=fd if "interior" in parts else 1.0)
    h, w = tr.shape
    if alpha is None:
        alpha = (1.0 - tr.bg).reshape(h, w)
    alpha = alpha.clamp(0, 1)
    if "filtered" in parts and f > 1.0:
        sigma = filter_sigma(f)
        rgb, alpha = gaussian_blur(rgb, sigma).clamp(0, 1), gaussian_blur(alpha, sigma).clamp(0, 1)
    return {"rgb": rgb, "alpha": alpha, "x": tr.x.reshape(h, w, 3), "trace": tr, "scale": f}


def straight_colour(premul: torch.Tensor, alpha: torch.Tensor, min_alpha: float = 1.0 / 510) -> torch.Tensor:
    """Straight (un-premultiplied) colour [H, W, 3] of a frame rendered over black (premul [H, W, 3] = alpha·c),
    alpha [H, W]: what an RGBA image file holds. 0 where alpha < min_alpha (below one 8-bit level)."""
    a = alpha.clamp(0, 1)[..., None]
    c = torch.where(a >= min_alpha, premul / a.clamp_min(min_alpha), torch.zeros_like(premul))
    return c.clamp(0, 1)

