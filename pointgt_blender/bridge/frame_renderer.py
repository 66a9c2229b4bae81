"""Render PointGT objects into one frame: model loading (cached), edit states (cached on their inputs) and
depth-ordered compositing of several models. No bpy here: the Blender side (preview, render engine) gathers
`ObjectInputs` from the scene and hands them over, so this module is tested with plain arrays.

Imports torch at module level: only import it after checking `deps.torch_status()`.
"""
from __future__ import annotations

import dataclasses
import os
import threading
from dataclasses import dataclass

import numpy as np
import torch

from core.bundle import load_bundle
from core.frames.edited import EditConfig, EditState, frame_trace, render_edited
from core.points.trace import Trace
from core.util.errors import InputError, ModelFileError

CORRESPONDENCE = {'DEFORM_AWARE': "deform-aware", 'NAIVE': "naive", 'DEFORM_GRADIENT': "deform-gradient"}


@dataclass
class ObjectInputs:
    """What one PointGT object contributes to a frame. positions [M, 3] float32 world space, ids [M] int64,
    atlas [H, W, 3] float32 display space row 0 = top (None: the model's own)."""

    name: str
    model_path: str           # absolute
    device: str               # 'cpu' | 'cuda'
    k: int
    correspondence: str       # 'DEFORM_AWARE' | 'NAIVE' | 'DEFORM_GRADIENT'
    point_count: int
    positions: np.ndarray
    ids: np.ndarray
    atlas: np.ndarray | None = None
    antialias: int = 2        # painted texels per pixel side (EditConfig.antialias)
    rest_extent: float = 0.0  # bounding-box diagonal of the undeformed points in world space (pose warnings)
    occlusion: bool = True    # EditConfig.f_occlusion: each ray keeps the front layer where a pose folds the surface
    reshade: str = "OFF"      # EditConfig.reshade: 'OFF' | 'AUTO' | 'ON'


class ModelCache:
    """Loaded models by (path, device), reloaded when the file changes on disk (size or modification time)."""

    def __init__(self):
        self._items: dict = {}
        self._lock = threading.Lock()  # the warm-up thread (bridge/warmup.py) and the frame load models alike

    def get(self, path: str, device: str):
        with self._lock:
            return self._get(path, device)

    def _get(self, path: str, device: str):
        try:
            st = os.stat(path)
        except OSError:
            raise ModelFileError(f"{path}: model file not found; point the object's Model setting (PointGT sidebar)"
                                 f" to the .pgt file, or keep it next to the .blend") from None
        key = (os.path.normcase(os.path.abspath(path)), device)
        stamp = (st.st_size, st.st_mtime_ns)
        hit = self._items.get(key)
        if hit is not None and hit[0] == stamp:
            return hit[1]
        bundle = load_bundle(path, device=device)
        self._items[key] = (stamp, bundle)
        return bundle

    def clear(self):
        self._items.clear()


def _same(a, b) -> bool:
    if a is None or b is None:
        return a is b
    return a.shape == b.shape and a.dtype == b.dtype and np.array_equal(a, b)


class StateCache:
    """One EditState per object name, rebuilt only when its model, settings, positions, ids or atlas change
    (building one compares the atlas with the model's and moves the points to the device); a new pose of an
    unchanged atlas keeps the prepared painted textures (EditState's paint_from)."""

    def __init__(self):
        self._items: dict = {}

    def get(self, inputs: ObjectInputs, bundle, cfg: EditConfig) -> tuple[EditState, bool]:
        """(state, rebuilt)."""
        old = self._items.get(inputs.name)
        paint_from = None
        if old is not None:
            o_bundle, o_cfg, o_pos, o_ids, o_atlas, state = old
            same_atlas = o_bundle is bundle and _same(o_atlas, inputs.atlas)
            if same_atlas and o_cfg == cfg and _same(o_pos, inputs.positions) and _same(o_ids, inputs.ids):
                return state, False
            paint_from = state if same_atlas else None
        state = EditState(bundle, points=torch.from_numpy(np.ascontiguousarray(inputs.positions)),
                          ids=torch.from_numpy(np.ascontiguousarray(inputs.ids)), atlas=inputs.atlas, cfg=cfg,
                          paint_from=paint_from)
        # copies: the caller may reuse its buffers
        self._items[inputs.name] = (bundle, cfg, inputs.positions.copy(), inputs.ids.copy(),
                                    None if inputs.atlas is None else inputs.atlas.copy(), state)
        return state, True

    def forget(self, name: str):
        self._items.pop(name, None)

    def clear(self):
        self._items.clear()


MODELS = ModelCache()
STATES = StateCache()


def prepare(inputs: ObjectInputs, models: ModelCache = MODELS, states: StateCache = STATES):
    """The EditState for one object's inputs (model loaded and checked against the object). The object's K is
    not stored in the cached model (two objects of one model may use different K): pass `inputs.k` to
    `trace_layer` / `render_layer`."""
    bundle = models.get(inputs.model_path, inputs.device)
    n = bundle.model.num_points
    if inputs.point_count and inputs.point_count != n:
        raise ModelFileError(f"{inputs.model_path}: holds {n} points but object '{inputs.name}' was imported with "
                             f"{inputs.point_count}; the file was replaced by another model - re-import it")
    if inputs.atlas is not None and bundle.atlas is None:
        inputs = dataclasses.replace(inputs, atlas=None)  # a points-only model: nothing to paint yet
    cfg = EditConfig(correspondence=CORRESPONDENCE[inputs.correspondence], antialias=int(inputs.antialias),
                     f_occlusion=bool(inputs.occlusion), reshade=str(inputs.reshade).lower())
    state, _ = states.get(inputs, bundle, cfg)
    return state


