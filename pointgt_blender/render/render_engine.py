"""The "PointGT" render engine: F12 and Render Animation render every visible PointGT model from the scene
camera, honouring resolution (and its percentage), frame range, film transparency and the output settings
(Blender writes the frames itself). Progress goes to update_progress and the stage (model, loading / tracing /
shading) to update_stats, after each stage of each model; test_break cancels between stages.

Colours: the model renders display-space (sRGB-encoded) colour; the Combined pass is scene-linear, so the
engine writes the linear equivalent, and Blender's Standard view transform turns it back into exactly the
model's colours (other view transforms are allowed but reported). Any problem (no camera, missing model, NaN
positions, torch missing) stops the render with an error report, so no frame file is overwritten with a
broken picture.
"""
from __future__ import annotations

import bpy
import numpy as np

from core.util.errors import InputError, PointGTError

from ..scene import atlas_image
from ..bridge import checks, deps
from ..ui.properties import is_pointgt_object

LAST: dict = {}  # the last render's warnings / error / stats (read by tests and the panel)


def render_objects(depsgraph) -> list:
    """(original object) of every PointGT model the render depsgraph shows."""
    out = []
    for ob in depsgraph.objects:
        orig = ob.original
        if is_pointgt_object(orig) and not orig.hide_render:
            out.append(orig)
    return sorted(out, key=lambda o: o.name)


# how far one model's frame is after each stage (the model loaded, the rays traced, the frame shaded)
STAGES = (("loading the model", 0.0), ("tracing", 0.15), ("shading", 0.65))


def render_pixels(depsgraph, width: int, height: int, progress=None, cancelled=None,
                  stage=None) -> np.ndarray | None:
    """RGBA float32 [H*W*4] scene-linear, rows bottom-up (Blender's pass layout) of one frame, or None when
    cancelled. progress(fraction in [0, 1]) after each stage of each model (LAST["progress"] keeps the
    fractions); stage(text) says which model and stage runs. Raises PointGTError."""
    from ..bridge import frame_renderer
    from ..scene import scene_inputs
    from ..scene.camera import scene_camera

    scene = depsgraph.scene
    objs = render_objects(depsgraph)
    if not objs:
        raise InputError(f"scene '{scene.name}' shows no PointGT model to render; import one (File > Import > "
                         f"PointGT Model) or enable its render visibility")
    c2w, focal = scene_camera(scene, width, height, depsgraph)
    layers, warnings = [], []
    LAST["progress"] = []

    def report(i, k):
        text, done = STAGES[k] if k < len(STAGES) else ("done", 1.0)
        frac = (i + done) / len(objs)
        LAST["progress"].append(frac)
        if progress is not None:
            progress(frac)
        if stage is not None and k < len(STAGES):
            stage(f"{objs[i].name} ({i + 1}/{len(objs)}): {text}")

    for i, obj in enumerate(objs):
        if cancelled is not None and cancelled():
            return None
        report(i, 0)
        scene_inputs.check_device(obj)
        inputs = scene_inputs.object_inputs(obj, depsgraph)
        warning = checks.pose_warning(obj.name, inputs.positions, inputs.rest_extent, c2w, focal, width, height)
        if warning:
            warnings.append(warning)
        state = frame_renderer.prepare(inputs)
        report(i, 1)
        trace = frame_renderer.trace_layer(state, c2w, height, width, focal, k=inputs.k)
        if cancelled is not None and cancelled():
            return None
        report(i, 2)
        layers.append(frame_renderer.render_layer(state, c2w, height, width, focal, k=inputs.k, trace=trace))
        report(i, 3)
    transparent = bool(scene.render.film_transparent)
    rgb, alpha = frame_renderer.composite(layers, background=tuple(scene.pointgt.background), transparent=transparent)
    rgba = np.empty((height, width, 4), dtype=np.float32)
    rgba[..., :3] = atlas_image.srgb_to_linear(rgb)
    if transparent:
        rgba[..., :3] *= alpha[..., None]  # Blender's passes hold premultiplied colour
        rgba[..., 3] = alpha
    else:
        rgba[..., 3] = 1.0
    LAST["stats"] = [l["result"]["stats"] for l in layers]
    if warnings:
        LAST["pose_warnings"] = warnings
    return np.ascontiguousarray(rgba[::-1]).reshape(-1)


