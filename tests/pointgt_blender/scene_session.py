"""Run in a fresh bpy subprocess by test_addon_scene.py; prints one JSON line "RESULTS: {...}".

argv after "--": zip model.pgt blank.pgt workdir
The tiny card model seen from above (64 x 48 px). Steps: duplicates (Shift+D, Alt+D) and moves must leave the
atlas bit-identical and give each object its own preview. Each step records what it saw (or the error).
"""
import importlib
import json
import os
import sys
import time
import traceback

import numpy as np
import bpy

zip_path, model, blank_model, work = sys.argv[sys.argv.index("--") + 1:]
R = {}
PKG = "bl_ext.user_default.pointgt"
W, H = 64, 48


def mod(name):
    return importlib.import_module(f"{PKG}.{name}")


def step(name):
    def deco(fn):
        try:
            R[name] = fn()
        except Exception as exc:
            R[name] = {"error": f"{type(exc).__name__}: {exc}", "trace": traceback.format_exc()[-2000:]}
        return fn
    return deco


def make_active(obj, *others):
    for o in bpy.context.view_layer.objects:
        o.select_set(False)
    for o in (obj, *others):
        o.select_set(True)
    bpy.context.view_layer.objects.active = obj


def raw(image):
    buf = np.empty(image.size[0] * image.size[1] * image.channels, np.float32)
    image.pixels.foreach_get(buf)
    return buf


def settle():
    """What the UI would do between events: the depsgraph update (handlers), then idle time for the preview."""
    bpy.context.view_layer.update()
    prev = mod("preview")
    if hasattr(prev, "run_pending"):
        prev.run_pending()


def obj():
    return bpy.data.objects["card"]


@step("install")
def _():
    res = bpy.ops.extensions.package_install_files(filepath=zip_path, repo="user_default", enable_on_install=True)
    return {"result": sorted(res)}


@step("scene")
def _():
    scene = bpy.context.scene
    for o in list(bpy.data.objects):
        if o.type != 'CAMERA':
            bpy.data.objects.remove(o)
    cam = scene.camera
    cam.location = (0.0, 0.0, 3.0)
    cam.rotation_euler = (0.0, 0.0, 0.0)
    r = scene.render
    r.resolution_x, r.resolution_y, r.resolution_percentage = W, H, 100
    res = bpy.ops.pointgt.import_model(filepath=model, preview_resolution=W)
    bpy.context.active_object.name = "card"
    mod("preview").update_previews(scene, force=True)
    settle()
    return {"import": sorted(res), "preview": obj().pointgt.preview_image.name}


@step("nonblocking")
def _():
    scene = bpy.context.scene
    prev = mod("preview")
    S = prev.S
    o = obj()
    o.pointgt.preview_resolution = 128  # levels 128x96 <- 64x48
    prev.run_pending()
    S.handler_ms.clear()
    c0 = dict(S.counts)
    # a batch of operator calls, as a script or an artist building a rig: no render until Blender is idle
    bpy.ops.object.armature_add(location=(0.0, 0.0, 0.0))
    arm = bpy.context.active_object
    bpy.ops.object.mode_set(mode='EDIT')
    for i in range(4):
        bpy.ops.armature.bone_primitive_add(name=f"b{i}")
    bpy.ops.object.mode_set(mode='OBJECT')
    make_active(o)
    for f in range(2, 7):
        scene.frame_set(f)
        o.location.y += 0.01
        bpy.context.view_layer.update()
    batch = {k: S.counts[k] - c0[k] for k in ("rendered", "levels", "requests")}
    handler_ms = list(S.handler_ms)
    # idle: slices render coarse-to-fine; the first level is shown before the full one
    slices, statuses, slice_ms = 0, [], []
    while True:
        t0 = time.perf_counter()
        more = prev.run_slice(budget=0.0)
        slice_ms.append((time.perf_counter() - t0) * 1000)
        statuses.append(prev.status(o))
        slices += 1
        if not more:
            break
    idle = {k: S.counts[k] - c0[k] for k in ("rendered", "levels", "jobs")}
    # a change while a job runs cancels it; the preview then shows the new state
    scene.frame_set(1)
    bpy.context.view_layer.update()
    o.location.y = 0.0
    bpy.context.view_layer.update()
    prev.run_slice(budget=0.0)
    prev.run_slice(budget=0.0)
    prev.run_slice(budget=0.0)
    cancelled0 = S.counts["cancelled"]
    o.location.x = 0.05
    bpy.context.view_layer.update()
    prev.run_pending()
    rendered_rgb = S.records["card"].rendered.copy()
    final_state_pos = float(S.records["card"].state.points[:, 0].mean())
    o.location.x = 0.0
    bpy.context.view_layer.update()
    prev.run_pending()
    bpy.data.objects.remove(arm)
    o.pointgt.preview_resolution = W
    prev.run_pending()
    return {"batch": batch, "handler_max_ms": max(handler_ms), "handler_calls": len(handler_ms), "idle": idle,
            "slices": slices, "refining_seen": any("refining" in t for t in statuses),
            "slice_max_ms": max(slice_ms), "cancelled": S.counts["cancelled"] - cancelled0,
            "mean_x_after_move": final_state_pos, "levels": prev.preview_levels(128, 96),
            "final_status": statuses[-1]}


