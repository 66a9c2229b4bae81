"""Stage 1: fit a PAPR point model to multi-view images (with the paper's geometry regularizers).

Each step renders a few random image patches of one training view (patches, not scattered rays, so the UNet
decoder and SSIM see image structure), with neighbours re-selected from the current points. Schedules run on the
fraction of the budget used (steps or wall-clock minutes, whichever ends first), so `--minutes` and `--steps`
give the same shape of training. A time budget alone (`--minutes` without `--steps`) has no step cap: it trains
for the minutes asked (`step_cap`). On several CPU threads a step shares its rays (attention and shading) and its
decoder patches out to worker threads with one torch thread each (`attend_and_shade`, core/util/workers.py) and
runs its other operations on one thread (`TrainConfig.workers`, `op_threads`).
"""
from __future__ import annotations

import dataclasses
import math
import time
from dataclasses import dataclass

import torch
import torch.nn.functional as F

from core.config import opt
from core.images.metrics import blank_floor, mean_scores, score_views, ssim
from core.images.pyramid import parse_scales, parse_weights, pyramid
from core.points.render import render_frame
from core.points.resolution import decoder_scale, training_footprint
from core.images.cameras import rays_for_pixels, scaled_focal
from core.points.init import visual_hull_points
from core.points.key_mlp import KEY_PATHS
from core.points.ema import ParamEMA
from core.points.floaters import floater_mask
from core.points.model import ModelConfig, PointModel, mean_spacing
from core.points.regularizers import close_to_ray, close_to_surface
from core.points.neighbors.select import select_neighbors
from core.util.device import resolve_device
from core.util.errors import InputError
from core.util.progress import Progress
from core.util.workers import split_rows


DEFAULT_STEPS = 6000  # the step budget of a fit given neither --steps nor --minutes
JITTER_TARGETS = ("pixel", "bilinear")
FINE_TRAINS = ("all", "no-decoder", "colour", "features")  # TrainConfig.train_scale_fine


