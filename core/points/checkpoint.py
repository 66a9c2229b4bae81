"""PointModel <-> plain arrays + JSON for the .pgt file (core/modelfile). No pickle anywhere.

Array names: "points/xyz" [N, 3], "points/features" [N, h], "points/influence" [N], "net/<state-dict key>" for
every other parameter or buffer. The model config goes to meta["model"].
"""
from __future__ import annotations

import numpy as np
import torch

from core.config import from_dict, to_dict
from core.points.model import ModelConfig, PointModel
from core.util.errors import ModelFileError

_POINT_ARRAYS = {"xyz": "points/xyz", "features": "points/features", "influence": "points/influence"}
# buffers files from before them lack: the model's default value stays
_OPTIONAL = {"train_footprint", "decoder_footprint", "interior_gain"}


def model_to_arrays(model: PointModel) -> tuple[dict[str, np.ndarray], dict]:
    arrays = {}
    for key, val in model.state_dict().items():
        name = _POINT_ARRAYS.get(key, f"net/{key}")
        arrays[name] = val.detach().cpu().numpy().astype(np.float32, copy=False) \
            if val.is_floating_point() else val.detach().cpu().numpy()
    return arrays, {"model": to_dict(model.cfg)}


def model_from_arrays(arrays: dict[str, np.ndarray], meta: dict, device="cpu", path: str = "model") -> PointModel:
    """Rebuild a PointModel; every array is checked against the shapes the config implies."""
    if "model" not in meta:
        raise ModelFileError(f"{path}: no 'model' section in the header; this file holds no point model")
    try:
        # files from before the decoder's mask head have a 3-channel UNet; from before the residual decoder, a
        # sigmoid UNet on the features alone
        cfg = from_dict(ModelConfig, {"decoder_alpha": False, "decoder_residual": False, **meta["model"]})
    except Exception as exc:  # InputError or TypeError from a damaged config
        raise ModelFileError(f"{path}: the model settings are invalid ({exc})") from exc
    for key, name in _POINT_ARRAYS.items():
        if name not in arrays:
            raise ModelFileError(f"{path}: missing array '{name}'")
    xyz = torch.from_numpy(np.ascontiguousarray(arrays["points/xyz"], dtype=np.float32))
    if xyz.ndim != 2 or xyz.shape[1] != 3 or xyz.shape[0] == 0:
        raise ModelFileError(f"{path}: 'points/xyz' must be [N, 3] with N > 0, got {tuple(xyz.shape)}")
    if not bool(torch.isfinite(xyz).all()):
        raise ModelFileError(f"{path}: 'points/xyz' holds NaN or infinite positions; the file is damaged")
    model = PointModel(cfg, xyz, spacing=1.0)
    state = model.state_dict()
    new_state = {}
    for key, ref in state.items():
        name = _POINT_ARRAYS.get(key, f"net/{key}")
        if name not in arrays:
            if key in _OPTIONAL:
                new_state[key] = ref
                continue
            raise ModelFileError(f"{path}: missing array '{name}'")
        arr = torch.from_numpy(np.array(arrays[name]))
        if tuple(arr.shape) != tuple(ref.shape):
            raise ModelFileError(f"{path}: array '{name}' has shape {tuple(arr.shape)}, expected {tuple(ref.shape)}"
                                 " for these model settings")
        if arr.is_floating_point() and not bool(torch.isfinite(arr).all()):  # even if the header allowed it
            raise ModelFileError(f"{path}: array '{name}' holds NaN or infinite values; the file is damaged")
        new_state[key] = arr.to(ref.dtype)
    model.load_state_dict(new_state)
    return model.to(device)