@step("duplicates")
def _():
    scene = bpy.context.scene
    prev = mod("preview")
    atlas = obj().pointgt.atlas
    before = raw(atlas)
    rendered0 = prev.COUNTS["rendered"]
    make_active(obj())
    bpy.ops.object.duplicate(linked=False)       # Shift+D
    dup = bpy.context.active_object
    settle()
    make_active(obj())
    bpy.ops.object.duplicate(linked=True)        # Alt+D
    linked = bpy.context.active_object
    settle()
    for i, (o, dx) in enumerate(((dup, 0.3), (linked, -0.3), (dup, 0.2), (obj(), 0.1))):
        o.location.x += dx
        settle()
        scene.frame_set(scene.frame_current + 1)
        settle()
    after = raw(atlas)
    objs = [obj(), dup, linked]
    previews = [o.pointgt.preview_image.name if o.pointgt.preview_image else None for o in objs]
    owners = [o.pointgt.preview_image.get("pointgt_owner") if o.pointgt.preview_image else None for o in objs]
    shared = [o.name for o in prev.atlas_users(obj())]
    # Make Atlas Single-User: the duplicate gets its own bit-identical copy, the original's atlas is untouched
    make_active(dup)
    res = bpy.ops.pointgt.single_user_atlas()
    own = dup.pointgt.atlas
    return {"identical": bool(np.array_equal(before, after)), "max_diff": float(np.abs(before - after).max()),
            "previews": previews, "owners": owners, "names": [o.name for o in objs],
            "renders": prev.COUNTS["rendered"] - rendered0, "transfers": prev.COUNTS["transfers"], "shared": shared,
            "single_user": sorted(res), "own_atlas": own.name, "own_differs": own != atlas,
            "own_identical": bool(np.array_equal(raw(own), after)), "own_packed": own.packed_file is not None,
            "shared_after": [o.name for o in prev.atlas_users(obj())],
            "status": {o.name: prev.status(o) for o in objs}}


def render_still(path):
    scene = bpy.context.scene
    scene.render.engine = 'POINTGT'
    scene.render.filepath = path
    bpy.ops.render.render(write_still=True)
    return path


@step("warnings")
def _():
    scene = bpy.context.scene
    prev = mod("preview")
    out = {}
    # a model that renders blank warns on import
    bpy.ops.pointgt.import_model(filepath=blank_model, preview_resolution=W)
    blank = bpy.context.active_object
    out["blank_status"] = prev.status(blank)
    bpy.data.objects.remove(blank)
    out["good_status"] = prev.status(obj())
    # poses the render cannot show: collapsed, blown up, off-camera (preview status and F12 both say so)
    ng = bpy.data.node_groups.new("scale", 'GeometryNodeTree')
    ng.interface.new_socket("Geometry", in_out='INPUT', socket_type='NodeSocketGeometry')
    ng.interface.new_socket("Geometry", in_out='OUTPUT', socket_type='NodeSocketGeometry')
    gin, gout = ng.nodes.new('NodeGroupInput'), ng.nodes.new('NodeGroupOutput')
    tf = ng.nodes.new('GeometryNodeTransform')
    ng.links.new(gin.outputs[0], tf.inputs[0])
    ng.links.new(tf.outputs[0], gout.inputs[0])
    gn = obj().modifiers.new("scale", 'NODES')
    gn.node_group = ng
    for label, scale in (("collapsed", 1e-6), ("exploded", 1e6)):  # as a bone or lattice scaled by 1e-6 / 1e6
        tf.inputs["Scale"].default_value = (scale, scale, scale)
        settle()
        out[label] = prev.status(obj())
    obj().modifiers.remove(gn)
    obj().location.x = 100.0
    settle()
    out["off_camera"] = prev.status(obj())
    render_still(os.path.join(work, "off.png"))
    out["off_camera_render"] = mod("render_engine").LAST.get("warning", "")
    obj().location.x = 0.0
    settle()
    out["back"] = prev.status(obj())
    return out


@step("packed")
def _():
    out = {}
    o = obj()
    text = o.pointgt.packed_model
    out["packed"] = text is not None and isinstance(text.get("pointgt_model"), bytes)
    out["packed_size"] = len(text["pointgt_model"]) if out["packed"] else 0
    for other in [x for x in bpy.data.objects if x.name != "card" and x.type == 'MESH']:
        bpy.data.objects.remove(other)  # the duplicates of the earlier step
    render_still(os.path.join(work, "before.png"))
    blend = os.path.join(work, "scene.blend")
    bpy.ops.wm.save_as_mainfile(filepath=blend)
    moved = model + ".away"
    os.rename(model, moved)  # the .blend must render without its .pgt (a render farm)
    try:
        bpy.ops.wm.open_mainfile(filepath=blend)
        render_still(os.path.join(work, "after.png"))
        out["error_after"] = mod("render_engine").LAST.get("error", "")
    finally:
        os.rename(moved, model)
    # Unpack Model writes the packed bytes out and points the object at the file
    make_active(obj())
    res = bpy.ops.pointgt.unpack_model(filepath=os.path.join(work, "unpacked.pgt"))
    out["unpack"] = sorted(res)
    out["unpacked_same"] = open(os.path.join(work, "unpacked.pgt"), "rb").read() == open(model, "rb").read()
    out["after_unpack"] = {"packed": obj().pointgt.packed_model is not None, "path": obj().pointgt.model_path,
                           "texts": [t.name for t in bpy.data.texts]}
    res = bpy.ops.pointgt.pack_model()
    out["repack"] = sorted(res)
    return out


print("RESULTS: " + json.dumps(R))
