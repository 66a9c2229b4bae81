"""PointGT for Blender: import neural point-cloud models, pose them with Blender rigs, paint their atlas.

Registers without PyTorch: importing, rigging and exporting points need only Blender's numpy; features that
run the network check for torch in their poll(). When packaged (`pointgt package-addon`), `core` is vendored
as a subpackage of this add-on and its imports are made relative; see docs/addon.md.

Package layout (one job per module; tests/pointgt_blender/test_addon_layers.py checks the import rules):
- ui/: Blender classes the user sees: properties (per-object settings), preferences (status + install),
  view3d_panel, image_panel (Image Editor tab).
- operators/: the operators: model_import, proxy, rig, reset, export, device_check, preview (coarse-to-fine
  preview jobs, paint transfer operators), reporting (their error decorator). No module-level torch.
- render/: render_engine (the "PointGT" engine) and composite (Composite with Scene).
- bridge/: the torch side, no bpy: deps (torch detection, pip), frame_renderer (model/state caches,
  compositing), paint_transfer, checks.
- scene/: reads and writes Blender data: evaluated (deformed points), scene_inputs, camera, proxy_mesh,
  model_pack, atlas_image, state (everything kept in memory, one clear()), handlers (every Blender handler and the
  UI timer).
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

_MODULES = ("ui.properties", "ui.preferences", "operators.model_import", "operators.proxy", "operators.rig",
            "operators.reset", "operators.export", "operators.device_check", "ui.view3d_panel", "operators.preview",
            "render.render_engine", "render.composite", "ui.image_panel")
_registered: list = []


def _modules():
    return [importlib.import_module(f"{__name__}.{name}") for name in _MODULES]


def register():
    import bpy  # only here, so `pointgt_blender.deps` and friends import without Blender in plain tests

    for mod in _modules():
        for cls in getattr(mod, "CLASSES", ()):
            bpy.utils.register_class(cls)
            _registered.append(cls)
    from .scene import handlers
    from .operators import model_import
    from .ui import preferences, properties
    from .render import render_engine

    properties.register_properties()
    model_import.register_menus()
    preferences.update_sys_path()
    render_engine.register_engine_panels()
    handlers.register_handlers()


def unregister():
    import bpy

    from .scene import handlers
    from .operators import model_import
    from .ui import preferences, properties
    from .render import render_engine

    handlers.unregister_handlers()
    render_engine.unregister_engine_panels()
    preferences.remove_sys_path()
    model_import.unregister_menus()
    properties.unregister_properties()
    for cls in reversed(_registered):
        bpy.utils.unregister_class(cls)
    _registered.clear()