@dataclass
class TrainConfig:
    """Stage-1 training (PAPR + geometry regularizers)."""

    steps: int = opt(0, f"maximum optimisation steps (0 = no cap when --minutes is set, else {DEFAULT_STEPS})",
                     min=0)
    minutes: float = opt(0.0, "wall-clock budget in minutes (0 = no limit; with --steps too, training ends at "
                              "whichever comes first)", min=0.0)
    patches: int = opt(16, "image patches per step", min=1, max=4096)
    patch_size: int = opt(16, "patch side in pixels", min=1, max=4096)
    fg_patch_frac: float = opt(0.75, "fraction of patches centred on foreground pixels", min=0.0, max=1.0)
    views_per_step: int = opt(1, "distinct training views a step draws its patches from, the patches shared out "
                                 "among them as evenly as they go (at most one view per patch, and no more than "
                                 "the training views), so each step's gradient sees the object from several "
                                 "directions; 1 = all patches of one view", min=1, max=1024)
    lr_points: float = opt(0.1, "point position learning rate, in units of the initial point spacing", min=0.0)
    lr_features: float = opt(1e-2, "point feature learning rate", min=0.0)
    lr_influence: float = opt(1e-2, "point influence learning rate", min=0.0)
    lr_networks: float = opt(2e-3, "attention / value / decoder learning rate", min=0.0)
    lr_final: float = opt(0.05, "learning rates decay exponentially to this fraction", above=0.0, max=1.0)
    lr_final_groups: str = opt("", "per-group final fractions overriding --lr-final, comma-separated name=fraction "
                                   "over the parameter groups xyz, features, influence, networks (attention / "
                                   "value) and decoder (e.g. xyz=0.05,decoder=0.15); empty = --lr-final for all")
    alpha_weight: float = opt(0.05, "weight of the foreground-mask loss (1 - background weight vs alpha)", min=0.0)
    decoder_alpha_weight: float = opt(0.5, "weight of the decoder mask head's loss (MSE against alpha)", min=0.0)
    ssim_weight: float = opt(0.0, "weight of the (1 - SSIM) loss on patches", min=0.0)
    base_weight: float = opt(0.0, "residual UNet decoder: weight of the loss (MSE against the image) on the "
                                  "decoder-free render the decoder corrects (the points' own blended colours), so "
                                  "the points carry the colour and the decoder only a correction", min=0.0)
    decoder_weight_decay: float = opt(0.0, "decoupled weight decay (AdamW, per step: lr x this) on the decoder's "
                                           "weights", min=0.0)
    decoder_dropout: float = opt(0.0, "UNet decoder: probability of zeroing each point-feature channel of a training "
                                      "patch's feature image (the others scaled by 1 / (1 - p); the residual "
                                      "decoder's base colour and coverage are kept); test renders use all",
                                 min=0.0, max=0.95)
    decoder_flip: bool = opt(True, "UNet decoder: each step flips and/or transposes its patches' feature images "
                                   "(one of the 8 symmetries of a square, at random) before the decoder and its "
                                   "output back, so the decoder cannot learn the training views' orientation: "
                                   "frames from a rolled camera and posed parts turned in the image keep their "
                                   "quality (docs/results.md, 'The decoder's orientation')")
    decoder_stop: float = opt(0.0, "UNet decoder: fraction of training at which its learning rate reaches 0 (held "
                                   "to its schedule until half of this fraction, then a cosine decay), so the "
                                   "points learn the colour late in training; 0 = off", min=0.0, max=1.0)
    ray_jitter: float = opt(0.25, "shift each training patch's rays by a random sub-pixel offset of up to this "
                                  "many pixels in x and y (one offset per patch, so a patch stays a regular grid the "
                                  "decoder reads as an image; its targets: --jitter-target), so the points and the "
                                  "decoder see neighbour blends between the training views' pixel centres; 0 = off",
                            min=0.0, max=0.5)
    jitter_target: str = opt("bilinear", "the target of a jittered ray (--ray-jitter): bilinear = the training image "
                                         "and mask bilinearly interpolated at the shifted position | pixel = the "
                                         "value of the pixel it was shifted from (a shifted ray learns a "
                                         "neighbour's value: a blur)", choices=JITTER_TARGETS)
    ema: float = opt(0.0, "decay per step of an exponential moving average of all trained parameters (points and "
                          "networks; warm-up d = min(decay, (1 + n) / (10 + n)) at step n, following the points "
                          "through pruning and cloning); the fit returns and saves the average, and its history's "
                          "last entry also scores the trained parameters (`raw`); 0 = off", min=0.0, max=0.9999)
    close2ray: bool = opt(True, "use the close-to-ray regularizer")
    close2ray_weight: float = opt(0.002, "close-to-ray weight gamma", min=0.0)
    close2surface: bool = opt(True, "use the close-to-surface regularizer")
    close2surface_weight: float = opt(0.01, "close-to-surface weight eta", min=0.0)
    reg_start: float = opt(0.1, "fraction of training after which the regularizers start", min=0.0, max=1.0)
    prune_every: int = opt(500, "prune unused points every N steps (0 = never)", min=0)
    clone_every: int = opt(1000, "clone the points with the largest position gradient every N steps (0 = never)", min=0)
    clone_frac: float = opt(0.1, "fraction of points cloned each time", min=0.0, max=1.0)
    max_points: int = opt(12000, "densification stops at this many points", min=1, max=10_000_000)
    keep_floaters: bool = opt(False, "keep the fit's floaters: by default each pruning step and the fit's end "
                                     "remove groups of fewer than --floater-size points farther than "
                                     "--floater-radius spacings from every other point (core/points/floaters.py: "
                                     "specks a new view shows over the background)")
    floaters_while_pruning: bool = opt(True, "remove floaters at every pruning step too (--prune-every), so the "
                                             "fit trains on without them; --no-floaters-while-pruning: at the end "
                                             "only")
    floater_size: int = opt(20, "floaters: groups of fewer points than this", min=2, max=100_000)
    floater_radius: float = opt(3.0, "floaters: the gap, in point spacings (the median nearest-point distance), "
                                     "that separates a group from the rest", above=0.0, max=1e6)
    zoom_frac: float = opt(0.0, "fraction of steps that render their patches on a finer pixel grid (zoom x zoom "
                                "sub-pixel rays per pixel, searched and decoded like a frame at zoom x the size) "
                                "and average them down to the training pixels, so the model is fitted between "
                                "pixel centres too (renders beyond the training size, core/points/resolution.py)",
                         min=0.0, max=1.0)
    train_scales: str = opt("", "multi-scale training from images larger than the training size: comma-separated "
                                "downscale factors of the loaded images (e.g. 1,2,4), each step trains on the patches "
                                "of one level (the images area-averaged by that factor, the camera scaled to match, "
                                "searched and rendered as a frame of that size); the coarsest level is the training "
                                "size (visual hull, profile, atlas, test renders), the finest the training footprint "
                                "renders are scaled against; empty or off = train on the loaded images as they are; "
                                "auto (`pointgt fit`'s default) = with --downscale N > 1, read the images at up to "
                                "4x the training size --downscale sets and train on their pyramid down to it, two "
                                "thirds of the steps on the training size (--downscale 4: levels 1,2,4 of the "
                                "full-size images, weights 1,1,4); with N = 1 nothing finer exists and auto is off")
    train_scale_weights: str = opt("", "share of the steps per level of --train-scales, comma-separated in its "
                                       "(sorted) order, fine to coarse; empty = equal shares")
    train_scale_settle: float = opt(0.0, "fraction of training, at its end, spent on the coarsest level of "
                                         "--train-scales alone (the training size), so the points and the decoder "
                                         "settle at the size the test views, the profile and the atlas use; the "
                                         "steps before share the levels by --train-scale-weights; 0 = the shares "
                                         "to the end", min=0.0, max=1.0)
    train_scale_mix: float = opt(0.0, "share of every step's patches on the coarsest level of --train-scales (the "
                                      "training size), the rest on one finer level drawn by the finer levels' "
                                      "--train-scale-weights: every step trains the training size (one backward "
                                      "over both parts, the same rays per step); 0 = off: each step on one level",
                                 min=0.0, max=0.95)
    train_scale_fine: str = opt("all", "what the steps on the finer levels of --train-scales train (the training "
                                       "size's steps train everything): all | no-decoder = all but the UNet decoder "
                                       "(it stays the training size's, softening the silhouette and the detail the "
                                       "training size cannot hold) | colour = the point features and the decoder "
                                       "only (positions, influence and attention keep the training size's "
                                       "coverage) | features = the point features only",
                                choices=FINE_TRAINS)
    zoom_max: int = opt(2, "largest zoom of those steps (each picks 2..zoom_max; patches / zoom² of them, so a "
                           "step costs about the same)", min=2, max=8)
    dropout: float = opt(0.3, "initial point dropout probability (cosine decay to 0 at --dropout-end)",
                         min=0.0, max=0.95)
    dropout_end: float = opt(0.5, "fraction of training at which the point dropout's cosine decay reaches 0",
                             above=0.0, max=1.0)
    eval_every: float = opt(30.0, "seconds of training between test-PSNR measurements", above=0.0)
    eval_views: int = opt(4, "test views used for the PSNR-vs-time curve", min=1)
    guard: bool = opt(True, "watch stage 1 for a collapsed fit (test renders at the blank-frame floor or without "
                            "foreground) and non-finite steps, and recover (reset the decoder's correction, then "
                            "restart without a decoder); what it did is kept in the history and the model file")
    guard_margin: float = opt(1.0, "dB: a fit whose object PSNR is within this of the blank frame's, and whose "
                                   "render is far closer to the blank frame than the truth, counts as collapsed",
                              min=0.0, max=100.0)
    guard_decline: float = opt(3.0, "dB: with --guard, a test checkpoint whose object PSNR fell this far below the "
                                    "fit's best so far (a fit losing its object: points drawn in, coverage lost) "
                                    "restarts the fit with the same settings on a new random course while at most "
                                    "0.6 of the budget is spent; later it is reported; 0 = off",
                               min=0.0, max=100.0)
    key_path: str = opt("auto", "how the attention key MLP is trained: chunked (only non-empty slots, in cache-sized "
                                "chunks, hand-written backward: the same numbers, ~1.9x less CPU time per step on "
                                "one CPU thread) | torch (autograd through the module, the reference) | auto (chunked "
                                "when the key MLP is the standard one)", choices=KEY_PATHS)
    workers: int = opt(0, "CPU worker threads the training step shares its large independent pieces out to, its "
                          "rays' attention and its patches' decoder, each worker on one torch thread (the same "
                          "numbers to float rounding, one thread synchronisation per piece instead of one per "
                          "operation); 0 = as many as torch threads (--threads), 1 = none: all on the training "
                          "thread; training on a GPU uses none", min=0, max=64)
    op_threads: int = opt(0, "torch threads of the step's other operations: 0 = one when the step has workers "
                             "(each operation split over the threads costs a thread synchronisation, and stalls "
                             "when other processes hold the cores), else --threads; test renders always use "
                             "--threads", min=0, max=1024)
    seed: int = opt(0, "random seed", min=0)
    device: str = opt("auto", "cpu | cuda | auto")
    threads: int = opt(0, "torch CPU threads (0 = torch default)", min=0, max=1024)


def step_cap(cfg: TrainConfig) -> float:
    """The fit's step budget: `cfg.steps` when set (> 0); otherwise none (inf) under a time budget
    (`cfg.minutes` > 0), so the minutes asked for are trained, and `DEFAULT_STEPS` without one."""
    if cfg.steps > 0:
        return float(cfg.steps)
    return float("inf") if cfg.minutes > 0 else float(DEFAULT_STEPS)


def _cosine(frac: float) -> float:
    return 0.5 * (1 + math.cos(math.pi * min(max(frac, 0.0), 1.0)))


def dihedral(x: torch.Tensor, t: int, inverse: bool = False) -> torch.Tensor:
    """One of the 8 symmetries of a square on images x [..., S, S] (t in 0..7: bit 0 flips the columns, bit 1 the
    rows, bit 2 transposes, applied in that order); inverse=True undoes it: dihedral(dihedral(x, t), t, True) == x."""
    flips = [d for bit, d in ((1, -1), (2, -2)) if t & bit]
    if not inverse:
        if flips:
            x = torch.flip(x, flips)
        return x.transpose(-1, -2) if t & 4 else x
    if t & 4:
        x = x.transpose(-1, -2)
    return torch.flip(x, flips) if flips else x


