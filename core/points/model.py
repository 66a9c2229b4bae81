"""PAPR point model: learnable points, features and influence, proximity attention with a background slot.

For ray i with K neighbour points p_ij (chosen by `core.points.neighbors`), the attention logit of neighbour j is
an MLP of rotation-invariant ray-relative geometry (perpendicular distance to the ray, depth behind the ray's
nearest neighbour, both in units of the point spacing) plus the point's learned influence. One extra background
slot competes in the softmax. The ray's feature is Σ a_ij v_ij; the surface point is x_i = Σ a_ij p_ij / Σ a_ij
(background slot dropped). Relative geometry only (no absolute positions in the keys) is what lets attention be
re-inferred after the points were deformed.
"""
from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass

import torch
import torch.nn as nn
import torch.nn.functional as F

from core.config import opt
from core.points.decoders import UNetDecoder
from core.points.key_mlp import KEY_PATHS, key_logits, standard_key_mlp
from core.points.neighbors.base import METHODS
from core.util.errors import InputError
from core.util.workers import split_batch

# Every model trains over white (datasets are composited onto it, `load_split`'s default): a decoder learns to
# paint this background itself, so renders over another colour must move its share (core/points/render.py).
TRAIN_BACKGROUND = (1.0, 1.0, 1.0)


@dataclass
class ModelConfig:
    """The PAPR point model (points, attention, decoder)."""

    num_points: int = opt(4000, "initial number of points (seeded inside the visual hull)", min=1, max=10_000_000)
    feature_dim: int = opt(32, "per-point feature size h", min=1, max=1024)
    k: int = opt(20, "neighbours per ray K", min=1, max=256)
    neighbors: str = opt("screen_depth", "neighbour search: screen | screen_depth | perpendicular",
                         choices=METHODS)
    neighbor_radius_px: float = opt(0.0, "screen metrics: a point is a candidate only within this many pixels of "
                                         "the ray's pixel (rays with none hit the background); 0 = auto from the "
                                         "projected point density, -1 = no cap", min=-1.0)
    decoder: str = opt("none", "decoder: none (value = RGB) | unet (small UNet on the feature image)",
                       choices=("none", "unet"))
    decoder_residual: bool = opt(True, "the unet decoder adds a learned correction (zero at initialisation) to the "
                                       "points' own colours, so it starts as, and cannot collapse below, the "
                                       "decoder-free render")
    decoder_alpha: bool = opt(True, "the unet decoder also predicts foreground alpha (a separate mask head): the "
                                    "coverage of atlas-coloured and painted rays")
    decoder_width: int = opt(32, "channels of the unet decoder's first level (the second has twice as many)",
                             min=1, max=1024)
    key_width: int = opt(64, "width of the attention key MLP", min=1, max=4096)
    key_freqs: int = opt(4, "Fourier frequencies of the ray-relative key features", min=0, max=16)
    value_width: int = opt(64, "width of the value MLP", min=1, max=4096)
    view_dependent: bool = opt(False, "let colours depend on the viewing direction (off for emission scenes)")
    temperature: float = opt(1.0, "softmax temperature at render time (< 1 sharpens attention)", min=1e-3, max=1e3)


def fourier(x: torch.Tensor, freqs: int) -> torch.Tensor:
    """x [..., D] -> [..., D * (1 + 2 * freqs)]: raw values plus sin/cos at octave frequencies."""
    if freqs <= 0:
        return x
    scales = 2.0 ** torch.arange(freqs, device=x.device, dtype=x.dtype)
    xs = (x[..., None] * scales).flatten(-2)
    return torch.cat([x, torch.sin(xs), torch.cos(xs)], dim=-1)


def _mlp(d_in: int, width: int, d_out: int, layers: int = 2) -> nn.Sequential:
    mods: list[nn.Module] = []
    d = d_in
    for _ in range(layers):
        mods += [nn.Linear(d, width), nn.ReLU(inplace=True)]
        d = width
    mods.append(nn.Linear(d, d_out))
    return nn.Sequential(*mods)


