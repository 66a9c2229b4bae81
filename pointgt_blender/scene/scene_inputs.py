"""Read what a PointGT object contributes to a frame from Blender: deformed points + ids, the (painted) atlas,
the resolved model path and the object's settings. The atlas conversion (scene-linear Blender pixels ->
display-space atlas) is cached on the raw pixels, so an unpainted atlas costs one foreach_get per update."""
from __future__ import annotations

import os

import bpy
import numpy as np

from core.util.errors import InputError

from . import atlas_image
from .evaluated import evaluated_points, to_world


def model_file(obj) -> str:
    """The file to load the object's model from: the packed copy when the model is packed into the .blend, else
    the model path, absolute ('//' resolved against the .blend, or its library)."""
    s = obj.pointgt
    if s.packed_model is not None:
        from .model_pack import extracted_path

        return extracted_path(s.packed_model)
    if not s.model_path:
        raise InputError(f"object '{obj.name}': no model file set; choose the .pgt in the PointGT sidebar")
    return os.path.normpath(bpy.path.abspath(s.model_path, library=obj.library))


class AtlasReader:
    """Display-space atlas [H, W, 3] of a Blender image, converted again only when its pixels changed."""

    def __init__(self):
        self._items: dict = {}  # image name -> (raw pixels, converted atlas)

    def raw(self, image) -> np.ndarray:
        w, h = image.size
        if w == 0 or h == 0:
            raise InputError(f"image '{image.name}' has no pixels (missing file?); reload it or re-import the model")
        buf = np.empty(w * h * image.channels, dtype=np.float32)
        image.pixels.foreach_get(buf)
        return buf

    def read(self, image) -> np.ndarray:
        buf = self.raw(image)
        hit = self._items.get(image.name)
        if hit is not None and hit[0].shape == buf.shape and np.array_equal(hit[0], buf):
            return hit[1]
        atlas = atlas_image.read_atlas_image(image)
        self._items[image.name] = (buf, atlas)
        return atlas

    def clear(self):
        self._items.clear()


ATLASES = AtlasReader()


def object_inputs(obj, depsgraph):
    """frame_renderer.ObjectInputs of one PointGT object at the depsgraph's state (needs torch)."""
    from ..bridge.frame_renderer import ObjectInputs

    s = obj.pointgt
    positions, ids = evaluated_points(obj, depsgraph, 'WORLD')
    atlas = ATLASES.read(s.atlas) if s.atlas is not None else None
    return ObjectInputs(name=obj.name, model_path=model_file(obj), device=s.device.lower(), k=int(s.neighbors),
                        correspondence=s.correspondence, point_count=int(s.point_count), positions=positions,
                        ids=ids, atlas=atlas, antialias=int(s.antialias), rest_extent=rest_extent(obj),
                        occlusion=bool(s.occlusion), reshade=str(s.reshade))


def rest_extent(obj) -> float:
    """Bounding-box diagonal of the object's undeformed points in world space."""
    from ..bridge.checks import extent

    mesh = obj.data
    co = np.empty(len(mesh.vertices) * 3, dtype=np.float32)
    mesh.vertices.foreach_get("co", co)
    return extent(to_world(co.reshape(-1, 3), obj.matrix_world))


def check_device(obj) -> None:
    """InputError when the object's device cannot run here (CUDA without a CUDA build)."""
    from ..operators.device_check import device_problem

    problem = device_problem(obj.pointgt.device)
    if problem:
        raise InputError(f"object '{obj.name}': {problem}")


def view_transform_warning(scene) -> str:
    """'' when colours come out as the model's (Standard view, no look, exposure 0, gamma 1), else a hint."""
    v = scene.view_settings
    if v.view_transform == 'Standard' and v.look in ('None', '') and abs(v.exposure) < 1e-6 \
            and abs(v.gamma - 1.0) < 1e-6:
        return ""
    return (f"colour management uses view transform '{v.view_transform}' (look '{v.look}', exposure {v.exposure:g}, "
            f"gamma {v.gamma:g}); set Render > Color Management > View Transform to Standard, Look None, Exposure 0 "
            f"and Gamma 1 to get the model's colours")
