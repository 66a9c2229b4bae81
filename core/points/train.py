"""Stage 1: fit a PAPR point model to multi-view images (with the paper's geometry regularizers).

Each step renders a few random image patches of one training view (patches, not scattered rays, so the UNet
decoder and SSIM see image structure), with neighbours re-selected from the current points. Schedules run on the
fraction of the budget used (steps or wall-clock minutes, whichever ends first), so `--minutes` and `--steps`
give the same shape of training.
"""
from __future__ import annotations

import math
import time
from dataclasses import dataclass

import torch
import torch.nn.functional as F

from core.config import opt
from core.images.metrics import mean_scores, score_views, ssim
from core.points.render import render_frame
from core.images.cameras import rays_for_pixels
from core.points.init import visual_hull_points
from core.points.model import ModelConfig, PointModel, mean_spacing
from core.points.regularizers import close_to_ray, close_to_surface
from core.points.select import select_neighbors
from core.util.device import resolve_device
from core.util.progress import Progress


@dataclass
class TrainConfig:
    """Stage-1 training (PAPR + geometry regularizers)."""

    steps: int = opt(6000, "maximum optimisation steps")
    minutes: float = opt(0.0, "wall-clock budget in minutes (0 = no limit; training ends at whichever comes first)")
    patches: int = opt(16, "image patches per step")
    patch_size: int = opt(16, "patch side in pixels")
    fg_patch_frac: float = opt(0.75, "fraction of patches centred on foreground pixels")
    lr_points: float = opt(0.1, "point position learning rate, in units of the initial point spacing")
    lr_features: float = opt(1e-2, "point feature learning rate")
    lr_influence: float = opt(1e-2, "point influence learning rate")
    lr_networks: float = opt(2e-3, "attention / value / decoder learning rate")
    lr_final: float = opt(0.05, "learning rates decay exponentially to this fraction")
    alpha_weight: float = opt(0.05, "weight of the foreground-mask loss (1 - background weight vs alpha)")
    decoder_alpha_weight: float = opt(0.5, "weight of the decoder mask head's loss (MSE against alpha)")
    ssim_weight: float = opt(0.0, "weight of the (1 - SSIM) loss on patches")
    close2ray: bool = opt(True, "use the close-to-ray regularizer")
    close2ray_weight: float = opt(0.002, "close-to-ray weight gamma")
    close2surface: bool = opt(True, "use the close-to-surface regularizer")
    close2surface_weight: float = opt(0.01, "close-to-surface weight eta")
    reg_start: float = opt(0.1, "fraction of training after which the regularizers start")
    prune_every: int = opt(500, "prune unused points every N steps (0 = never)")
    clone_every: int = opt(1000, "clone the points with the largest position gradient every N steps (0 = never)")
    clone_frac: float = opt(0.1, "fraction of points cloned each time")
    max_points: int = opt(12000, "densification stops at this many points")
    dropout: float = opt(0.3, "initial point dropout probability (cosine decay to 0 at half of training)")
    eval_every: float = opt(30.0, "seconds of training between test-PSNR measurements")
    eval_views: int = opt(4, "test views used for the PSNR-vs-time curve")
    seed: int = opt(0, "random seed")
    device: str = opt("auto", "cpu | cuda | auto")
    threads: int = opt(0, "torch CPU threads (0 = torch default)")


def _cosine(frac: float) -> float:
    return 0.5 * (1 + math.cos(math.pi * min(max(frac, 0.0), 1.0)))


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
    nets = [p for n, p in model.named_parameters() if n not in _POINT_PARAMS]
    return torch.optim.Adam([
        {"params": [model.xyz], "lr": cfg.lr_points * float(model.spacing), "name": "xyz"},
        {"params": [model.features], "lr": cfg.lr_features, "name": "features"},
        {"params": [model.influence], "lr": cfg.lr_influence, "name": "influence"},
        {"params": nets, "lr": cfg.lr_networks, "name": "networks"},
    ])


def resize_points(model: PointModel, opt: torch.optim.Adam, src: torch.Tensor, jitter: torch.Tensor | None = None):
    """Replace the point parameters by model.<param>[src] (+ jitter on xyz), carrying Adam state along.

    New Parameter objects are created (changing .data's shape in place confuses autograd)."""
    groups = {g["name"]: g for g in opt.param_groups}
    for name in _POINT_PARAMS:
        old = getattr(model, name)
        data = old.detach()[src].clone()
        if name == "xyz" and jitter is not None:
            data += jitter
        new = torch.nn.Parameter(data)
        state = opt.state.pop(old, None)
        setattr(model, name, new)
        groups[name]["params"] = [new]
        if state:
            opt.state[new] = {k: (v[src].clone() if torch.is_tensor(v) and v.dim() > 0 else v)
                              for k, v in state.items()}


@torch.no_grad()
def evaluate(model: PointModel, split, views, background) -> dict:
    """Mean PSNR (full frame and object pixels) and SSIM over the given view indices of a split."""
    def render(i):
        return render_frame(model, split.c2w[i], split.height, split.width, split.focal, background=background)
    return mean_scores(score_views(render, split.images, split.alphas, views))