def feature_dropout(feat: torch.Tensor, p: float, keep: int, gen: torch.Generator) -> torch.Tensor:
    """Channel dropout of a batch of feature images feat [B, C, H, W]: each channel from `keep` on of each image is
    zeroed with probability p and the rest scaled by 1 / (1 - p); channels 0..keep-1 pass unchanged."""
    if p <= 0 or feat.shape[1] <= keep:
        return feat
    mask = (torch.rand(feat.shape[0], feat.shape[1] - keep, 1, 1, generator=gen) >= p).to(feat)
    return torch.cat([feat[:, :keep], feat[:, keep:] * (mask / (1.0 - p))], dim=1)


def point_dropout(frac: float, p: float, end: float) -> float:
    """Point dropout probability at a fraction of training: p at 0, a cosine decay to 0 at `end` (> 0), 0 after."""
    return p * _cosine(frac / end)


LR_GROUPS = ("xyz", "features", "influence", "networks", "decoder")  # build_optimizer's parameter groups


def lr_finals(cfg: "TrainConfig") -> dict[str, float]:
    """Final learning-rate fraction of each parameter group (LR_GROUPS): --lr-final, overridden per group by
    --lr-final-groups ("xyz=0.05,decoder=0.15"). A malformed list raises InputError."""
    out = {g: float(cfg.lr_final) for g in LR_GROUPS}
    for part in (p.strip() for p in str(cfg.lr_final_groups).split(",")):
        if not part:
            continue
        name, eq, val = (t.strip() for t in part.partition("="))
        if not eq or name not in LR_GROUPS:
            raise InputError(f"--lr-final-groups: name=fraction items, names from {', '.join(LR_GROUPS)}; "
                             f"got {part!r}")
        try:
            v = float(val)
        except ValueError:
            raise InputError(f"--lr-final-groups: {name}'s fraction must be a number, got {val!r}") from None
        if not 0.0 < v <= 1.0:
            raise InputError(f"--lr-final-groups: {name}'s fraction must be in (0, 1], got {val!r}")
        out[name] = v
    return out


def decoder_lr_factor(frac: float, stop: float) -> float:
    """Multiplier of the decoder's learning rate at a fraction of training: 1 until stop / 2, a cosine decay to 0 at
    stop, 0 after; stop <= 0: always 1."""
    if stop <= 0:
        return 1.0
    return _cosine((frac - 0.5 * stop) / (0.5 * stop)) if frac > 0.5 * stop else 1.0


def jitter_patches(px: torch.Tensor, p: int, amount: float, gen: torch.Generator) -> torch.Tensor:
    """px [P*S*S, 2] pixel centres of P patches (`sample_patches`) -> the same, each patch shifted by its own
    offset, uniform in [-amount, amount]² pixels."""
    off = (torch.rand(p, 1, 2, generator=gen, dtype=px.dtype) * 2.0 - 1.0) * amount
    return (px.reshape(p, -1, 2) + off).reshape(-1, 2)


def sample_bilinear(image: torch.Tensor, px: torch.Tensor) -> torch.Tensor:
    """Bilinear interpolation of image [H, W, C] (or [H, W]) at px [R, 2] (col, row) positions in pixels, pixel
    (r, c)'s centre at (c + 0.5, r + 0.5) -> [R, C] (or [R]); positions beyond the outer pixel centres take the
    edge pixels' values (clamped). At pixel centres it is the pixels' values exactly."""
    h, w = image.shape[:2]
    x = (px[:, 0].to(torch.float64) - 0.5).clamp(0.0, w - 1.0)
    y = (px[:, 1].to(torch.float64) - 0.5).clamp(0.0, h - 1.0)
    x0, y0 = x.floor().long().clamp(max=w - 1), y.floor().long().clamp(max=h - 1)
    x1, y1 = (x0 + 1).clamp(max=w - 1), (y0 + 1).clamp(max=h - 1)
    fx, fy = (x - x0).to(image.dtype), (y - y0).to(image.dtype)
    if image.dim() == 3:
        fx, fy = fx[:, None], fy[:, None]
    top = image[y0, x0] * (1 - fx) + image[y0, x1] * fx
    bottom = image[y1, x0] * (1 - fx) + image[y1, x1] * fx
    return top * (1 - fy) + bottom * fy


def zoom_pixels(px: torch.Tensor, size: int, zoom: int) -> torch.Tensor:
    """Sub-pixel centres of patches: px [P*size*size, 2] pixel centres (col, row) of P square patches in raster
    order (`sample_patches`) -> [P*(zoom*size)², 2], each patch's zoom x zoom finer grid in raster order (the
    patch as a frame zoom times larger would see it, in the original pixel coordinates)."""
    p = px.shape[0] // (size * size)
    corner = px.reshape(p, size * size, 2)[:, 0] - 0.5                       # [P, 2] top-left (col, row)
    t = (torch.arange(size * zoom, dtype=px.dtype, device=px.device) + 0.5) / zoom
    r, c = torch.meshgrid(t, t, indexing="ij")
    grid = torch.stack([c.reshape(-1), r.reshape(-1)], dim=-1)              # [(zoom*size)², 2]
    return (corner[:, None, :] + grid[None]).reshape(-1, 2)


def pool_zoomed(values: torch.Tensor, p: int, size: int, zoom: int) -> torch.Tensor:
    """Average zoomed patch values [P*(zoom*size)², C] down to the patch pixels [P*size*size, C]."""
    c = values.shape[-1]
    img = values.reshape(p, size * zoom, size * zoom, c).permute(0, 3, 1, 2)
    return F.avg_pool2d(img, zoom).permute(0, 2, 3, 1).reshape(-1, c)


def pool_index(p: int, size: int, zoom: int) -> torch.Tensor:
    """For each ray of `zoom_pixels`' order [P*(zoom*size)²], the index of its patch pixel in [P*size*size]."""
    t = torch.arange(size * zoom) // zoom
    r, c = torch.meshgrid(t, t, indexing="ij")
    local = (r * size + c).reshape(-1)
    return (torch.arange(p)[:, None] * size * size + local[None]).reshape(-1)


def pick_level(level_p: torch.Tensor, frac: float, settle: float, gen: torch.Generator) -> int:
    """The pyramid level a multi-scale step trains on, an index into the levels fine to coarse: drawn from the
    shares level_p [L] (float64, summing to 1); at a fraction of training frac >= 1 - settle (settle > 0) the
    coarsest, the training size, without a draw. One level: 0, without a draw."""
    n = level_p.shape[0]
    if n == 1:
        return 0
    if settle > 0 and frac >= 1.0 - settle:
        return n - 1
    return int(torch.multinomial(level_p, 1, generator=gen))


def mixed_patches(patches: int, share: float, levels: int) -> int:
    """Patches of a --train-scale-mix step on the training size: round(share x patches), at least 1 and leaving at
    least 1 to the finer level; 0 (not mixed) with share 0, one level or fewer than 2 patches."""
    if share <= 0 or levels < 2 or patches < 2:
        return 0
    return min(patches - 1, max(1, round(share * patches)))


