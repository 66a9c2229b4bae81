"""A trained PointGT model as one object: the point model (stage 1), the atlas (stage 2, optional) and metadata.

Saved as one `.pgt` file (core/modelfile): arrays "points/*", "net/*" from the point model, "atlas/*" from the
atlas; meta holds the configs, the scene description and the training summary.
"""
from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

from core.modelfile import load_pgt, save_pgt
from core.points.checkpoint import model_from_arrays, model_to_arrays
from core.points.model import PointModel
from core.util.device import resolve_device
from core.util.errors import ModelFileError


@dataclass
class Bundle:
    model: PointModel
    atlas: object | None = None            # core.atlas.atlas.Atlas once stage 2 ran
    meta: dict = field(default_factory=dict)

    @property
    def device(self):
        return self.model.xyz.device


def save_bundle(path: str | Path, bundle: Bundle, backup: bool = True) -> Path:
    arrays, meta = model_to_arrays(bundle.model)
    meta = {**bundle.meta, **meta}
    if bundle.atlas is not None:
        arrays.update(bundle.atlas.to_arrays())
        meta["atlas"] = bundle.atlas.meta()
    else:
        meta.pop("atlas", None)
    # The texel map marks "no surface" with NaN by design.
    allow = [n for n in arrays if n.startswith("atlas/texel")]
    return save_pgt(path, arrays, meta, backup=backup, allow_nonfinite=allow)


def load_bundle(path: str | Path, device="auto") -> Bundle:
    dev = resolve_device(device)
    arrays, meta = load_pgt(path)
    model = model_from_arrays(arrays, meta, device=dev, path=str(path))
    atlas = None
    if "atlas" in meta:
        from core.atlas.atlas import Atlas

        try:
            atlas = Atlas.from_arrays({k: v for k, v in arrays.items() if k.startswith("atlas/")}, meta["atlas"],
                                      device=dev)
        except ModelFileError as exc:
            raise ModelFileError(f"{path}: {exc}") from exc
        except Exception as exc:
            raise ModelFileError(f"{path}: the atlas section is damaged ({exc}); refit it with `pointgt atlas`") from exc
    model.eval()
    return Bundle(model=model, atlas=atlas, meta={k: v for k, v in meta.items() if k not in ("model", "atlas")})