def safe_normalize(v: torch.Tensor, eps: float = 1e-12) -> torch.Tensor:
    return v / v.norm(dim=-1, keepdim=True).clamp_min(eps)


class PointModel(nn.Module):
    """Points + proximity attention. Shapes: N points, R rays, K neighbours, h features."""

    def __init__(self, cfg: ModelConfig, xyz: torch.Tensor, spacing: float):
        super().__init__()
        self.cfg = cfg
        n = xyz.shape[0]
        self.xyz = nn.Parameter(xyz.detach().clone().float())                       # [N, 3]
        self.features = nn.Parameter(0.1 * torch.randn(n, cfg.feature_dim))         # [N, h]
        self.influence = nn.Parameter(torch.zeros(n))                                # [N]
        # Length unit of the key features: the typical spacing between neighbouring points.
        self.register_buffer("spacing", torch.tensor(float(spacing)))
        # World size of one training pixel at the object (core/points/resolution.py; 0 = unknown, older files):
        # frames with finer pixels than this are rendered by the resolution mode of core/points/render.py.
        self.register_buffer("train_footprint", torch.tensor(0.0))
        # World size of one pixel of the training size, which the decoder is run at (core/points/resolution.py):
        # the coarsest level of a multi-scale fit (its train_footprint is the finest level's), where
        # `--train-scales auto` gives the decoder most of its steps; 0 = train_footprint (older files).
        self.register_buffer("decoder_footprint", torch.tensor(0.0))
        # dB the `interior` blend gained over the full-size decode on a multi-scale fit's finest level (measured
        # by the fit, core/points/train.py `interior_gain`; 0 = no gain or not measured: single-scale fits, no
        # decoder, older files): the render mode `auto` follows it.
        self.register_buffer("interior_gain", torch.tensor(0.0))
        key_in = 2 * (1 + 2 * cfg.key_freqs)
        self.key_mlp = _mlp(key_in, cfg.key_width, 1)
        self.bg_logit = nn.Parameter(torch.tensor(0.0))
        dir_in = 3 * (1 + 2 * 2) if cfg.view_dependent else 0
        if cfg.decoder == "none":
            self.value_mlp = _mlp(cfg.feature_dim + dir_in, cfg.value_width, 3, layers=1)
            self.bg_value = None
            self.decoder = None
        else:
            # Residual decoder: each value also carries an RGB colour (3 leading channels), blended like the
            # decoder-free render and handed to the UNet as its base, with the attention's coverage.
            colour = 3 if cfg.decoder_residual else 0
            self.value_mlp = _mlp(cfg.feature_dim + dir_in, cfg.value_width, colour + cfg.feature_dim, layers=1)
            self.bg_value = nn.Parameter(torch.zeros(cfg.feature_dim))
            self.decoder = UNetDecoder((colour + 1 if colour else 0) + cfg.feature_dim, width=cfg.decoder_width,
                                       alpha=cfg.decoder_alpha, residual=cfg.decoder_residual)

    @property
    def num_points(self) -> int:
        return self.xyz.shape[0]

    # ---- attention -------------------------------------------------------------------------------------------
    def attend(self, points: torch.Tensor, influence: torch.Tensor, origins: torch.Tensor, dirs: torch.Tensor,
               idx: torch.Tensor, temperature: float | None = None, inv_f: torch.Tensor | None = None,
               log_window: torch.Tensor | None = None, keys: str = "auto", rebase_depth: bool = False) -> dict:
        """Attention over each ray's neighbours plus the background slot.

        Args: points [N, 3] (canonical or deformed positions), influence [N], origins [R, 3], dirs [R, 3] (unit),
        idx [R, K] int64 neighbour indices (-1 = empty slot).
        inv_f [N, 3, 3]: inverse local deformation gradients of deformed points (core/edits/deformation.py); the
        key features are then measured in each neighbour's canonical frame: with δ = p − (o + t_min d) the offset
        from the ray's reference point, u = F⁻¹ δ and the ray direction d' = F⁻¹ d / |F⁻¹ d| mapped the same way,
        depth = u·d' and distance = |u − (u·d') d'| (the same numbers as without inv_f when F = I).
        rebase_depth (with inv_f): the depths are then taken from the ray's nearest neighbour in these canonical
        frames instead of from the deformed ray's nearest one: neighbour j's depth u·d' is 0 at the point
        t_min + depth_j / |F_j⁻¹ d| of the deformed ray (its foot); every depth is measured from the nearest foot,
        depth_j − min_l(depth_l / |F_l⁻¹ d|) |F_j⁻¹ d| (the same numbers when F = I; for one affine map shared by
        all neighbours exactly the canonical model's depths along the canonical ray). A deformation that is no
        rigid motion reorders depths (a squash's canonical ray runs across the squashed axis), and the key learned
        "depth behind the nearest neighbour".
        log_window [R, K]: added to the neighbours' logits (finite; core/points/neighbors/select.py
        `select_neighbors_soft`: a neighbour's share faded out towards the edges of its footprint).
        keys: how the key MLP runs: "torch" (autograd through the module), "chunked" (core/points/key_mlp.py: only
        the non-empty slots, in cache-sized chunks, a hand-written backward; the same numbers to float rounding,
        about half the time of a training step's key MLP) or "auto" (chunked when gradients are on and the key MLP
        is the standard one; without gradients the renderers chunk the rays themselves).
        Returns dict: weights [R, K] (0 on empty slots), bg [R] background weight, x [R, 3] surface point
        (NaN-free: rays with no neighbour get the ray point at the mean depth 0), t [R, K] depth along the ray.
        """
        valid = idx >= 0
        safe_idx = idx.clamp_min(0)
        # index_select rather than points[safe_idx]: the same values, and its backward (index_add) is 2x faster
        flat_idx = safe_idx.reshape(-1)
        p = points.index_select(0, flat_idx).view(*idx.shape, points.shape[-1])  # [R, K, 3]
        rel = p - origins[:, None, :]
        t = (rel * dirs[:, None, :]).sum(-1)                                   # [R, K]
        perp = rel - t[..., None] * dirs[:, None, :]
        rho = perp.norm(dim=-1)
        s = self.spacing.clamp_min(1e-12)
        big = torch.finfo(t.dtype).max / 4
        t_min = torch.where(valid, t.detach(), torch.full_like(t, big)).min(dim=1, keepdim=True).values
        t_min = torch.where(t_min >= big, torch.zeros_like(t_min), t_min)
        # Clamp the key features: points sent far away or huge scene scales must not overflow the Fourier terms.
        depth = t - t_min
        if inv_f is not None:  # key geometry in each neighbour's canonical frame
            fi = inv_f[safe_idx]                                                  # [R, K, 3, 3]
            delta = rel - t_min[..., None] * dirs[:, None, :]
            u = (fi @ delta[..., None]).squeeze(-1)
            fd = (fi @ dirs[:, None, :, None].expand(-1, idx.shape[1], -1, -1)).squeeze(-1)  # F⁻¹ d [R, K, 3]
            dc = safe_normalize(fd)
            depth = (u * dc).sum(-1)
            rho = (u - depth[..., None] * dc).norm(dim=-1)
            if rebase_depth:  # from the nearest neighbour in the canonical frames (empty slots left out)
                # neighbour j's canonical depth falls by g_j = |F_j⁻¹ d| per unit along the deformed ray, so it is 0
                # at depth_j / g_j past t_min (its foot): measure every depth from the nearest foot
                g = fd.norm(dim=-1).clamp_min(1e-12)
                foot = depth.detach() / g
                ok = valid & torch.isfinite(foot)
                f_min = torch.where(ok, foot, torch.full_like(foot, big)).min(dim=1, keepdim=True).values
                f_min = torch.where((f_min >= big) | ~torch.isfinite(f_min), torch.zeros_like(f_min), f_min)
                depth = depth - f_min * g
        feats = torch.stack([(rho / s).clamp(max=64.0), (depth / s).clamp(-64.0, 64.0)], dim=-1)
        if keys not in KEY_PATHS:
            raise InputError(f"attend: keys must be one of {KEY_PATHS}, got {keys!r}")
        standard = standard_key_mlp(self.key_mlp)
        if keys == "chunked" and not standard:
            raise InputError("attend: keys='chunked' needs the standard key MLP (Linear, ReLU, Linear, ReLU, Linear)")
        if keys == "chunked" or (keys == "auto" and standard and torch.is_grad_enabled()):
            # empty slots are masked out of the softmax below: their logits are never used
            key = key_logits(self.key_mlp, feats, self.cfg.key_freqs, valid)
        else:
            key = self.key_mlp(fourier(feats, self.cfg.key_freqs)).squeeze(-1)
        # Influence clamped: ±1e30 softmaxes fine (max subtracted), an infinite one (diverged fit) would give inf − inf.
        logits = key + influence.index_select(0, flat_idx).view(idx.shape).clamp(-1e30, 1e30)
        if log_window is not None:
            logits = logits + log_window.to(logits.dtype).clamp(-1e30, 0.0)
        temp = self.cfg.temperature if temperature is None else temperature
        all_logits = torch.cat([logits, self.bg_logit.expand(logits.shape[0], 1)], dim=1) / max(temp, 1e-3)
        all_logits = all_logits.masked_fill(torch.cat([~valid, torch.zeros_like(valid[:, :1])], 1), float("-inf"))
        # The background slot is always valid, so every row has a finite max and softmax never sees all -inf.
        a = torch.softmax(all_logits, dim=1)
        w, bg = a[:, :-1], a[:, -1]
        # x_i = Σ a_ij p_ij / Σ a_ij, computed as a softmax over the neighbour slots alone: identical when the
        # foreground weight is positive, and still well defined when it underflows to zero (far-away rays).
        any_valid = valid.any(dim=1, keepdim=True)
        fg_logits = all_logits[:, :-1].masked_fill(~any_valid, 0.0)
        a_fg = torch.softmax(fg_logits, dim=1)
        x = (a_fg[..., None] * p).sum(1)
        x = torch.where(any_valid, x, origins)  # no neighbour at all: a finite placeholder, marked by bg = 1
        return {"weights": w, "bg": bg, "x": x, "t": t, "p": p, "valid": valid, "fg_weights": a_fg}

    # ---- values ------------------------------------------------------------------------------------------------
    def point_values(self, dirs: torch.Tensor | None = None, idx: torch.Tensor | None = None,
                     features: torch.Tensor | None = None) -> torch.Tensor:
        """Values per neighbour: [R, K, C] (C = 3 RGB in [0,1] without decoder; with the residual decoder 3 + h:
        RGB in [0, 1], then the features; else h).
        features [M, h] overrides the model's (e.g. features gathered by point ids after a part was duplicated)."""
        feats = self.features if features is None else features
        if self.cfg.view_dependent:
            f = feats[idx.clamp_min(0)]
            d = fourier(dirs, 2)[:, None, :].expand(-1, f.shape[1], -1)
            v = self.value_mlp(torch.cat([f, d], dim=-1))
        else:  # values depend on the point only: evaluate once per point, then gather (N << R*K)
            v = self.value_mlp(feats)[idx.clamp_min(0)]
        return self._activate(v)

    def point_table(self, features: torch.Tensor | None = None, rows: torch.Tensor | None = None
                    ) -> torch.Tensor | None:
        """Values of each point [M, C] (what point_values gathers per neighbour; features [M, h] as there), or
        None when values depend on the view direction. Computed once per frame, it serves every chunk of rays.
        rows [P] long: only those points' values are computed (the points a frame's rays hold; each row's value is
        the same as in the whole table), the other rows are 0."""
        if self.cfg.view_dependent:
            return None
        feats = self.features if features is None else features
        if rows is not None:
            table = feats.new_zeros((feats.shape[0], self.value_mlp[-1].out_features))
            table[rows] = self._activate(self.value_mlp(feats[rows]))
            return table
        return self._activate(self.value_mlp(feats))

    def _activate(self, v: torch.Tensor) -> torch.Tensor:
        """The value MLP's output [..., C] as point values (sigmoid colours; a residual decoder's features raw)."""
        if self.decoder is None:
            return torch.sigmoid(v)
        if self.cfg.decoder_residual:
            return torch.cat([torch.sigmoid(v[..., :3]), v[..., 3:]], dim=-1)
        return v

    def shade(self, att: dict, dirs: torch.Tensor, idx: torch.Tensor, background: torch.Tensor,
              features: torch.Tensor | None = None, table: torch.Tensor | None = None) -> dict:
        """Ray colours (no decoder) or ray features (decoder) from attention. background [3] display colour.
        table [M, C]: point_table(features), when the caller computed it already.
        Returns dict(rgb [R, 3] or None, feature [R, C] or None). With the residual decoder the feature's first
        three channels are the decoder-free colour over the training background and the fourth the attention's
        coverage 1 − bg (the decoder's bases; frames over another background are recomposited by
        core/points/render.py like any decoder output)."""
        if table is None:
            table = self.point_table(features)
        if table is None:  # view-dependent values: one per neighbour slot
            v = self.point_values(dirs, idx, features)
            fv = (att["weights"][..., None] * v).sum(1)
        else:  # Σ_j w_ij v[idx_ij] without the [R, K, C] gather (empty slots carry weight 0)
            fv = F.embedding_bag(idx.clamp_min(0), table, per_sample_weights=att["weights"].to(table.dtype),
                                 mode="sum")
        bg = att["bg"][:, None]
        if self.decoder is None:
            rgb = fv + bg * background
            return {"rgb": rgb, "feature": None}
        if self.cfg.decoder_residual:
            white = torch.as_tensor(TRAIN_BACKGROUND, dtype=fv.dtype, device=fv.device)
            base = fv[:, :3] + bg * white
            return {"rgb": None, "feature": torch.cat([base, 1.0 - bg, fv[:, 3:] + bg * self.bg_value], dim=1)}
        return {"rgb": None, "feature": fv + bg * self.bg_value}

    def decode(self, feature_image: torch.Tensor) -> torch.Tensor:
        """feature_image [B, C, H, W] -> rgb [B, 3, H, W] (UNet decoder only)."""
        return self.decode_with_alpha(feature_image)[0]

    def decode_with_alpha(self, feature_image: torch.Tensor, workers: int = 1
                          ) -> tuple[torch.Tensor, torch.Tensor | None]:
        """feature_image [B, C, H, W] -> (rgb [B, 3, H, W], alpha [B, H, W] or None without the mask head).
        The residual decoder's rgb is not clamped (training keeps its gradient everywhere): clamp to show it.
        workers > 1 (with gradients, on the CPU): the batch is shared out to that many worker threads, forward and
        backward (core/util/workers.py `split_batch`; the same numbers to float rounding)."""
        y = self.decoder(feature_image) if workers <= 1 else split_batch(self.decoder, feature_image, workers)
        rgb = y[:, :3] if self.cfg.decoder_residual else torch.sigmoid(y[:, :3])
        return rgb, (torch.sigmoid(y[:, 3]) if y.shape[1] > 3 else None)

    def reset_decoder_correction(self) -> None:
        """Residual decoder only: zero its last layers, so the decoder render is the decoder-free render again
        (the collapse guard's recovery, core/points/train.py)."""
        self.decoder.reset_correction()

    # ---- (de)serialisation helpers ---------------------------------------------------------------------------
    def config_dict(self) -> dict:
        return dataclasses.asdict(self.cfg)


def mean_spacing(xyz: torch.Tensor, sample: int = 2048) -> float:
    """Median distance from a point to its nearest other point (on a random subset), xyz [N, 3]."""
    n = xyz.shape[0]
    if n < 2:
        return 1.0
    g = torch.Generator().manual_seed(0)
    sel = torch.randperm(n, generator=g)[: min(sample, n)].to(xyz.device)
    d = torch.cdist(xyz[sel].float(), xyz.float())
    d[torch.arange(len(sel)), sel] = float("inf")
    nn_d = d.min(dim=1).values
    nn_d = nn_d[torch.isfinite(nn_d)]
    med = float(nn_d.median()) if nn_d.numel() else 1.0
    return med if math.isfinite(med) and med > 0 else 1.0