def trace_layer(state: EditState, c2w: np.ndarray, height: int, width: int, focal: float,
                k: int | None = None) -> Trace:
    """Neighbours and attention of one model's frame, as `render_edited` traces it (core `frame_trace` with the
    state's points and the object's K; None: the model's own K): the expensive half of `render_layer`, so a
    preview can yield between the two. Returns the Trace (flat per-ray tensors, R = height * width)."""
    c2w_t = torch.as_tensor(np.asarray(c2w, dtype=np.float32))
    return frame_trace(state, c2w_t, height, width, focal, None if k is None else int(k))


def render_layer(state: EditState, c2w: np.ndarray, height: int, width: int, focal: float, k: int | None = None,
                 trace: Trace | None = None) -> dict:
    """One model over a black background: premultiplied display-space colour [H, W, 3], alpha [H, W], depth
    [H, W] along the ray (inf off the object) and the raw result of `render_edited`. k: neighbours per ray
    (None: the model's own); trace: from `trace_layer` with the same arguments (skips tracing)."""
    c2w_t = torch.as_tensor(np.asarray(c2w, dtype=np.float32))
    if trace is None:
        trace = trace_layer(state, c2w, height, width, focal, k)
    res = render_edited(state, c2w_t, height, width, focal, background=(0.0, 0.0, 0.0), trace=trace)
    tr = res["trace"]
    alpha = res["alpha"].clamp(0, 1)
    depth = tr.depth.reshape(height, width)
    depth = torch.where((alpha > 1e-4) & torch.isfinite(depth), depth, torch.full_like(depth, float("inf")))
    return {"premul": res["rgb"].cpu().numpy(), "alpha": alpha.cpu().numpy(), "depth": depth.cpu().numpy(),
            "result": res}


def composite(layers: list[dict], background=(1.0, 1.0, 1.0), transparent: bool = False) -> tuple[np.ndarray,
                                                                                                  np.ndarray]:
    """Depth-ordered 'over' of premultiplied layers, nearest first per pixel.
    Returns (rgb [H, W, 3] display space, alpha [H, W]); rgb is over `background` unless `transparent`, in which
    case it is the straight (un-premultiplied) colour."""
    if not layers:
        raise InputError("nothing to composite: no PointGT object is visible")
    prem = np.stack([l["premul"] for l in layers])            # [L, H, W, 3]
    alpha = np.stack([l["alpha"] for l in layers])            # [L, H, W]
    order = np.argsort(np.stack([l["depth"] for l in layers]), axis=0, kind="stable")
    prem = np.take_along_axis(prem, order[..., None], axis=0)
    alpha = np.take_along_axis(alpha, order, axis=0)
    acc = np.zeros(prem.shape[1:], dtype=np.float32)
    acc_a = np.zeros(alpha.shape[1:], dtype=np.float32)
    for p, a in zip(prem, alpha):  # a handful of layers, each a whole image
        acc += (1.0 - acc_a)[..., None] * p
        acc_a += (1.0 - acc_a) * a
    if transparent:
        rgb = np.where(acc_a[..., None] > 1e-6, acc / np.maximum(acc_a, 1e-6)[..., None], 0.0)
    else:
        rgb = acc + (1.0 - acc_a)[..., None] * np.asarray(background, dtype=np.float32)
    return np.clip(np.nan_to_num(rgb, nan=0.0), 0.0, 1.0).astype(np.float32), np.clip(acc_a, 0.0, 1.0)


@torch.no_grad()
def blank_warning(path: str, device: str = "cpu", size: int = 48, models: ModelCache = MODELS,
                  label: str = "") -> str:
    """'' when the model at `path` shows something, else a warning: it is rendered at size x size from six
    cameras around its points (bounding box in view, the model's own K) and counts as blank when no view has
    at least 1 % of its pixels covered (alpha > 0.5) or no pixel differs from the white it was trained over.
    label: the model's name in the message (default: the file name)."""
    from core.points.render import render_frame
    from core.images.cameras import look_at

    label = label or os.path.basename(path)
    bundle = models.get(path, device)
    xyz = bundle.model.xyz.detach()
    xyz = xyz[torch.isfinite(xyz).all(1)]
    if xyz.shape[0] == 0:
        return f"{label}: the model has no finite points, so it renders blank"
    lo, hi = xyz.min(0).values, xyz.max(0).values
    centre, radius = (lo + hi) / 2, float((hi - lo).norm()) / 2 + 1e-6
    focal = size / 2 / np.tan(np.radians(20.0))
    best_cover, best_content = 0.0, 0.0
    for axis in range(3):
        for sign in (1.0, -1.0):
            d = torch.zeros(3)
            d[axis] = sign
            up = (0.0, 1.0, 0.0) if axis == 2 else (0.0, 0.0, 1.0)
            eye = centre.cpu() + d * radius * 3.2
            c2w = look_at(eye.tolist(), centre.cpu().tolist(), up)
            res = render_frame(bundle.model, c2w, size, size, float(focal), background=(1.0, 1.0, 1.0))
            best_cover = max(best_cover, float((res["alpha"] > 0.5).float().mean()))
            best_content = max(best_content, float((1.0 - res["rgb"]).abs().max()))
    if best_cover < 0.01 or best_content < 0.02:
        return (f"{label} renders blank: seen from six sides it covers {best_cover:.1%} of the "
                f"view at most; the model may not be trained (refit it), or it was saved from a failed run")
    return ""