def fit_points(train, test, model_cfg: ModelConfig, cfg: TrainConfig, background=(1.0, 1.0, 1.0),
               progress_callback=None, show_progress: bool = True):
    """Train a PointModel. train/test: `SplitData` (images [V,H,W,3], alphas [V,H,W], c2w [V,4,4], focal, ...).

    Returns (model, history) where history is a list of dicts (step, seconds, points, psnr, psnr_object, ssim)
    measured on `cfg.eval_views` test views; `seconds` is training wall-clock time, evaluation excluded.
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
    xyz = visual_hull_points(train.alphas, train.c2w, train.focal, model_cfg.num_points, seed=cfg.seed)
    model = PointModel(model_cfg, xyz, mean_spacing(xyz)).to(dev)
    opt = build_optimizer(model, cfg)
    base_lrs = [g["lr"] for g in opt.param_groups]
    dens = Densifier(model.num_points, dev)
    bg = torch.as_tensor(background, dtype=torch.float32, device=dev)
    images, alphas, c2ws = train.images, train.alphas, train.c2w
    eval_ids = list(range(0, len(test.files), max(1, len(test.files) // max(cfg.eval_views, 1))))[: cfg.eval_views]
    history: list[dict] = []
    budget_s = cfg.minutes * 60.0 if cfg.minutes > 0 else float("inf")
    train_s = 0.0
    next_eval = 0.0
    step = 0
    by_time = budget_s < float("inf")
    with Progress(1000 if by_time else cfg.steps, "fit", callback=progress_callback, enabled=show_progress) as bar:
        while step < cfg.steps and train_s < budget_s:
            if train_s >= next_eval:
                history.append({"step": step, "seconds": round(train_s, 3), "points": model.num_points,
                                **evaluate(model, test, eval_ids, background)})
                next_eval = train_s + cfg.eval_every
            t0 = time.perf_counter()
            frac = max(step / cfg.steps, train_s / budget_s)
            decay = cfg.lr_final ** frac
            for g, lr in zip(opt.param_groups, base_lrs):
                g["lr"] = lr * decay
            v = int(torch.randint(images.shape[0], (1,), generator=gen))
            px, rows, cols, size = sample_patches(alphas[v], cfg.patches, cfg.patch_size, cfg.fg_patch_frac, gen)
            gt = images[v][rows, cols].to(dev)
            gt_a = alphas[v][rows, cols].to(dev)
            c2w = c2ws[v].to(dev)
            px = px.to(dev)
            o, d = rays_for_pixels(c2w, px, train.height, train.width, train.focal)
            search = model.xyz.detach()
            p_drop = cfg.dropout * _cosine(min(frac * 2, 1.0))
            if p_drop > 0:
                drop = torch.rand(search.shape[0], generator=gen).to(dev) < p_drop
                search = torch.where(drop[:, None], torch.full_like(search, float("nan")), search)
            idx = select_neighbors(search, model_cfg.neighbors, model_cfg.k, c2w, train.height, train.width,
                                   train.focal, px, o, d)
            att = model.attend(model.xyz, model.influence, o, d, idx)
            sh = model.shade(att, d, idx, bg)
            if model.decoder is None:
                rgb = sh["rgb"]
            else:
                p = cfg.patches
                feat = sh["feature"].reshape(p, size, size, -1).permute(0, 3, 1, 2)
                rgb, dec_alpha = model.decode_with_alpha(feat)
                rgb = rgb.permute(0, 2, 3, 1).reshape(-1, 3)
            loss = F.mse_loss(rgb, gt)
            if model.decoder is not None and dec_alpha is not None and cfg.decoder_alpha_weight > 0:
                loss = loss + cfg.decoder_alpha_weight * F.mse_loss(dec_alpha.reshape(-1), gt_a)
            if cfg.alpha_weight > 0:
                loss = loss + cfg.alpha_weight * F.mse_loss(1.0 - att["bg"], gt_a)
            if cfg.ssim_weight > 0:
                pr = rgb.reshape(cfg.patches, size, size, 3)
                loss = loss + cfg.ssim_weight * (1 - ssim(pr, gt.reshape(cfg.patches, size, size, 3)))
            c2r = c2s = torch.zeros((), device=dev)
            if frac >= cfg.reg_start:
                fg_mask = gt_a > 0.5
                if cfg.close2ray:
                    c2r = close_to_ray(att, o, d, fg_mask)
                    loss = loss + cfg.close2ray_weight * c2r
                if cfg.close2surface:
                    c2s = close_to_surface(att, fg_mask)
                    loss = loss + cfg.close2surface_weight * c2s
            opt.zero_grad(set_to_none=True)
            loss.backward()
            dens.accumulate(model, idx, att["weights"])
            opt.step()
            step += 1
            # Densification between 10 % and 70 % of training, when geometry is coarse-right but still moving.
            if 0.1 <= frac <= 0.7:
                if cfg.prune_every and step % cfg.prune_every == 0:
                    keep = torch.nonzero(dens.prune_mask()).squeeze(1)
                    if keep.numel() >= model_cfg.k and keep.numel() < model.num_points:
                        resize_points(model, opt, keep)
                        dens.reset(model.num_points, dev)
                if cfg.clone_every and step % cfg.clone_every == 0 and model.num_points < cfg.max_points:
                    src = dens.clone_indices(cfg.clone_frac, cfg.max_points - model.num_points)
                    if src.numel():
                        allidx = torch.cat([torch.arange(model.num_points, device=dev), src])
                        jit = torch.zeros(allidx.shape[0], 3, device=dev)
                        jit[-src.numel():] = 0.5 * float(model.spacing) * torch.randn(src.numel(), 3, generator=gen).to(dev)
                        resize_points(model, opt, allidx, jit)
                        dens.reset(model.num_points, dev)
            train_s += time.perf_counter() - t0
            info = dict(step=step, loss=float(loss.detach()), pts=model.num_points,
                        psnr=history[-1]["psnr"] if history else float("nan"))
            if by_time:
                bar.set_fraction(max(step / cfg.steps, train_s / budget_s), **info)
            else:
                bar.update(1, **info)
    history.append({"step": step, "seconds": round(train_s, 3), "points": model.num_points,
                    **evaluate(model, test, eval_ids, background)})
    return model, history
