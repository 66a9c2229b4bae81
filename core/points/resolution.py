"""Rendering beyond the training resolution: the scale factor of a frame and what the renderer does with it.

A model is fitted on rays through the pixel centres of its training images; nothing constrains its colour field
between them. Rendered with finer pixels (a larger frame, or a camera closer than the training cameras), the
field shows what it is between those samples: every point whose attention stays high until it leaves a ray's K
nearest neighbours (or the pixel-radius cap) is a hard-edged disc about one training pixel wide, and a UNet decoder
applies the corrections it learned for one training pixel to a patch F times smaller.

The scale factor F of a frame = the world size of one training pixel at the object / that of one output pixel
(`PointModel.train_footprint`, set by training: the median over the training views of the camera's distance to
the points' centre over its focal length; moved points of an edited frame count in their own size, the median
local scale of their deformation gradients: an object scaled in Blender is not a magnified one). F <= 1 (and F
within 5 % of 1: cameras a little closer than the training median) renders exactly as the model was trained (the
training size is pixel-identical in every mode); above, the modes of `RENDER_MODES` apply:
- pixels: nothing changes (every size rendered as if it were the training size);
- filtered: the frame (colour and coverage) is low-passed by a Gaussian of FILTER_PER_SCALE·(F − 1) output pixels —
  zero at F = 1 and growing towards a fixed fraction of a training pixel — which anti-aliases the disc rims; with a
  UNet decoder that has a mask head its coverage is first gated by the coverage it gives at its training size
  (`gate_coverage`, at the decoder's scale factor F_dec below: a multi-scale fit's finest level is gated too):
  isolated faint points that the decoder hides in a training-size frame (one pixel there) would otherwise show as
  opaque specks a few pixels wide, since its 3×3 kernels see them magnified F times;
- footprint: anti-aliased neighbour footprints: a point's share of a ray fades out over F − 1 output pixels (one
  training pixel at large F) where it leaves the ray's K nearest or the pixel-radius cap, instead of stopping at a
  hard edge (`core.points.neighbors.select.select_neighbors_soft`; 2K neighbour slots);
- decoder: a UNet decoder runs at the training scale: the feature image is area-averaged down by F, decoded, and
  the decoder's correction (colour and coverage logit) is upsampled bicubically onto the full-size base (the
  points' own colours and coverage, rendered at the full size); models without a decoder render as `pixels`;
- decoder+filtered, footprint+decoder: both;
- interior: a UNet decoder runs at both scales and the frame takes the training scale's decode inside the object
  and the full size's at its silhouette: per pixel, the weight of the training-scale decode is its coverage
  eroded by one training pixel (`interior_weight`), so the band of one training pixel around the silhouette
  (where the full-size decoder draws the sharper edge) and the background keep the full-size decode, and the
  interior (where the full-size decoder, its 3×3 kernels on a frame magnified F times, mottles what it learned
  to smooth) gets the one the decoder was trained for; models without a decoder render as `pixels`;
- interior+filtered: both (the filter's coverage gate applies to the full-size share);
- upsampled: the model's frame rendered at the training scale (the same camera, H/F x W/F pixels, `low_size`)
  and upsampled bicubically (`upsample_frame`): no detail finer than a training pixel, and nothing the model
  does not draw at its training size; what is drawn per ray on top of the model's colour (a painted texture
  looked up through the correspondence, posed frames) stays at the full size. The full-size rays are not traced:
  their trace is interpolated from the training-scale one (`interpolate_trace`: surface points, coverage and the
  canonical points of the correspondence blended across each training pixel, never across an occlusion edge),
  so a frame costs one training-size trace whatever its size. A posed frame whose surface is stretched more
  along one screen direction than across it (a 5x stretch seen from the side) is traced instead on a
  `StretchGrid` (`stretch_grid`, chosen by core/frames/edited.py): the camera turned to the stretch, as many
  pixels as the training-scale frame, spent across the stretch at the screen's own scale and along it the rest;
  the frame is resampled from it (`warp_frame`) and its trace interpolated (`interpolate_trace(coords=...)`).
  A posed frame traced at its own pixels whose surface is squashed on the screen (F < 1 across one direction:
  a part squashed flat, or turned away from the camera) is traced on a StretchGrid finer than the output across
  the squash, at the training scale there, and `warp_frame` averages it back over each output pixel (a tent
  filter), as a camera's pixel averages the squashed surface it sees.
The decoder's scale factor (`decoder_scale`, used by `decoder` and `interior`) counts in the pixel of the training
size (`PointModel.decoder_footprint`): for a multi-scale fit (`pointgt fit --train-scales`) that is its coarsest
level, where the decoder had most of its steps, while its train_footprint is the finest level's — such a model
renders its finest level with F = 1 (nothing filtered) and F_dec = the ratio of the levels.
`python -m tools.bench.resolution` measures them against Cycles at 2x and 4x (docs/results.md, "Resolution"). The
mode `auto` is per model (`auto_mode`). A single-scale fit renders `upsampled`: trained on one size of images, it
has learned nothing finer than their pixels, and its full-size frames (points magnified F times, a decoder on a
frame it never saw) fall below its upsampled training-size frame on most library scenes at 4x (by up to 4 dB after
a ten-minute fit). A multi-scale fit (`pointgt fit --train-scales`) has learned the finer levels: it measures
which decode is better inside the object on its finest level's images (`core.points.train.interior_gain`) and
`auto` renders `interior+filtered` where that gained, `filtered` elsewhere. (Models without a training footprint,
older files, render every size as the training size.)
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import torch
import torch.nn.functional as F

from core.images.cameras import Intrinsics, focal_scale, intrinsics, pixel_rays, project_points
from core.points.trace import CoarseLink, Trace
from core.util.errors import InputError

RENDER_MODES = ("pixels", "filtered", "footprint", "decoder", "decoder+filtered", "footprint+decoder", "interior",
                "interior+filtered", "upsampled")
DEFAULT_RENDER_MODE = "filtered"  # a multi-scale fit's, unless its interior gain says `interior+filtered`
SINGLE_SCALE_MODE = "upsampled"  # a single-scale fit's (docs/results.md "Resolution")
FILTER_PER_SCALE = 0.25  # Gaussian sigma in output pixels per (F − 1): ~ a box of one training pixel at large F
_SCALE_TOL = 0.05  # F within this of 1 is the training scale (cameras a few % closer than the training median)
MAX_SCALE = 1e6  # larger scale factors are clamped (a camera inside the object): the filter covers the frame anyway


def check_mode(mode: str, model=None) -> str:
    """"auto" -> the model's `auto_mode` (DEFAULT_RENDER_MODE without a model); an unknown mode raises InputError
    naming the choices."""
    if mode == "auto":
        return DEFAULT_RENDER_MODE if model is None else auto_mode(model)
    if mode not in RENDER_MODES:
        raise InputError(f"render mode must be 'auto' or one of {', '.join(RENDER_MODES)}, got {mode!r}")
    return mode


def multi_scale(model) -> bool:
    """True for a model fitted on several image sizes (`pointgt fit --train-scales`): its decoder's training pixel
    (the coarsest level's, `decoder_footprint`) is larger than its training footprint (the finest level's)."""
    tf = float(model.train_footprint)
    df = float(getattr(model, "decoder_footprint", torch.tensor(0.0)))
    return math.isfinite(tf) and math.isfinite(df) and tf > 0 and df > tf * (1.0 + _SCALE_TOL)


def auto_mode(model) -> str:
    """The render mode `auto` picks for a model: for a multi-scale fit `interior+filtered` when it measured the
    interior blend better than the full-size decode on its finest level (`PointModel.interior_gain` > 0 dB,
    `core.points.train.interior_gain`), else `filtered`; for a single-scale fit (and older files) SINGLE_SCALE_MODE,
    `upsampled`."""
    if not multi_scale(model):
        return SINGLE_SCALE_MODE
    gain = float(getattr(model, "interior_gain", torch.tensor(0.0)))
    return "interior+filtered" if math.isfinite(gain) and gain > 0.0 else DEFAULT_RENDER_MODE


def pixel_footprint(c2w: torch.Tensor, focal, centre: torch.Tensor) -> float:
    """World size of one pixel at `centre` [3] seen by the camera c2w [4, 4] with `focal` (pixels or Intrinsics):
    distance / focal. 0 when it is not finite and positive."""
    d = float((c2w[:3, 3].double() - centre.double().to(c2w.device)).norm())
    fp = d / float(focal_scale(focal))
    return fp if math.isfinite(fp) and fp > 0 else 0.0


def points_centre(points: torch.Tensor) -> torch.Tensor:
    """Mean of the finite rows of points [N, 3] -> [3] (zeros when none is finite)."""
    ok = torch.isfinite(points).all(dim=1)
    if not bool(ok.any()):
        return torch.zeros(3, dtype=points.dtype, device=points.device)
    return points[ok].double().mean(0).to(points.dtype)


def training_footprint(c2ws: torch.Tensor, focal, points: torch.Tensor) -> float:
    """The median over the training cameras c2ws [V, 4, 4] of `pixel_footprint` at the centre of points [N, 3]."""
    c = points_centre(points.detach())
    fps = [pixel_footprint(c2ws[i], focal, c) for i in range(c2ws.shape[0])]
    fps = [f for f in fps if f > 0]
    return float(torch.tensor(fps, dtype=torch.float64).median()) if fps else 0.0


def scale_factor(train_footprint: float, c2w: torch.Tensor, focal, points: torch.Tensor,
                 centre: torch.Tensor | None = None) -> float:
    """F of a frame: train_footprint / the frame's pixel footprint at the centre of points [N, 3] (`points_centre`;
    centre [3]: that centre where the caller has it); 1 when either is unknown, exactly 1 within _SCALE_TOL of it,
    at most MAX_SCALE."""
    if not (math.isfinite(train_footprint) and train_footprint > 0):
        return 1.0
    fp = pixel_footprint(c2w, focal, points_centre(points) if centre is None else centre)
    if fp <= 0:
        return 1.0
    f = train_footprint / fp
    if not math.isfinite(f):
        return MAX_SCALE
    return 1.0 if abs(f - 1.0) <= _SCALE_TOL else min(f, MAX_SCALE)


def low_size(height: int, width: int, scale: float) -> tuple[int, int, float]:
    """The `upsampled` mode's training-scale frame for an H x W frame at scale factor F: (h, w, s), h = H/F and
    w = W/F rounded (at least 1 pixel), s = h / H the factor its focal length is scaled by. F within 5 % of a
    whole number counts as that number (as F within 5 % of 1 is the training scale): 256² at F = 4.09 renders 64²."""
    f = max(float(scale), 1.0)
    f = float(round(f)) if abs(f - round(f)) <= _SCALE_TOL * f else f
    h = max(1, int(round(height / f)))
    w = max(1, int(round(width * h / height)))
    return h, w, h / height


def upsample_frame(img: torch.Tensor, height: int, width: int) -> torch.Tensor:
    """Bicubic upsampling of img [h, w] or [h, w, C] in [0, 1] to [H, W(, C)] (pixel centres aligned), clamped to
    [0, 1]; non-finite values count as 0."""
    squeeze = img.dim() == 2
    x = torch.nan_to_num((img[..., None] if squeeze else img).float(), nan=0.0).permute(2, 0, 1)[None]
    y = _upsample(x, height, width)[0].permute(1, 2, 0).clamp(0.0, 1.0)
    return y[..., 0] if squeeze else y


@dataclass(frozen=True)
class StretchGrid:
    """The `upsampled` mode's training-scale frame of a frame stretched more along one screen direction than across
    it (a posed part pulled out of shape, or squashed flat): the camera turned about its view axis by `angle`
    (radians, from the image's x axis towards its up axis) so that the direction lies along the grid's rows, and
    scaled per axis, `scales` = (along, across) output pixels per grid pixel (a stretch: each at least 1, coarser
    along the stretch, where the surface is spread, than across it; a squash: finer than the output across it,
    down to MIN_GRID_SCALE). c2w [4, 4], height x width and focal (Intrinsics) are the grid's camera;
    coords [H*W, 2] where each output pixel centre lies in the grid's pixels ((row, col), centres at +0.5), for
    `interpolate_trace` and `warp_frame`. The grid holds the output frame's corners, or, cut to the points'
    outline (`stretch_grid(points=...)`), the part of it they can reach."""
    c2w: torch.Tensor
    height: int
    width: int
    focal: Intrinsics
    coords: torch.Tensor
    scales: tuple[float, float]
    angle: float


GRID_MARGIN = 16  # grid pixels kept around the points' outline when a StretchGrid is cut to it
# the finest grid pixel stretch_grid makes, in output pixels (a floor on the grid's size; the edited render asks for
# its own, EditConfig.squash_grid_finest)
MIN_GRID_SCALE = 1.0 / 16.0


def stretch_grid(c2w: torch.Tensor, height: int, width: int, focal, scales: tuple[float, float],
                 angle: float, points: torch.Tensor | None = None, margin: int = GRID_MARGIN) -> StretchGrid:
    """The `StretchGrid` of an H x W frame with camera c2w [4, 4] and focal (pixels or Intrinsics): grid pixels
    scales = (along, across) times the output pixel (clamped to at least MIN_GRID_SCALE: below 1, finer than the
    output, which `warp_frame` then filters) along the screen direction at `angle`
    (radians, image x towards up) and across it. points [N, 3]: the grid is cut to their outline on it and
    `margin` pixels around (more than the neighbour search reaches and the decoder's kernels see: the grid's
    edge is background), unless a finite point lies behind the camera; output pixels beyond the cut read the
    edge (background)."""
    k = intrinsics(focal, height, width)
    fx, fy, cx, cy = float(k.fx), float(k.fy), float(k.cx), float(k.cy)
    f = math.sqrt(fx * fy)
    s_along, s_across = (max(float(v), MIN_GRID_SCALE) for v in scales)
    cos, sin = math.cos(angle), math.sin(angle)
    dev = c2w.device

    def plane(u, v):  # output pixel position -> the turned camera's image-plane coordinates (at depth 1)
        a, b = (u - cx) / fx, -(v - cy) / fy
        return a * cos + b * sin, -a * sin + b * cos
    ca, cb = plane(torch.tensor([0.0, width, 0.0, width], dtype=torch.float64),
                   torch.tensor([0.0, 0.0, height, height], dtype=torch.float64))
    gfx, gfy = f / s_along, f / s_across
    gw = max(1, int(math.ceil(float(ca.max() - ca.min()) * gfx - 1e-9)))
    gh = max(1, int(math.ceil(float(cb.max() - cb.min()) * gfy - 1e-9)))
    gcx = -float(ca.min()) * gfx + 0.5 * (gw - float(ca.max() - ca.min()) * gfx)
    gcy = float(cb.max()) * gfy + 0.5 * (gh - float(cb.max() - cb.min()) * gfy)
    rows = torch.arange(height, dtype=torch.float64, device=dev) + 0.5
    cols = torch.arange(width, dtype=torch.float64, device=dev) + 0.5
    v, u = torch.meshgrid(rows, cols, indexing="ij")
    a, b = plane(u.reshape(-1), v.reshape(-1))
    coords = torch.stack([gcy - b * gfy, gcx + a * gfx], 1)
    turn = torch.tensor([[cos, -sin, 0.0], [sin, cos, 0.0], [0.0, 0.0, 1.0]], dtype=c2w.dtype, device=dev)
    gc2w = c2w.clone()
    gc2w[:3, :3] = c2w[:3, :3] @ turn
    if points is not None:
        pts = points.detach().to(dev, c2w.dtype)
        pts = pts[torch.isfinite(pts).all(1)]
        if pts.shape[0]:
            uv, depth = project_points(pts, gc2w, gh, gw, Intrinsics(gfx, gfy, gcx, gcy))
            if bool((depth > 0).all()) and bool(torch.isfinite(uv).all()):
                c0 = min(max(int(math.floor(float(uv[:, 0].min()))) - margin, 0), gw - 1)
                r0 = min(max(int(math.floor(float(uv[:, 1].min()))) - margin, 0), gh - 1)
                c1 = max(min(int(math.ceil(float(uv[:, 0].max()))) + margin, gw), c0 + 1)
                r1 = max(min(int(math.ceil(float(uv[:, 1].max()))) + margin, gh), r0 + 1)
                gw, gh, gcx, gcy = c1 - c0, r1 - r0, gcx - c0, gcy - r0
                coords = coords - torch.tensor([r0, c0], dtype=coords.dtype, device=dev)
    return StretchGrid(gc2w, gh, gw, Intrinsics(gfx, gfy, gcx, gcy), coords, (s_along, s_across), float(angle))


# the pixel filter a grid finer than the output is averaged with before it is resampled (`warp_frame`): a tent this
# many output pixels wide on either side of the pixel centre
GRID_FILTER_PIXELS = 1.25


def _filter_axis(x: torch.Tensor, k: torch.Tensor, dim: int) -> torch.Tensor:
    """x [N, 1, H, W] convolved along `dim` (2 rows, 3 columns) with the odd-length kernel k [2r + 1], edges
    replicated: the same size back (the separable filters of this module)."""
    r = (k.numel() - 1) // 2
    xp = F.pad(x, (0, 0, r, r) if dim == 2 else (r, r, 0, 0), mode="replicate")
    return F.conv2d(xp, k.reshape((1, 1, -1, 1) if dim == 2 else (1, 1, 1, -1)))


def _tent_filter(x: torch.Tensor, dim: int, radius: float) -> torch.Tensor:
    """x [1, C, h, w] filtered along `dim` (2 rows, 3 columns) with a tent of `radius` pixels (normalised weights,
    edges replicated); x itself for a radius of at most one pixel."""
    r = int(math.floor(radius))
    if r < 1:
        return x
    t = torch.arange(-r, r + 1, dtype=x.dtype, device=x.device)
    k = (1.0 - t.abs() / radius).clamp_min(0.0)
    return _filter_axis(x.transpose(0, 1), k / k.sum(), dim).transpose(0, 1)


def warp_frame(img: torch.Tensor, grid: StretchGrid, height: int, width: int,
               filter_pixels: float = GRID_FILTER_PIXELS) -> torch.Tensor:
    """img [h, w] or [h, w, C] in [0, 1] on `grid`'s pixels, resampled bicubically at the output pixels
    (`StretchGrid.coords`) -> [H, W(, C)], clamped to [0, 1]; non-finite values count as 0, edges replicated. Along
    a grid axis finer than the output (scale s < 1) the image is first averaged over the output pixel's filter (a
    tent filter_pixels / s grid pixels to either side), as a renderer's pixel filter averages the surface it
    sees."""
    squeeze = img.dim() == 2
    x = torch.nan_to_num((img[..., None] if squeeze else img).float(), nan=0.0).permute(2, 0, 1)[None]
    s_along, s_across = grid.scales
    if s_across < 1.0:  # the grid's rows step across the squash (dim 2), its columns along it (dim 3)
        x = _tent_filter(x, 2, filter_pixels / s_across)
    if s_along < 1.0:
        x = _tent_filter(x, 3, filter_pixels / s_along)
    h, w = x.shape[-2:]
    c = grid.coords.to(x.device, torch.float64)
    g = torch.stack([c[:, 1] / w * 2 - 1, c[:, 0] / h * 2 - 1], 1).to(x.dtype).reshape(1, height, width, 2)
    mode = "bicubic" if min(h, w) >= 2 else "nearest"
    y = F.grid_sample(x, g, mode=mode, padding_mode="border", align_corners=False)[0].permute(1, 2, 0).clamp(0, 1)
    return y[..., 0] if squeeze else y


SAME_SURFACE_PIXELS = 3.0  # training pixels of depth within which two neighbouring rays are on one surface


def interpolate_trace(low: Trace, c2w: torch.Tensor, height: int, width: int, focal, low_focal,
                      coords: torch.Tensor | None = None) -> Trace:
    """The trace of an H x W frame interpolated from the trace `low` of the same camera at the training scale
    (h x w, focal `low_focal`): what the `upsampled` mode's texture lookups, correspondence, depth and paint
    transfer read, without searching neighbours and running the attention for every full-size ray.

    Each full-size ray takes the four training-scale rays around its pixel centre (bilinear weights, pixel
    centres aligned as in `upsample_frame`) and keeps the active ones on the surface of the nearest (depth within
    SAME_SURFACE_PIXELS training pixels: no blending across an occlusion edge), renormalised: its surface point x
    is their surface points blended by these weights (smooth between the training-scale rays on one surface), its
    neighbours and their attention those of the nearest (`Trace.idx` etc.), its background share bg the bilinear
    blend of all four (the coverage falls off across the silhouette as the upsampled frame's). A ray with no
    active ray around is background (bg 1, no neighbours, x = its origin). The blend is kept as the trace's
    `coarse` (`CoarseLink`): the correspondence interpolates the training-scale rays' canonical points with it
    (`core.frames.edited.EditState.canonical_surface`).

    low: Trace with shape (h, w); c2w [4, 4] and focal the full-size frame's camera. coords [H*W, 2]: where each
    full-size pixel centre lies in `low`'s pixels, (row, col) with centres at +0.5 (a `StretchGrid`'s: a grid
    turned and scaled per axis), else the same camera scaled (pixel centres aligned). Returns a Trace of shape
    (H, W) with the same K and dtypes."""
    h, w = low.shape
    dev = low.x.device
    fdt = low.x.dtype
    n = height * width
    origins, dirs = pixel_rays(c2w.to(dev, torch.float32), height, width, focal)
    origins, dirs = origins.reshape(-1, 3), dirs.reshape(-1, 3)

    if coords is None:  # the same camera scaled: pixel centres aligned, row-major
        rows = (torch.arange(height, device=dev, dtype=torch.float64) + 0.5) * (h / height)
        cols = (torch.arange(width, device=dev, dtype=torch.float64) + 0.5) * (w / width)
        coords = torch.stack([rows.repeat_interleave(width), cols.repeat(height)], 1)
    # per ray: the two source rows and columns around its position and the second ones' weights
    t = coords.to(dev, torch.float64) - 0.5
    t0 = torch.floor(t)
    lo0 = t0.long()
    r0, c0 = lo0[:, 0].clamp(0, h - 1), lo0[:, 1].clamp(0, w - 1)
    r1, c1 = (lo0[:, 0] + 1).clamp(0, h - 1), (lo0[:, 1] + 1).clamp(0, w - 1)
    wy, wx = (t - t0)[:, 0].to(fdt), (t - t0)[:, 1].to(fdt)
    corners = torch.stack([r0 * w + c0, r0 * w + c1, r1 * w + c0, r1 * w + c1], 1)  # [R, 4]
    bil = torch.stack([(1 - wy) * (1 - wx), (1 - wy) * wx, wy * (1 - wx), wy * wx], 1)  # [R, 4]
    flat = corners.reshape(-1)

    def at(v):  # per-ray values of the low trace at the corners: [h*w, ...] -> [R, 4, ...]
        return v.index_select(0, flat).reshape(n, 4, *v.shape[1:])
    bg = (bil * at(low.bg).to(fdt)).sum(1)
    active_c = at(low.active)
    depth_c = at(low.depth)
    ref = torch.where(active_c, bil, torch.full_like(bil, -1.0)).argmax(1, keepdim=True)  # the nearest active
    ref_depth = depth_c.gather(1, ref)
    step = SAME_SURFACE_PIXELS * ref_depth.abs() / float(focal_scale(low_focal))
    b = torch.where(active_c & ((depth_c - ref_depth).abs() <= step), bil, torch.zeros_like(bil))
    total = b.sum(1, keepdim=True)
    active = total[:, 0] > 0  # an active corner at bilinear weight 0 does not count: at F = 1 this is `low`
    b = b / total.clamp_min(1e-12)
    x = torch.where(active[:, None], (b[..., None] * at(low.x)).sum(1), origins.to(fdt))
    bg = torch.where(active, bg.clamp(0.0, 1.0), torch.ones_like(bg))
    owner = corners.gather(1, ref)[:, 0]
    # neighbour lists [R, K] only for the active rays (the rest: no neighbours): a frame's background rays are
    # most of it at sizes where this mode runs
    act = torch.nonzero(active).squeeze(1)
    src = owner.index_select(0, act)
    k = low.idx.shape[1]
    idx = torch.full((n, k), -1, dtype=low.idx.dtype, device=dev).index_copy_(0, act, low.idx.index_select(0, src))
    fg_act = low.fg_weights.index_select(0, src)
    fg_weights = torch.zeros((n, k), dtype=fg_act.dtype, device=dev).index_copy_(0, act, fg_act)
    weights = torch.zeros_like(fg_weights).index_copy_(
        0, act, fg_act * (1.0 - bg.index_select(0, act))[:, None].to(fg_act.dtype))
    return Trace(origins=origins, dirs=dirs, idx=idx, weights=weights, fg_weights=fg_weights, bg=bg, x=x,
                 active=active, shape=(height, width), non_finite_points=low.non_finite_points,
                 coarse=CoarseLink(low, corners, b))


def interpolate_rays(link: CoarseLink, values: torch.Tensor, sel: torch.Tensor) -> torch.Tensor:
    """Per-ray values of the training-scale trace blended to the full-size rays `sel` [S] by `link`'s weights:
    values [h*w, C] -> [S, C] (a non-finite value with weight reaches the result)."""
    c, wt = link.corners[sel], link.weights[sel]
    v = values[c]                                                    # [S, 4, C]
    return (torch.where(wt[..., None] > 0, v, torch.zeros_like(v)) * wt[..., None].to(v.dtype)).sum(1)


def decoder_footprint(model) -> float:
    """World size of the pixel a model's decoder is run at in the `decoder` and `interior` modes: its
    `decoder_footprint` (the training size's: the coarsest level of a multi-scale fit), else (0 or not finite:
    older files, single-scale fits) its `train_footprint`."""
    fp = float(getattr(model, "decoder_footprint", torch.tensor(0.0)))
    return fp if math.isfinite(fp) and fp > 0 else float(model.train_footprint)


def decoder_scale(model, scale: float | None, c2w: torch.Tensor, focal, points: torch.Tensor,
                  size_scale: float = 1.0, centre: torch.Tensor | None = None) -> float:
    """The scale factor of a frame for the decoder (`decoder_footprint` / the frame's pixel footprint): from the
    camera c2w [4, 4], focal and points [N, 3] like `scale_factor` (the footprint times size_scale: moved points in
    their own size; centre as there), or, when the caller gives the frame's scale factor `scale` (against train_footprint), that
    times decoder_footprint / train_footprint. 1 for F_dec <= 1 or not finite; at most MAX_SCALE."""
    if scale is None:
        f = scale_factor(decoder_footprint(model) * size_scale, c2w, focal, points, centre)
    else:
        tf, df = float(model.train_footprint), decoder_footprint(model)
        ratio = df / tf if math.isfinite(tf) and tf > 0 and math.isfinite(df) and df > 0 else 1.0
        f = float(scale) * ratio
        f = 1.0 if abs(f - 1.0) <= _SCALE_TOL else f
    return min(f, MAX_SCALE) if f == f and f > 1.0 else 1.0


def gaussian_blur(img: torch.Tensor, sigma: float) -> torch.Tensor:
    """Separable Gaussian low-pass of img [H, W] or [H, W, C] with `sigma` pixels (edges replicated); the kernel
    radius is 3 sigma, at most the frame's size. sigma <= 0 returns img itself."""
    if not (sigma > 0) or img.numel() == 0:
        return img
    squeeze = img.dim() == 2
    x = (img[..., None] if squeeze else img).permute(2, 0, 1)[:, None].float()  # [C, 1, H, W]
    h, w = x.shape[-2:]
    r = int(min(math.ceil(3.0 * min(sigma, 1e6)), max(h, w)))
    t = torch.arange(-r, r + 1, dtype=torch.float64, device=x.device)
    g = torch.exp(-0.5 * (t / sigma) ** 2)
    g = (g / g.sum()).to(x.dtype)
    x = _filter_axis(_filter_axis(x, g, 3), g, 2)
    out = x[:, 0].permute(1, 2, 0)
    return out[..., 0] if squeeze else out


def filter_sigma(scale: float) -> float:
    """The `filtered` mode's Gaussian sigma in output pixels at scale factor F (0 for F <= 1)."""
    return FILTER_PER_SCALE * max(float(scale) - 1.0, 0.0)


def decode_at_scale(model, feature: torch.Tensor, scale: float):
    """A residual UNet decoder run at the training scale. feature [1, C, H, W] (channels 0-2 the base colour, 3 the
    coverage) -> (rgb [1, 3, H, W], alpha [1, H, W] or None), like `PointModel.decode_with_alpha`: the feature image
    is area-averaged to H/F x W/F (at least 1 pixel), decoded, and the decoder's corrections (output − its base)
    are upsampled bicubically and added to the full-size base. Older (non-residual) decoders and F <= 1 decode the
    full-size image as it is."""
    if scale <= 1.0 or not model.cfg.decoder_residual:
        return model.decode_with_alpha(feature)
    h, w = feature.shape[-2:]
    lh, lw = max(1, int(round(h / scale))), max(1, int(round(w / scale)))
    low = F.interpolate(feature, size=(lh, lw), mode="area")
    y = model.decoder(low)
    corr = y[:, :3] - low[:, :3]
    rgb = feature[:, :3] + _upsample(corr, h, w)
    alpha = None
    if y.shape[1] > 3:
        logit = lambda c: torch.logit(c.clamp(1e-6, 1.0 - 1e-6))  # noqa: E731
        a_corr = y[:, 3:4] - logit(low[:, 3:4])
        alpha = torch.sigmoid(logit(feature[:, 3:4]) + _upsample(a_corr, h, w))[:, 0]
    return rgb, alpha


def training_scale_coverage(model, feature: torch.Tensor, scale: float) -> torch.Tensor | None:
    """The coverage a residual UNet decoder's mask head gives at the training scale, at the full size: feature
    [1, C, H, W] (as `decode_at_scale`) -> alpha [1, H, W] in [0, 1] (`decode_at_scale`'s); None for F <= 1, models
    without a decoder, older (non-residual) decoders and decoders without a mask head."""
    dec = getattr(model, "decoder", None)
    if not scale > 1.0 or dec is None or not model.cfg.decoder_residual or not model.cfg.decoder_alpha:
        return None
    return decode_at_scale(model, feature, scale)[1]


GATE_SURFACE = 0.5  # training-scale coverage from which a pixel counts as near the object's surface


def gate_coverage(alpha: torch.Tensor, low_alpha: torch.Tensor, scale: float) -> torch.Tensor:
    """The `filtered` mode's coverage gate: alpha [..., H, W] (the decoder's mask head run on the full-size frame)
    limited by the training-scale coverage low_alpha [..., H, W] (`training_scale_coverage`). Near the object —
    where the training-scale coverage reaches GATE_SURFACE within ⌈F⌉ pixels, about one training pixel — the limit
    is the largest training-scale coverage within those ⌈F⌉ pixels, so silhouettes and interiors keep their
    full-size coverage (the window reaches past the upsampled edge's blur); away from it, the limit is the
    training-scale coverage of the pixel itself, so a speck the decoder hides at the training scale fades to what
    it gives it there, in that blip's own (upsampled) shape rather than a disc ⌈F⌉ pixels wide. F <= 1 returns
    alpha itself; the result is in [0, 1] and finite (non-finite inputs count as 0)."""
    if not scale > 1.0:
        return alpha
    r = int(min(math.ceil(min(float(scale), 1e6)), max(low_alpha.shape[-2:])))
    lo = torch.nan_to_num(low_alpha, nan=0.0, posinf=1.0, neginf=0.0).clamp(0.0, 1.0)
    shape = lo.shape
    flat = lo.reshape(-1, 1, *shape[-2:])
    near = F.max_pool2d(F.pad(flat, (r, r, r, r), value=0.0), 2 * r + 1, stride=1).reshape(shape)
    limit = torch.where(near >= GATE_SURFACE, near, lo)
    a = torch.nan_to_num(alpha, nan=0.0, posinf=1.0, neginf=0.0).clamp(0.0, 1.0)
    return torch.minimum(a, limit)


def interior_weight(coverage: torch.Tensor, scale: float) -> torch.Tensor:
    """The `interior` mode's per-pixel weight of the training-scale decode: coverage [..., H, W] (the training
    scale's, at the full size) eroded by ⌈F⌉ pixels — one training pixel — so it is 0 on the band of one training
    pixel inside the silhouette and outside the object, and the coverage itself well inside (the frame's border
    is no silhouette: the coverage is extended past it). F <= 1 gives zeros (the full-size decode, which is the
    training scale's there); the result is in [0, 1] and finite (non-finite coverage counts as 0)."""
    c = torch.nan_to_num(coverage.float(), nan=0.0, posinf=1.0, neginf=0.0).clamp(0.0, 1.0)
    if not scale > 1.0 or c.numel() == 0:
        return torch.zeros_like(c)
    r = int(min(math.ceil(min(float(scale), 1e6)), max(c.shape[-2:])))
    shape = c.shape
    x = c.reshape(-1, 1, *shape[-2:])
    eroded = -F.max_pool2d(F.pad(-x, (r, r, r, r), mode="replicate"), 2 * r + 1, stride=1)  # frame edge: no rim
    return eroded.reshape(shape).clamp(0.0, 1.0)


def _upsample(x: torch.Tensor, h: int, w: int) -> torch.Tensor:
    if x.shape[-2:] == (h, w):
        return x
    if min(x.shape[-2:]) < 2:  # bicubic needs 2 pixels; a 1-pixel image is constant anyway
        return F.interpolate(x, size=(h, w), mode="nearest")
    return F.interpolate(x, size=(h, w), mode="bicubic", align_corners=False)
