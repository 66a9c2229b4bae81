"""One frame with the rest of the scene: Cycles or EEVEE render every other object, PointGT renders its models into
a layer with a depth pass, and the compositor merges the two per pixel by depth (Z Combine), so a box in front
hides the model and the model hides the floor behind it. The models' surface proxies stay in the scene as
shadow casters only (invisible to camera rays), so the model casts a shadow on the floor and scene lights act on
the rest.

`setup_composite` builds it once (the *Composite with Scene* operator); the render_pre handler
(handlers.on_render_pre) renders the PointGT layer of each frame into two images the compositor reads:
'PointGT layer' (straight scene-linear RGBA) and 'PointGT depth' (planar camera depth, as Cycles' Depth pass;
1e9 where no model is). So F12, Render Animation and `blender -b file.blend -a` all composite.
"""
from __future__ import annotations

import time

import bpy
import numpy as np

from core.util.errors import InputError

from ..scene import atlas_image
from ..scene.camera import render_size
from ..operators.reporting import reports_errors

LAYER = "PointGT layer"
DEPTH = "PointGT depth"
TREE = "PointGT Composite"
FAR = 1.0e9
LAST_LAYER: dict = {}  # the last layer rendered: its frame and progress fractions (read by tests)


def _image(name: str, width: int, height: int, data: bool):
    img = bpy.data.images.get(name)
    if img is None or tuple(img.size) != (width, height):
        if img is not None:
            bpy.data.images.remove(img)
        img = bpy.data.images.new(name, width=width, height=height, alpha=True, float_buffer=True)
    img.colorspace_settings.name = "Non-Color" if data else "Linear Rec.709"
    img.alpha_mode = 'STRAIGHT'
    return img


def layer_arrays(depsgraph, width: int, height: int, progress=None) -> tuple[np.ndarray, np.ndarray]:
    """The PointGT layer of a frame: straight scene-linear RGBA [H, W, 4] and planar depth [H, W] (FAR where no
    model), rows top-down. progress(fraction, text) after each model. Raises PointGTError."""
    from ..bridge import frame_renderer
    from ..scene import scene_inputs
    from ..scene.camera import scene_camera
    from .render_engine import render_objects

    scene = depsgraph.scene
    c2w, focal = scene_camera(scene, width, height, depsgraph)
    fwd = -np.asarray(c2w, dtype=np.float64)[:3, 2]
    layers, depth = [], np.full((height, width), FAR, dtype=np.float64)
    objs = render_objects(depsgraph)
    for i, obj in enumerate(objs):
        t0 = time.perf_counter()
        scene_inputs.check_device(obj)
        inputs = scene_inputs.object_inputs(obj, depsgraph)
        state = frame_renderer.prepare(inputs)
        layer = frame_renderer.render_layer(state, c2w, height, width, focal, k=inputs.k)
        tr = layer["result"]["trace"]
        z = ((tr.x - tr.origins).cpu().numpy().astype(np.float64) @ fwd).reshape(height, width)
        covered = np.isfinite(layer["depth"]) & np.isfinite(z) & (layer["alpha"] > 0.02)
        depth = np.where(covered, np.minimum(depth, z), depth)
        layers.append(layer)
        if progress is not None:
            progress((i + 1) / len(objs), f"{obj.name} ({i + 1}/{len(objs)}) in {time.perf_counter() - t0:.2f} s")
    rgba = np.zeros((height, width, 4), dtype=np.float32)
    if layers:
        rgb, alpha = frame_renderer.composite(layers, transparent=True)
        rgba[..., :3] = atlas_image.srgb_to_linear(rgb)
        rgba[..., 3] = alpha
    return rgba, depth.astype(np.float32)


def update_layer(scene, depsgraph=None) -> int:
    """Render the PointGT layer of the scene's current frame into the compositor's images. Returns the number of
    covered pixels."""
    r = scene.render
    width, height = render_size(r.resolution_x, r.resolution_y, r.resolution_percentage)
    depsgraph = depsgraph or bpy.context.evaluated_depsgraph_get()
    frame = scene.frame_current
    LAST_LAYER.clear()
    LAST_LAYER.update(frame=frame, progress=[])

    def progress(fraction, text):
        # render_pre runs before the other engine starts (in its render thread, where Blender's progress bar
        # belongs to that engine): the console gets the progress, which is what `blender -b ... -a` shows
        LAST_LAYER["progress"].append(fraction)
        print(f"PointGT layer, frame {frame}: {text} ({fraction:.0%})", flush=True)

    rgba, depth = layer_arrays(depsgraph, width, height, progress=progress)
    img = _image(LAYER, width, height, data=False)
    img.pixels.foreach_set(np.ascontiguousarray(rgba[::-1]).reshape(-1))
    img.update()
    d = np.ones((height, width, 4), dtype=np.float32)
    d[..., :3] = depth[..., None]
    dimg = _image(DEPTH, width, height, data=True)
    dimg.pixels.foreach_set(np.ascontiguousarray(d[::-1]).reshape(-1))
    dimg.update()
    return int((rgba[..., 3] > 0.5).sum())