def frozen_on_fine(model: PointModel, what: str) -> list[torch.nn.Parameter]:
    """The parameters a finer level's step of a multi-scale fit leaves alone under `--train-scale-fine what`
    (FINE_TRAINS): none for all; the decoder's for no-decoder; all but the point features and the decoder for
    colour; all but the point features for features."""
    if what == "all":
        return []
    keep = {"features"} | ({"decoder."} if what == "colour" else set())
    if what == "no-decoder":
        return [p for n, p in model.named_parameters() if n.startswith("decoder.")]
    return [p for n, p in model.named_parameters()
            if n not in keep and not (n.startswith("decoder.") and "decoder." in keep)]


def patch_neighbors(points: torch.Tensor, model_cfg: ModelConfig, c2w: torch.Tensor, level, px: torch.Tensor,
                    zoom: int = 1):
    """Rays and neighbours of a training step's pixels, found as a frame of the level's size renders them.

    points [N, 3] (detached; NaN rows = dropped out), c2w [4, 4], level: the split (or pyramid level) the pixels
    belong to (height, width, focal), px [R, 2] pixel centres (col, row) in that level's pixels (with zoom > 1,
    sub-pixel centres of `zoom_pixels`, searched as a frame zoom times larger). Returns origins [R, 3],
    dirs [R, 3] and idx [R, K]: `select_neighbors` with the model's method, K and pixel-radius rule over the whole
    level frame — the neighbours `render_frame` at that size gives those pixels."""
    o, d = rays_for_pixels(c2w, px, level.height, level.width, level.focal)
    idx = select_neighbors(points, model_cfg.neighbors, model_cfg.k, c2w, level.height * zoom, level.width * zoom,
                           scaled_focal(level.focal, zoom), px * zoom, o, d, model_cfg.neighbor_radius_px)
    return o, d, idx


_ATTENTION = ("weights", "bg", "x", "t", "p", "valid", "fg_weights")  # what attend returns, in this order


def attend_and_shade(model: PointModel, origins: torch.Tensor, dirs: torch.Tensor, idx: torch.Tensor,
                     background: torch.Tensor, keys: str = "auto", workers: int = 1) -> tuple[dict, dict]:
    """`model.attend` (all points, their influence) and `model.shade` of a training step's rays: origins, dirs
    [R, 3], idx [R, K]; background [3]. Returns (att, shaded) as those give them. workers > 1 (CPU, with
    gradients): the rays are shared out to that many worker threads in contiguous pieces of about equal work,
    forward and backward (core/util/workers.py `split_rows`; rays are independent there, so the same numbers to
    float rounding), the point values computed once before."""
    if workers <= 1 or not torch.is_grad_enabled():
        att = model.attend(model.xyz, model.influence, origins, dirs, idx, keys=keys)
        return att, model.shade(att, dirs, idx, background)
    table = model.point_table()  # None: view-dependent values, gathered per slot inside the pieces
    shared = [model.xyz, model.influence] + ([table] if table is not None else [])
    params = [p for n, p in model.named_parameters()
              if n not in ("xyz", "influence") and not n.startswith("decoder.")]

    def piece(o, d, i, xyz, influence, *tab):
        att = model.attend(xyz, influence, o, d, i, keys=keys)
        sh = model.shade(att, d, i, background, table=tab[0] if tab else None)
        return [att[k] for k in _ATTENTION] + [sh["rgb"] if model.decoder is None else sh["feature"]]
    # pieces of equal work: a ray costs its K slots' geometry and its non-empty slots' key MLP (~5x a slot's
    # geometry); the background patches' rays have few non-empty slots
    cost = (idx >= 0).sum(1) + 0.2 * idx.shape[1]
    *att, out = split_rows(piece, [origins, dirs, idx], shared, params, workers, cost)
    att = dict(zip(_ATTENTION, att))
    return att, ({"rgb": out, "feature": None} if model.decoder is None else {"rgb": None, "feature": out})


def step_views(first: int, n: int, total: int, gen: torch.Generator) -> list[int]:
    """The training views of one step (`TrainConfig.views_per_step`): `first` (already drawn) and up to n - 1 others
    drawn without repeats from the remaining total - 1; fewer when there are fewer views."""
    n = max(1, min(n, total))
    if n == 1:
        return [first]
    rest = torch.randperm(total - 1, generator=gen)[: n - 1]
    return [first] + [int(r) + (int(r) >= first) for r in rest]