class PointGTRenderEngine(bpy.types.RenderEngine):
    bl_idname = "POINTGT"
    bl_label = "PointGT"
    bl_use_preview = False

    def render(self, depsgraph):
        LAST.clear()
        scene = depsgraph.scene
        width, height = int(self.resolution_x), int(self.resolution_y)
        try:
            st = deps.torch_status()
            if not st.available:
                raise InputError(st.message)
            from ..scene import scene_inputs

            if scene.pointgt.composite and scene.render.use_compositing:
                raise InputError("Composite with Scene is set up: render with Cycles or EEVEE (they render the "
                                 "scene and PointGT adds its layer), or switch the scene's Compositing off")
            warning = scene_inputs.view_transform_warning(scene)
            if warning:
                LAST["warning"] = warning
                self.report({'WARNING'}, f"PointGT: {warning}")
            frame = scene.frame_current
            self.update_stats("PointGT", f"Frame {frame}: rendering")
            pixels = render_pixels(depsgraph, width, height, progress=self.update_progress,
                                   cancelled=self.test_break,
                                   stage=lambda text: self.update_stats("PointGT", f"Frame {frame}: {text}"))
            for text in LAST.get("pose_warnings", ()):
                LAST["warning"] = text
                self.report({'WARNING'}, f"PointGT: {text}")
        except PointGTError as exc:
            self._fail(str(exc))
            return
        except Exception as exc:  # never let a render take Blender down
            self._fail(f"PointGT render failed: {type(exc).__name__}: {exc}")
            return
        if pixels is None or self.test_break():
            return
        result = self.begin_result(0, 0, width, height)
        result.layers[0].passes["Combined"].rect.foreach_set(pixels)
        self.end_result(result)

    def _fail(self, message: str):
        # An ERROR report stops the render job (Render Animation stops too), so no frame file is overwritten.
        LAST["error"] = message
        self.report({'ERROR'}, f"PointGT: {message}")


def _panel_compat():
    """Built-in panels that make sense for this engine (output, dimensions, colour management, film)."""
    names = ("RENDER_PT_color_management", "RENDER_PT_color_management_curves", "RENDER_PT_format",
             "RENDER_PT_frame_range", "RENDER_PT_output", "RENDER_PT_film")
    return [getattr(bpy.types, n) for n in names if hasattr(bpy.types, n)]


class POINTGT_PT_render(bpy.types.Panel):
    bl_label = "PointGT"
    bl_space_type = 'PROPERTIES'
    bl_region_type = 'WINDOW'
    bl_context = "render"
    COMPAT_ENGINES = {"POINTGT"}

    @classmethod
    def poll(cls, context):
        return context.engine in cls.COMPAT_ENGINES

    def draw(self, context):
        layout = self.layout
        s = context.scene.pointgt
        layout.prop(s, "background")
        layout.prop(context.scene.render, "film_transparent")
        layout.prop(s, "live_preview")
        if LAST.get("error"):
            layout.label(text=LAST["error"], icon='ERROR')
        elif LAST.get("warning"):
            layout.label(text=LAST["warning"], icon='INFO')


CLASSES = (PointGTRenderEngine, POINTGT_PT_render)


def register_engine_panels():
    for panel in _panel_compat():
        if hasattr(panel, "COMPAT_ENGINES"):
            panel.COMPAT_ENGINES.add("POINTGT")


def unregister_engine_panels():
    for panel in _panel_compat():
        if hasattr(panel, "COMPAT_ENGINES"):
            panel.COMPAT_ENGINES.discard("POINTGT")