def clear_layer(scene) -> None:
    """Empty the layer images (no model anywhere): a frame whose PointGT layer failed shows no stale model."""
    for name, value in ((LAYER, 0.0), (DEPTH, FAR)):
        img = bpy.data.images.get(name)
        if img is not None:
            buf = np.full(img.size[0] * img.size[1] * 4, value, dtype=np.float32)
            if name == DEPTH:
                buf[3::4] = 1.0
            img.pixels.foreach_set(buf)
            img.update()


def setup_composite(context) -> list[str]:
    """Set the scene up (see the module doc). Returns what was done, one line each."""
    scene = context.scene
    done = []
    if scene.render.engine == 'POINTGT':
        scene.render.engine = 'CYCLES'
        done.append("render engine: Cycles (PointGT renders its models into a layer)")
    for vl in scene.view_layers:
        vl.use_pass_z = True
    models = [o for o in scene.objects if getattr(o, "pointgt", None) is not None and o.pointgt.is_model]
    if not models:
        raise InputError("no PointGT model in the scene; import one first")
    for obj in models:
        proxy = obj.pointgt.proxy
        if proxy is None:
            done.append(f"'{obj.name}' has no surface proxy: it casts no shadow (Add Surface Proxy)")
            continue
        proxy.visible_camera = False
        proxy.visible_shadow = True
        done.append(f"'{proxy.name}': shadow caster only")
    r = scene.render
    width, height = render_size(r.resolution_x, r.resolution_y, r.resolution_percentage)
    layer, depth = _image(LAYER, width, height, data=False), _image(DEPTH, width, height, data=True)
    tree = bpy.data.node_groups.get(TREE)
    if tree is None:
        tree = bpy.data.node_groups.new(TREE, 'CompositorNodeTree')
        tree.interface.new_socket("Image", in_out='OUTPUT', socket_type='NodeSocketColor')
    tree.nodes.clear()
    rl = tree.nodes.new('CompositorNodeRLayers')
    rl.scene = scene
    n_layer, n_depth = tree.nodes.new('CompositorNodeImage'), tree.nodes.new('CompositorNodeImage')
    n_layer.image, n_depth.image = layer, depth
    zc = tree.nodes.new('CompositorNodeZcombine')
    out = tree.nodes.new('NodeGroupOutput')
    rl.location, n_layer.location, n_depth.location = (-500, 200), (-500, -150), (-500, -400)
    out.location = (250, 0)
    tree.links.new(rl.outputs["Image"], zc.inputs[0])
    tree.links.new(rl.outputs["Depth"], zc.inputs[1])
    tree.links.new(n_layer.outputs["Image"], zc.inputs[2])
    tree.links.new(n_depth.outputs["Image"], zc.inputs[3])
    if "Use Alpha" in zc.inputs:
        zc.inputs["Use Alpha"].default_value = True
    tree.links.new(zc.outputs[0], out.inputs[0])
    scene.compositing_node_group = tree
    r.use_compositing = True
    scene.pointgt.composite = True
    done.append(f"compositor '{TREE}': the scene's render and the PointGT layer merged by depth")
    return done


class POINTGT_OT_setup_composite(bpy.types.Operator):
    """Render PointGT models together with the rest of the scene: Cycles/EEVEE render the other objects, the
    compositor merges the PointGT layer by depth, the surface proxies cast the shadows"""
    bl_idname = "pointgt.setup_composite"
    bl_label = "Composite with Scene"
    bl_options = {'REGISTER', 'UNDO'}

    @reports_errors("Setting up the compositing")
    def execute(self, context):
        done = setup_composite(context)
        self.report({'INFO'}, "; ".join(done))
        return {'FINISHED'}


CLASSES = (POINTGT_OT_setup_composite,)