def share_patches(n_patches: int, n_views: int) -> list[int]:
    """Patches per view when a step's n_patches are shared out among n_views (<= n_patches): as even as they go,
    the first views one more."""
    return [n_patches // n_views + (j < n_patches % n_views) for j in range(n_views)]


def sample_patches(alpha: torch.Tensor, n: int, size: int, fg_frac: float, gen: torch.Generator):
    """Top-left corners of n patches in an [H, W] image, a fraction centred on foreground pixels.
    Returns pixel centres px [n*size*size, 2] (col, row) and integer rows/cols [n*size*size]."""
    h, w = alpha.shape
    size = min(size, h, w)
    fg = torch.nonzero(alpha > 0.5)
    n_fg = int(round(n * fg_frac)) if fg.shape[0] else 0
    centres = []
    if n_fg:
        pick = fg[torch.randint(fg.shape[0], (n_fg,), generator=gen)]
        centres.append(pick)
    if n - n_fg:
        centres.append(torch.stack([torch.randint(h, (n - n_fg,), generator=gen),
                                    torch.randint(w, (n - n_fg,), generator=gen)], dim=1))
    c = torch.cat(centres)
    r0 = (c[:, 0] - size // 2).clamp(0, h - size)
    c0 = (c[:, 1] - size // 2).clamp(0, w - size)
    ar = torch.arange(size)
    rows = (r0[:, None, None] + ar[None, :, None]).expand(-1, size, size).reshape(-1)
    cols = (c0[:, None, None] + ar[None, None, :]).expand(-1, size, size).reshape(-1)
    px = torch.stack([cols.float() + 0.5, rows.float() + 0.5], dim=-1)
    return px, rows, cols, size


class Densifier:
    """Accumulates per-point statistics; prunes unused points and clones the most-pulled ones."""

    def __init__(self, n: int, device):
        self.reset(n, device)

    def reset(self, n: int, device):
        self.grad = torch.zeros(n, device=device)
        self.hits = torch.zeros(n, device=device)
        self.usage = torch.zeros(n, device=device)

    def accumulate(self, model: PointModel, idx: torch.Tensor, weights: torch.Tensor):
        valid = idx >= 0
        flat = idx[valid]
        self.usage.index_add_(0, flat, weights.detach()[valid])
        self.hits.index_add_(0, flat, torch.ones_like(flat, dtype=self.hits.dtype))
        if model.xyz.grad is not None:
            self.grad += model.xyz.grad.norm(dim=1)

    def prune_mask(self) -> torch.Tensor:
        """Keep points that received a meaningful share of attention (or were never seen: keep them)."""
        mean_use = self.usage[self.hits > 0].mean() if bool((self.hits > 0).any()) else torch.tensor(0.0)
        return (self.hits == 0) | (self.usage > 1e-3 * mean_use)

    def clone_indices(self, frac: float, budget: int) -> torch.Tensor:
        n = min(int(frac * self.grad.shape[0]), budget)
        if n <= 0:
            return torch.zeros(0, dtype=torch.long, device=self.grad.device)
        score = self.grad / self.hits.clamp_min(1)
        return torch.topk(score, n).indices


_POINT_PARAMS = ("xyz", "features", "influence")


def build_optimizer(model: PointModel, cfg: TrainConfig) -> torch.optim.Adam:
    nets = [p for n, p in model.named_parameters() if n not in _POINT_PARAMS and not n.startswith("decoder.")]
    dec = [p for n, p in model.named_parameters() if n.startswith("decoder.")]
    groups = [
        {"params": [model.xyz], "lr": cfg.lr_points * float(model.spacing), "name": "xyz"},
        {"params": [model.features], "lr": cfg.lr_features, "name": "features"},
        {"params": [model.influence], "lr": cfg.lr_influence, "name": "influence"},
        {"params": nets, "lr": cfg.lr_networks, "name": "networks"},
    ]
    if dec:
        groups.append({"params": dec, "lr": cfg.lr_networks, "name": "decoder",
                       "weight_decay": cfg.decoder_weight_decay})
    return torch.optim.Adam(groups, weight_decay=0.0, decoupled_weight_decay=True)


def resize_points(model: PointModel, opt: torch.optim.Adam | None, src: torch.Tensor,
                  jitter: torch.Tensor | None = None, ema: ParamEMA | None = None):
    """Replace the point parameters by model.<param>[src] (src [N'] int64; + jitter [N', 3] on xyz), carrying Adam
    state (`opt`; None: a model that is not being trained) and the parameters' moving average (`ema`, when given)
    along.

    New Parameter objects are created (changing .data's shape in place confuses autograd)."""
    groups = {g["name"]: g for g in opt.param_groups} if opt is not None else {}
    for name in _POINT_PARAMS:
        old = getattr(model, name)
        data = old.detach()[src].clone()
        if name == "xyz" and jitter is not None:
            data += jitter
        new = torch.nn.Parameter(data)
        setattr(model, name, new)
        if opt is None:
            continue
        state = opt.state.pop(old, None)
        groups[name]["params"] = [new]
        if state:
            opt.state[new] = {k: (v[src].clone() if torch.is_tensor(v) and v.dim() > 0 else v)
                              for k, v in state.items()}
    if ema is not None:
        ema.resize(_POINT_PARAMS, src, jitter)


INTERIOR_VIEWS = 6  # finest-level training views a multi-scale fit renders both ways to pick the `auto` mode


@torch.no_grad()
def interior_gain(model: PointModel, split, views: int = INTERIOR_VIEWS, background=(1.0, 1.0, 1.0)) -> float:
    """What the `interior` decode gains inside the object, in dB of object PSNR: `interior+filtered` minus
    `filtered` (core/points/resolution.py) on `views` evenly spaced views of split (images [V, H, W, 3]) rendered
    at their size. A multi-scale fit measures its finest level, where the model's scale factor is 1 and the
    decoder's F_dec the ratio of the levels: real images finer than the decoder's training size. (A single-scale
    fit has none: its training views rendered at 2x and area-averaged back predicted the wrong sign on a
    ten-minute suzanne, docs/results.md "Resolution", so it measures nothing.) NaN for models without a residual
    UNet decoder or whose decoder runs at this size (both modes are the same frame)."""
    if model.decoder is None or not model.cfg.decoder_residual or views < 1:
        return float("nan")
    n = split.images.shape[0]
    ids = sorted({int(i) for i in torch.linspace(0, n - 1, min(views, n)).round().tolist()})
    if decoder_scale(model, None, split.c2w[ids[0]], split.focal, model.xyz.detach()) <= 1.0:
        return float("nan")
    scores = {}
    for mode in ("filtered", "interior+filtered"):
        def render(i, mode=mode):
            out = render_frame(model, split.c2w[i], split.height, split.width, split.focal, background=background,
                               mode=mode)
            return {"rgb": out["rgb"], "alpha": out["alpha"]}
        scores[mode] = mean_scores(score_views(render, split.images, split.alphas, ids))["psnr_object"]
    gain = scores["interior+filtered"] - scores["filtered"]
    return gain if math.isfinite(gain) else float("nan")


@torch.no_grad()
def evaluate(model: PointModel, split, views, background) -> dict:
    """Mean PSNR (full frame and object pixels) and SSIM over the given view indices of a split (the evaluation
    loop of core/images/metrics.py), plus what the collapse guard reads: `coverage`, the share of the ground
    truth's object pixels (alpha > 0.5) the render covers (alpha > 0.5); `blank_distance`, the mean
    |render − background| over those pixels; `object_contrast`, the same for the ground truth (how far the object
    is from a blank frame). NaN where a view has no object pixel (left out of the means)."""
    def render(i):
        out = render_frame(model, split.c2w[i], split.height, split.width, split.focal, background=background)
        gt = split.images[i].to(out["rgb"].device)
        obj = split.alphas[i].to(gt.device) > 0.5
        bg = torch.as_tensor(background, dtype=gt.dtype, device=gt.device)
        nan = float("nan")
        has = bool(obj.any())
        extra = {"coverage": float((out["alpha"][obj] > 0.5).float().mean()) if has else nan,
                 "blank_distance": float((out["rgb"][obj] - bg).abs().mean()) if has else nan,
                 "object_contrast": float((gt[obj] - bg).abs().mean()) if has else nan}
        return {"rgb": out["rgb"], "alpha": out["alpha"], "extra": extra}

    return mean_scores(score_views(render, split.images, split.alphas, views))


MIN_COVERAGE = 0.3  # a render covering less of the object's pixels than this renders nothing
BLANK_SHARE = 0.25  # a render this much closer to the blank frame than the truth is (over the object) is blank


def collapse_reason(scores: dict, floor: dict, margin_db: float) -> str | None:
    """Why a model's test scores (from `evaluate`) count as a collapsed fit, or None: not finite; covering too
    little of the object; or rendering (nearly) the blank frame where the truth does not — object PSNR within
    margin_db of the blank frame's (floor: `blank_floor` of the same views) and the render BLANK_SHARE times
    closer to the background than the ground truth. A near-white object on white stays fine when rendered right:
    its ground truth is as close to the background as its render."""
    vals = [scores.get("psnr"), scores.get("psnr_object")]
    if any(v is None or not math.isfinite(v) for v in vals):
        return "the test render is not finite"
    cov = scores.get("coverage", float("nan"))
    if math.isfinite(cov) and cov < MIN_COVERAGE:
        return f"the render covers {100 * cov:.0f} % of the object's pixels"
    blank = floor["psnr_object"]
    dist, contrast = scores.get("blank_distance", float("nan")), scores.get("object_contrast", float("nan"))
    if (math.isfinite(blank) and scores["psnr_object"] < blank + margin_db and math.isfinite(dist)
            and math.isfinite(contrast) and dist < BLANK_SHARE * contrast):
        return (f"the render is the blank frame: object PSNR {scores['psnr_object']:.2f} dB against the blank "
                f"frame's {blank:.2f} dB, {dist:.3f} from the background where the object is {contrast:.3f}")
    return None


def decline_reason(best: tuple[int, float] | None, scores: dict, margin_db: float) -> str | None:
    """Why a checkpoint's scores count as a fit that lost its object, or None: object PSNR more than margin_db
    (> 0) below the fit's best so far, best = (step, object PSNR) or None."""
    if best is None or margin_db <= 0:
        return None
    now = scores.get("psnr_object", float("nan"))
    if not math.isfinite(now) or best[1] - now <= margin_db:
        return None
    return (f"the object PSNR fell from {best[1]:.2f} dB at step {best[0]} to {now:.2f} dB "
            f"(coverage {scores.get('coverage', float('nan')):.2f})")


class CollapseGuard:
    """Watches a stage-1 fit and decides how to recover (TrainConfig.guard).

    On a collapse at a test checkpoint (`collapse_reason`): first reset the residual decoder's correction (the
    render is then the decoder-free one, which trains); on a second collapse, or without a residual decoder,
    restart the fit without a decoder. A checkpoint more than decline_db below the best one so far
    (`decline_reason`) restarts the fit with its settings while at most DECLINE_UNTIL of the budget is spent (a
    healthy fit's test curve dips by about 1 dB at most). Non-finite losses or gradients skip the step; a run of
    them restarts. At most MAX_RESTARTS restarts in all. Every action is appended to `events` (step, seconds,
    action, reason)."""

    MAX_BAD_STEPS = 20
    MIN_FRACTION = 0.05  # no verdict before this share of the budget (and MIN_STEPS): the first steps are rough
    MIN_STEPS = 50
    DECLINE_UNTIL = 0.6
    MAX_RESTARTS = 2

    def __init__(self, floor: dict, margin_db: float, decline_db: float = 0.0):
        self.floor = floor
        self.margin = margin_db
        self.decline_db = decline_db
        self.best: tuple[int, float] | None = None  # (step, object PSNR): the best checkpoint since the (re)start
        self.events: list[dict] = []
        self.bad_steps = 0
        self.skipped_steps = 0
        self.decoder_resets = 0
        self.restarts = 0

    def record(self, step: int, seconds: float, action: str, reason: str) -> None:
        self.events.append({"step": step, "seconds": round(seconds, 3), "action": action, "reason": reason})
        print(f"[fit] guard at step {step}: {reason}; {action}")

    def check(self, model: PointModel, scores: dict, step: int, frac: float) -> tuple[str | None, str | None]:
        """(action, reason) a checkpoint calls for: action None, "reset_decoder", "restart" (without a decoder) or
        "refit" (the same settings again); frac: the share of the budget spent since the fit (re)started."""
        if frac < self.MIN_FRACTION or step < self.MIN_STEPS:
            return None, None
        reason = collapse_reason(scores, self.floor, self.margin)
        if reason is None:
            reason = decline_reason(self.best, scores, self.decline_db)
            now = scores.get("psnr_object", float("nan"))
            if reason is None:
                if math.isfinite(now) and (self.best is None or now > self.best[1]):
                    self.best = (step, now)
                return None, None
            return ("refit" if frac <= self.DECLINE_UNTIL and self.restarts < self.MAX_RESTARTS else None), reason
        residual = model.decoder is not None and model.cfg.decoder_residual
        if residual and self.decoder_resets == 0:
            return "reset_decoder", reason
        return ("restart" if self.restarts < self.MAX_RESTARTS else None), reason

    def step_ok(self, loss: torch.Tensor, model: PointModel) -> bool:
        """True when the step's loss and gradients are finite; else the step is to be skipped."""
        ok = bool(torch.isfinite(loss))
        if ok:
            ok = all(bool(torch.isfinite(p.grad).all()) for p in model.parameters() if p.grad is not None)
        self.bad_steps = 0 if ok else self.bad_steps + 1
        self.skipped_steps += 0 if ok else 1
        return ok

    def summary(self) -> dict:
        return {"events": self.events, "skipped_steps": self.skipped_steps, "decoder_resets": self.decoder_resets,
                "restarts": self.restarts, "blank_floor": self.floor}


def fit_points(train, test, model_cfg: ModelConfig, cfg: TrainConfig, background=(1.0, 1.0, 1.0),
               progress_callback=None, show_progress: bool = True):
    """Train a PointModel. train/test: `SplitData` (images [V,H,W,3], alphas [V,H,W], c2w [V,4,4], focal, ...).
    With `cfg.train_scales`, train holds the images at the finest size (H, W divisible by every factor, else
    InputError); the visual hull starts from the coarsest level and the training footprint is the finest level's.
    test is rendered at its own size (the fit command passes it at the coarsest level).

    Returns (model, history) where history is a list of dicts (step, seconds, points, psnr, psnr_object, ssim,
    coverage) measured on `cfg.eval_views` test views; `seconds` is training wall-clock time, evaluation excluded.
    The last entry also holds "guard": the collapse guard's events, skipped steps, the blank floor of those views
    and "collapsed" (None, or why the final model still counts as collapsed).
    """
    threads = torch.get_num_threads()
    if cfg.threads > 0:
        torch.set_num_threads(cfg.threads)
    try:
        return _fit_points(train, test, model_cfg, cfg, background, progress_callback, show_progress)
    finally:
        torch.set_num_threads(threads)  # a process-wide setting: do not leave it changed


def _fit_points(train, test, model_cfg, cfg, background, progress_callback, show_progress):
    torch.manual_seed(cfg.seed)
    gen = torch.Generator().manual_seed(cfg.seed)
    dev = resolve_device(cfg.device)
    # Multi-scale training: one split per level, fine to coarse; the coarsest is the training size.
    scales = parse_scales(cfg.train_scales)
    finals = lr_finals(cfg)  # each parameter group's final learning-rate fraction
    levels = [train] if not scales else list(pyramid(train, scales).values())
    level_p = torch.tensor(parse_weights(cfg.train_scale_weights, len(levels)), dtype=torch.float64)
    level_steps = [0] * len(levels)  # steps (with --train-scale-mix: step parts) per level
    # --train-scale-mix: the finer part's level, by the finer levels' shares (equal when those are all 0)
    fine_p = level_p[:-1] if float(level_p[:-1].sum()) > 0 else torch.ones(max(len(levels) - 1, 1),
                                                                            dtype=torch.float64)
    fine, coarse = levels[0], levels[-1]
    xyz = visual_hull_points(coarse.alphas, coarse.c2w, coarse.focal, model_cfg.num_points, seed=cfg.seed)

    def start(mcfg):
        m = PointModel(mcfg, xyz, mean_spacing(xyz)).to(dev)
        m.train_footprint.fill_(training_footprint(fine.c2w, fine.focal, xyz))
        m.decoder_footprint.fill_(training_footprint(coarse.c2w, coarse.focal, xyz))
        o = build_optimizer(m, cfg)
        ema = ParamEMA(m, cfg.ema) if cfg.ema > 0 else None
        return m, o, [g["lr"] for g in o.param_groups], Densifier(m.num_points, dev), ema

    def restart(mcfg, reason, same: bool = False):
        """The guard's restart: a new model without a decoder (the last resort after a collapse), or with the same
        settings (same: after a decline; the random course goes on, so the new fit takes another); the schedules
        rerun over the remaining budget."""
        guard.restarts += 1
        guard.best = None
        guard.record(step, train_s, "restarted the fit with the same settings" if same
                     else "restarted the fit without a decoder", reason)
        if not same:
            mcfg = dataclasses.replace(mcfg, decoder="none")
        return (mcfg, *start(mcfg))

    model, opt, base_lrs, dens, ema = start(model_cfg)
    bg = torch.as_tensor(background, dtype=torch.float32, device=dev)
    c2ws = train.c2w
    eval_ids = list(range(0, len(test.files), max(1, len(test.files) // max(cfg.eval_views, 1))))[: cfg.eval_views]
    guard = CollapseGuard(blank_floor(test.images, test.alphas, eval_ids, background), cfg.guard_margin,
                          cfg.guard_decline)
    history: list[dict] = []
    budget_s = cfg.minutes * 60.0 if cfg.minutes > 0 else float("inf")
    train_s = 0.0
    next_eval = 0.0
    step = 0
    # A restart (the guard's last resort) runs the schedules again over what is left of the budget.
    step0, sec0 = 0, 0.0
    by_time = budget_s < float("inf")
    # CPU threads: test renders use all (--threads); the step shares its large pieces out to `workers` (on the CPU),
    # and runs its other operations on op_threads
    threads = torch.get_num_threads()
    workers = (cfg.workers or threads) if dev.type == "cpu" else 1
    op_threads = cfg.op_threads or (1 if workers > 1 else threads)

    def level_loss(lv, patches: int):
        """One level's part of a step: `patches` patches of random views of level lv (--views-per-step of them)
        rendered, decoded and compared with their images. Returns (loss, idx [R, K], attention)."""
        images, alphas = lv.images, lv.alphas
        v = int(torch.randint(images.shape[0], (1,), generator=gen))
        zoom = 1
        if cfg.zoom_frac > 0 and float(torch.rand(1, generator=gen)) < cfg.zoom_frac:
            zoom = int(torch.randint(2, cfg.zoom_max + 1, (1,), generator=gen))
        n_patches = max(1, patches // (zoom * zoom))
        views = step_views(v, min(cfg.views_per_step, n_patches), images.shape[0], gen)
        parts = []  # per view: c2w, its patches' pixel centres, targets
        for vj, n_j in zip(views, share_patches(n_patches, len(views))):
            px, rows, cols, size = sample_patches(alphas[vj], n_j, cfg.patch_size, cfg.fg_patch_frac, gen)
            if cfg.ray_jitter > 0:
                px = jitter_patches(px, n_j, cfg.ray_jitter, gen)
            if cfg.ray_jitter > 0 and cfg.jitter_target == "bilinear":  # the images where the shifted rays are
                gt = sample_bilinear(images[vj], px).to(dev)
                gt_a = sample_bilinear(alphas[vj], px).to(dev)
            else:
                gt = images[vj][rows, cols].to(dev)
                gt_a = alphas[vj][rows, cols].to(dev)
            px = px.to(dev)
            if zoom > 1:  # the rays of a frame zoom times larger; the losses compare their average per pixel
                px = zoom_pixels(px, size, zoom)
            parts.append((c2ws[vj].to(dev), px, gt, gt_a))
        gt, gt_a = torch.cat([p[2] for p in parts]), torch.cat([p[3] for p in parts])
        if zoom > 1:
            pix_of_ray = pool_index(n_patches, size, zoom).to(dev)
        search = model.xyz.detach()
        p_drop = point_dropout(frac, cfg.dropout, cfg.dropout_end)
        if p_drop > 0:
            drop = torch.rand(search.shape[0], generator=gen).to(dev) < p_drop
            search = torch.where(drop[:, None], torch.full_like(search, float("nan")), search)
        found = [patch_neighbors(search, model_cfg, c2w, lv, px, zoom) for c2w, px, _, _ in parts]
        o, d, idx = (torch.cat(x) for x in zip(*found))
        att, sh = attend_and_shade(model, o, d, idx, bg, cfg.key_path, workers)
        zs = size * zoom
        if model.decoder is None:
            rgb = sh["rgb"]
        else:
            feat = sh["feature"].reshape(n_patches, zs, zs, -1).permute(0, 3, 1, 2)
            if cfg.decoder_dropout > 0:  # the residual decoder's base colour and coverage stay
                feat = feature_dropout(feat, cfg.decoder_dropout, 4 if model.cfg.decoder_residual else 0,
                                       gen)
            sym = int(torch.randint(8, (1,), generator=gen)) if cfg.decoder_flip else 0
            rgb, dec_alpha = model.decode_with_alpha(dihedral(feat, sym), workers=workers)
            rgb = dihedral(rgb, sym, inverse=True).permute(0, 2, 3, 1).reshape(-1, 3)
            if dec_alpha is not None:
                dec_alpha = dihedral(dec_alpha, sym, inverse=True)
            if dec_alpha is not None and zoom > 1:
                dec_alpha = pool_zoomed(dec_alpha.reshape(-1, 1), n_patches, size, zoom)
        cover = 1.0 - att["bg"]
        if zoom > 1:
            rgb = pool_zoomed(rgb, n_patches, size, zoom)
            cover = pool_zoomed(cover[:, None], n_patches, size, zoom)[:, 0]
        loss = F.mse_loss(rgb, gt)
        if model.decoder is not None and dec_alpha is not None and cfg.decoder_alpha_weight > 0:
            loss = loss + cfg.decoder_alpha_weight * F.mse_loss(dec_alpha.reshape(-1), gt_a)
        if cfg.alpha_weight > 0:
            loss = loss + cfg.alpha_weight * F.mse_loss(cover, gt_a)
        if model.decoder is not None and model.cfg.decoder_residual and cfg.base_weight > 0:
            base = sh["feature"][:, :3]
            if zoom > 1:
                base = pool_zoomed(base, n_patches, size, zoom)
            loss = loss + cfg.base_weight * F.mse_loss(base, gt)
        if cfg.ssim_weight > 0:
            pr = rgb.reshape(n_patches, size, size, 3)
            loss = loss + cfg.ssim_weight * (1 - ssim(pr, gt.reshape(n_patches, size, size, 3)))
        c2r = c2s = torch.zeros((), device=dev)
        if frac >= cfg.reg_start:
            fg_mask = (gt_a[pix_of_ray] if zoom > 1 else gt_a) > 0.5
            if cfg.close2ray:
                c2r = close_to_ray(att, o, d, fg_mask)
                loss = loss + cfg.close2ray_weight * c2r
            if cfg.close2surface:
                c2s = close_to_surface(att, fg_mask)
                loss = loss + cfg.close2surface_weight * c2s
        return loss, idx, att

    max_steps = step_cap(cfg)  # inf: a time budget alone, the minutes decide
    floaters = 0  # points removed as floaters (core/points/floaters.py), at the pruning steps and the end
    with Progress(1000 if by_time else int(max_steps), "fit", callback=progress_callback,
                  enabled=show_progress) as bar:
        while step < max_steps and train_s < budget_s:
            frac = max((step - step0) / max(max_steps - step0, 1), (train_s - sec0) / (budget_s - sec0))
            if train_s >= next_eval:
                torch.set_num_threads(threads)
                scores = evaluate(model, test, eval_ids, background)
                history.append({"step": step, "seconds": round(train_s, 3), "points": model.num_points, **scores})
                next_eval = train_s + cfg.eval_every
                action, reason = guard.check(model, scores, step, frac) if cfg.guard else (None, None)
                if action == "reset_decoder":
                    guard.decoder_resets += 1
                    guard.best = None  # the decoder-free render starts lower: measure declines from it
                    guard.record(step, train_s, "reset the decoder's correction to zero", reason)
                    model.reset_decoder_correction()
                    zeroed = [*model.decoder.out.parameters()]
                    if model.decoder.alpha_head is not None:
                        zeroed += [*model.decoder.alpha_head[-1].parameters()]
                    for p in zeroed:  # fresh Adam moments for the zeroed layers
                        opt.state.pop(p, None)
                    if ema is not None:  # the decoder's average restarts from the reset decoder
                        ema.reset(model, "decoder.")
                elif action in ("restart", "refit"):
                    model_cfg, model, opt, base_lrs, dens, ema = restart(model_cfg, reason, same=action == "refit")
                    step0, sec0 = step, train_s
                    frac = 0.0
                    floaters = 0  # the new model's
            t0 = time.perf_counter()
            if torch.get_num_threads() != op_threads:
                torch.set_num_threads(op_threads)
            dec_factor = decoder_lr_factor(frac, cfg.decoder_stop)
            for g, lr in zip(opt.param_groups, base_lrs):
                g["lr"] = lr * finals[g["name"]] ** frac * (dec_factor if g["name"] == "decoder" else 1.0)
            n_coarse = mixed_patches(cfg.patches, cfg.train_scale_mix, len(levels))
            if n_coarse:  # the step's patches on the training size and on one finer level, one backward
                li = int(torch.multinomial(fine_p, 1, generator=gen))
                level_steps[li] += 1
                level_steps[-1] += 1
                l_c, idx_c, att_c = level_loss(levels[-1], n_coarse)
                l_f, idx_f, att_f = level_loss(levels[li], cfg.patches - n_coarse)
                w = n_coarse / cfg.patches  # the patches' shares: one MSE over all the step's rays
                loss = w * l_c + (1.0 - w) * l_f
                idx, att = torch.cat([idx_c, idx_f]), {"weights": torch.cat([att_c["weights"], att_f["weights"]])}
                li = len(levels) - 1  # the step has the training size's patches: it trains everything
            else:
                li = pick_level(level_p, frac, cfg.train_scale_settle, gen)
                level_steps[li] += 1
                loss, idx, att = level_loss(levels[li], cfg.patches)
            opt.zero_grad(set_to_none=True)
            loss.backward()
            if li != len(levels) - 1:  # a finer level's step: only what --train-scale-fine names trains
                for p in frozen_on_fine(model, cfg.train_scale_fine):
                    p.grad = None  # no gradient: Adam leaves the parameter (and its moments) as it is
            if cfg.guard and not guard.step_ok(loss, model):
                # a non-finite loss or gradient: skip the update; a run of them starts the fit again
                opt.zero_grad(set_to_none=True)
                if guard.bad_steps >= guard.MAX_BAD_STEPS and guard.restarts < 2:
                    model_cfg, model, opt, base_lrs, dens, ema = restart(
                        model_cfg, f"{guard.bad_steps} steps in a row had a non-finite loss or gradient")
                    step0, sec0 = step, train_s
                    guard.bad_steps = 0
                    floaters = 0  # the new model's
                step += 1
                train_s += time.perf_counter() - t0
                continue
            dens.accumulate(model, idx, att["weights"])
            opt.step()
            if ema is not None:
                ema.update(model)
            step += 1
            # Densification between 10 % and 70 % of training, when geometry is coarse-right but still moving.
            if 0.1 <= frac <= 0.7:
                if cfg.prune_every and step % cfg.prune_every == 0:
                    kept = dens.prune_mask()
                    specks = torch.zeros_like(kept)
                    if cfg.floaters_while_pruning and not cfg.keep_floaters:
                        specks = floater_mask(model.xyz.detach(), cfg.floater_size, cfg.floater_radius)
                        kept &= ~specks
                    keep = torch.nonzero(kept).squeeze(1)
                    if keep.numel() >= model_cfg.k and keep.numel() < model.num_points:
                        resize_points(model, opt, keep, ema=ema)
                        dens.reset(model.num_points, dev)
                        floaters += int(specks.sum())
                if cfg.clone_every and step % cfg.clone_every == 0 and model.num_points < cfg.max_points:
                    src = dens.clone_indices(cfg.clone_frac, cfg.max_points - model.num_points)
                    if src.numel():
                        allidx = torch.cat([torch.arange(model.num_points, device=dev), src])
                        jit = torch.zeros(allidx.shape[0], 3, device=dev)
                        jit[-src.numel():] = 0.5 * float(model.spacing) * torch.randn(src.numel(), 3, generator=gen).to(dev)
                        resize_points(model, opt, allidx, jit, ema=ema)
                        dens.reset(model.num_points, dev)
            train_s += time.perf_counter() - t0
            info = dict(step=step, loss=float(loss.detach()), pts=model.num_points,
                        psnr=history[-1]["psnr"] if history else float("nan"))
            if by_time:
                bar.set_fraction(max(step / max_steps, train_s / budget_s), **info)
            else:
                bar.update(1, **info)
    torch.set_num_threads(threads)
    # the training pixel's world size at the final points (what renders at other sizes are scaled against)
    model.train_footprint.fill_(training_footprint(fine.c2w, fine.focal, model.xyz.detach()))
    raw = None
    if ema is not None:  # the trained parameters' scores, then the model becomes their average
        raw = evaluate(model, test, eval_ids, background)
        ema.swap(model)
    if not cfg.keep_floaters:
        drop = floater_mask(model.xyz.detach(), cfg.floater_size, cfg.floater_radius)
        if bool(drop.any()):
            floaters += int(drop.sum())
            resize_points(model, opt, torch.nonzero(~drop).squeeze(1))
    model.train_footprint.fill_(training_footprint(fine.c2w, fine.focal, model.xyz.detach()))
    model.decoder_footprint.fill_(training_footprint(coarse.c2w, coarse.focal, model.xyz.detach()))
    # which decode the render mode `auto` uses inside the object beyond the training size (measured, not guessed)
    gain = interior_gain(model, fine, background=background) if len(levels) > 1 else float("nan")
    model.interior_gain.fill_(gain if math.isfinite(gain) else 0.0)  # 0: nothing measured, `filtered`
    scores = evaluate(model, test, eval_ids, background)
    reason = collapse_reason(scores, guard.floor, cfg.guard_margin)
    declined = decline_reason(guard.best, scores, cfg.guard_decline) if cfg.guard else None
    history.append({"step": step, "seconds": round(train_s, 3), "points": model.num_points, **scores,
                    "floaters_removed": floaters, "interior_gain": gain if math.isfinite(gain) else None,
                    "guard": {**guard.summary(), "collapsed": reason, "declined": declined}})
    if raw is not None:  # the scores above are the average's (what is returned); these the trained parameters'
        history[-1]["raw"] = raw
    if scales:  # steps per level, finest first: {"1": n, "2": n, ...}
        history[-1]["train_levels"] = {str(s): n for s, n in zip(scales, level_steps)}
    return model, history
