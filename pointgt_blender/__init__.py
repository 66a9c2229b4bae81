"""PointGT for Blender: import neural point-cloud models, pose them with Blender rigs, paint their atlas.

Registers without PyTorch: importing, rigging and exporting points need only Blender's numpy; features that
run the network check for torch in their poll(). When packaged (`pointgt package-addon`), `core` is vendored
as a subpackage of this add-on and its imports are made relative; see docs/addon.md.

Module layout (one job each): deps (torch detection, pip), preferences (status + install), properties
(per-object settings), model_import, atlas_image, rig (lattice, armature), reset, evaluated (deformed points +
checks), export, device_check, view3d_panel; session (the in-memory state, one clear()), handlers (every
Blender handler and the UI timer), preview (coarse-to-fine preview jobs, paint transfer operators),
render_engine (the "PointGT" engine), image_panel (Image Editor tab). Torch-only helpers, imported lazily:
frame_renderer (model/state caches, compositing), scene_inputs, paint_transfer, camera.
"""
from __future__ import annotations

import importlib

# Read only when installed as a legacy add-on (`pointgt package-addon --legacy`); as an extension Blender uses
# blender_manifest.toml instead. `pointgt package-addon` checks that both carry the same version.
bl_info = {
    "name": "PointGT",
    "author": "PointGT developers",
    "version": (0, 1, 0),
    "blender": (4, 2, 0),
    "location": "View3D > Sidebar > PointGT; File > Import > PointGT Model (.pgt)",
    "description": "Pose and paint neural point clouds reconstructed from photos",
    "category": "Render",
}

_MODULES = ("properties", "preferences", "model_import", "proxy", "rig", "reset", "export", "device_check", "view3d_panel",
            "preview", "render_engine", "composite", "image_panel")
_registered: list = []


def _modules():
    return [importlib.import_module(f"{__name__}.{name}") for name in _MODULES]


def register():
    import bpy  # only here, so `pointgt_blender.deps` and friends import without Blender in plain tests

    for mod in _modules():
        for cls in getattr(mod, "CLASSES", ()):
            bpy.utils.register_class(cls)
            _registered.append(cls)
    from . import handlers, model_import, preferences, properties, render_engine

    properties.register_properties()
    model_import.register_menus()
    preferences.update_sys_path()
    render_engine.register_engine_panels()
    handlers.register_handlers()


def unregister():
    import bpy

    from . import handlers, model_import, preferences, properties, render_engine

    handlers.unregister_handlers()
    render_engine.unregister_engine_panels()
    preferences.remove_sys_path()
    model_import.unregister_menus()
    properties.unregister_properties()
    for cls in reversed(_registered):
        bpy.utils.unregister_class(cls)
    _registered.clear()
