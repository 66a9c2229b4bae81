"""Run in a fresh bpy subprocess by test_addon_render.py; prints one JSON line "RESULTS: {...}".

argv after "--": zip model.pgt atlas_patch.npy workdir
Scene: the tiny card model (plane z = 0) seen from straight above, an armature bone over its right half that
turns about +Z over frames 1..3, the PointGT render engine at 64 x 48 px. Steps record what they saw (or the
error) so that one failure does not hide the others. torch is blocked until the "torch_missing" step is done.
"""
import importlib
import json
import math
import os
import shutil
import sys
import zipfile

import numpy as np


from script_common import block_torch, camera_only_scene, drop_ids_modifier, make_active, recorder

BLOCKER = block_torch()

import bpy  # noqa: E402

zip_path, model, patch_path, work = sys.argv[sys.argv.index("--") + 1:]
R = {}
PKG = "bl_ext.user_default.pointgt"
W, H = 64, 48
PATCH_CENTRE = np.array([0.45, 0.15, 0.0])
PATCH_RADIUS = 0.15


def mod(name):
    return importlib.import_module(f"{PKG}.{name}")


step = recorder(R)



def render_error(**kw):
    """Run a render that should fail: its error text ('' if it did not fail)."""
    try:
        bpy.ops.render.render(**kw)
    except RuntimeError as exc:
        return str(exc)
    return ""


def project(points, scene):
    """World points [N, 3] -> pixel (col, row) [N, 2] in the scene camera's W x H render."""
    c2w, focal = mod("scene.camera").scene_camera(scene, W, H)
    cam = (points - c2w[:3, 3]) @ c2w[:3, :3]
    return np.stack([focal * cam[:, 0] / -cam[:, 2] + W / 2, -focal * cam[:, 1] / -cam[:, 2] + H / 2], axis=1)


def obj():
    return bpy.data.objects["card"]


@step("install")
def _():
    res = bpy.ops.extensions.package_install_files(filepath=zip_path, repo="user_default", enable_on_install=True)
    bpy.ops.wm.save_userpref()  # a fresh Blender (the reload step) starts with the add-on enabled, as for artists
    return {"result": sorted(res), "torch_loaded": "torch" in sys.modules}


@step("scene")
def _():
    scene, cam = camera_only_scene()
    cam.scale = (2.0, 2.0, 2.0)  # scale must not change the view
    r = scene.render
    r.engine = 'POINTGT'
    r.resolution_x, r.resolution_y, r.resolution_percentage = 2 * W, 2 * H, 50
    r.dither_intensity = 0.0
    r.image_settings.file_format = 'PNG'
    r.image_settings.color_mode = 'RGB'
    scene.view_settings.view_transform = 'Standard'
    scene.view_settings.look = 'None'
    scene.frame_start, scene.frame_end = 1, 3
    res = bpy.ops.pointgt.import_model(filepath=model, preview_resolution=W)
    o = bpy.context.active_object
    o.name = "card"
    return {"import": sorted(res), "k": o.pointgt.neighbors, "engine": r.engine}


@step("torch_missing")
def _():
    prev = mod("operators.preview")
    done = prev.update_previews(bpy.context.scene)
    err = render_error(write_still=False)
    return {"status": prev.status(obj()), "done": done, "render_error": err, "torch_loaded": "torch" in sys.modules}


sys.meta_path.remove(BLOCKER)
importlib.import_module(PKG + ".bridge.deps").torch_status(refresh=True)


@step("rig")
def _():
    scene = bpy.context.scene
    bpy.ops.object.armature_add(location=(0.0, 0.0, 0.0))
    arm = bpy.context.active_object
    arm.name = "rig"
    bpy.ops.object.mode_set(mode='EDIT')
    eb = arm.data.edit_bones[0]
    eb.head, eb.tail, eb.roll = (0.05, 0.0, 0.0), (0.95, 0.0, 0.0), 0.0
    eb.head_radius = eb.tail_radius = 0.3
    eb.envelope_distance = 0.3
    bpy.ops.object.mode_set(mode='OBJECT')
    make_active(obj(), arm)
    bpy.ops.pointgt.bind_armature(mode='ENVELOPE')
    pb = arm.pose.bones[0]
    pb.rotation_mode = 'XYZ'
    for frame, angle in ((1, 0.0), (2, 14.0), (3, 28.0)):
        # the bone's local Z is world Z for a bone along +X with roll 0: the right half turns in the card's plane
        pb.rotation_euler = (0.0, 0.0, math.radians(angle))
        pb.keyframe_insert("rotation_euler", frame=frame)
    scene.frame_set(1)
    return {"modifiers": [m.type for m in obj().modifiers]}


def patch_ids():
    """Canonical points of the model within the painted disc (by pointgt_id)."""
    m = obj().data
    co = np.empty(len(m.vertices) * 3, np.float32)
    m.vertices.foreach_get("co", co)
    co = co.reshape(-1, 3)
    return np.nonzero(np.linalg.norm(co[:, :2] - PATCH_CENTRE[:2], axis=1) < 0.6 * PATCH_RADIUS)[0]


@step("paint_atlas")
def _():
    img = obj().pointgt.atlas
    atlas_image = mod("scene.atlas_image")
    atlas = atlas_image.read_atlas_image(img)
    mask = np.load(patch_path)
    atlas[mask] = (1.0, 0.0, 0.0)  # a red disc, written as pixels (strokes segfault in the module build)
    img.pixels.foreach_set(atlas_image.atlas_to_pixels(atlas))
    img.update()
    return {"texels": int(mask.sum()), "shape": list(atlas.shape)}


@step("animation")
def _():
    scene = bpy.context.scene
    scene.render.filepath = os.path.join(work, "anim", "f_")
    bpy.ops.render.render(animation=True)
    ids = patch_ids()
    expect = {}
    dg = bpy.context.evaluated_depsgraph_get()
    ev = mod("scene.evaluated")
    for f in (1, 2, 3):
        scene.frame_set(f)
        pos, pid = ev.evaluated_points(obj(), dg)
        centre = pos[np.isin(pid, ids)].mean(0)
        expect[f] = project(centre[None], scene)[0].tolist()
    scene.frame_set(1)
    files = sorted(os.listdir(os.path.join(work, "anim")))
    return {"files": files, "expect": expect, "n_ids": int(len(ids)), "last": mod("render.render_engine").LAST.get("stats")}


@step("live_preview")
def _():
    scene = bpy.context.scene
    prev = mod("operators.preview")
    fr = mod("bridge.frame_renderer")
    counts = {}
    scene.frame_set(2)  # frame_change_post asks for a preview; the idle timer's slices render it
    prev.run_pending()
    img = obj().pointgt.preview_image
    counts["after_frame"] = prev.COUNTS["rendered"]
    bpy.context.view_layer.update()  # the image write triggered an update: nothing to redo
    scene.frame_set(2)
    prev.run_pending()
    counts["same_frame"] = prev.COUNTS["rendered"]
    buf = np.empty(img.size[0] * img.size[1] * 4, np.float32)
    img.pixels.foreach_get(buf)
    frame2 = prev._RECORDS["card"].rendered.copy()
    scene.frame_set(3)
    prev.run_pending()
    counts["next_frame"] = prev.COUNTS["rendered"]
    moved = float(np.abs(prev._RECORDS["card"].rendered - frame2).max())
    # painting the atlas (pixels written, as a stroke would) re-renders on the next depsgraph update
    atlas = obj().pointgt.atlas
    raw = np.empty(atlas.size[0] * atlas.size[1] * 4, np.float32)
    atlas.pixels.foreach_get(raw)
    before_states = fr.STATES._items["card"][-1]
    raw2 = raw.copy()
    row = raw2[:4 * atlas.size[0]].reshape(-1, 4)
    row[:, :3] = 1.0 - row[:, :3]  # the bottom row's colours inverted: a change wherever the layout put its islands
    atlas.pixels.foreach_set(raw2)
    atlas.update()
    atlas.update_tag()  # as a paint stroke tags the image; the depsgraph handler asks for a new preview
    bpy.context.view_layer.update()
    prev.run_pending()
    counts["after_paint"] = prev.COUNTS["rendered"]
    rebuilt = fr.STATES._items["card"][-1] is not before_states
    atlas.pixels.foreach_set(raw)  # undo
    atlas.update()
    atlas.update_tag()
    bpy.context.view_layer.update()
    scene.frame_set(1)
    prev.run_pending()
    return {"size": list(img.size), "counts": counts, "moved": moved, "rebuilt": rebuilt,
            "status": prev.status(obj()), "image_name": img.name}


@step("paint_preview")
def _():
    scene = bpy.context.scene
    prev = mod("operators.preview")
    scene.frame_set(1)
    make_active(obj())
    bpy.ops.pointgt.refresh_preview()
    img = obj().pointgt.preview_image
    atlas_before = mod("scene.atlas_image").read_atlas_image(obj().pointgt.atlas)
    rec = prev._RECORDS["card"]
    rgb = rec.rendered.copy()
    r0, c0, size = 20, 16, 6  # a square on the card's left half (row 0 = top)
    rgb[r0:r0 + size, c0:c0 + size] = (0.1, 0.9, 0.1)
    img.pixels.foreach_set(mod("scene.atlas_image").atlas_to_pixels(rgb))
    img.update()
    res = bpy.ops.pointgt.transfer_paint()
    atlas_after = mod("scene.atlas_image").read_atlas_image(obj().pointgt.atlas)
    changed = np.linalg.norm(atlas_after - atlas_before, axis=-1) > 0.05
    # where is that square on the surface? the camera ray through its centre meets the card plane z = 0
    c2w, focal = mod("scene.camera").scene_camera(scene, W, H)
    px = np.array([c0 + size / 2, r0 + size / 2])
    d = c2w[:3, :3] @ np.array([(px[0] - W / 2) / focal, -(px[1] - H / 2) / focal, -1.0])
    o = c2w[:3, 3]
    point = o + d * (-o[2] / d[2])
    # the other camera: off to the side and tilted
    cam = scene.camera
    cam.location = (0.9, -1.2, 2.4)
    direction = -np.array(cam.location)
    cam.rotation_euler = __import__("mathutils").Vector(direction).to_track_quat('-Z', 'Y').to_euler()
    bpy.context.view_layer.update()
    scene.render.filepath = os.path.join(work, "other_view.png")
    bpy.ops.render.render(write_still=True)
    expect = project(point[None], scene)[0].tolist()
    green_pct = float(np.mean(np.all(np.abs(atlas_after[changed] - (0.1, 0.9, 0.1)) < 0.05, axis=-1))) \
        if changed.any() else 0.0
    # automatic transfer: paint again (blue-ish) and let the next depsgraph update find it
    cam.location, cam.rotation_euler = (0.0, 0.0, 3.0), (0.0, 0.0, 0.0)
    bpy.context.view_layer.update()
    bpy.ops.pointgt.refresh_preview()
    rgb = prev._RECORDS["card"].rendered.copy()
    rgb[24:28, 40:44] = (0.9, 0.9, 0.0)
    img.pixels.foreach_set(mod("scene.atlas_image").atlas_to_pixels(rgb))
    img.update()
    before_auto = mod("scene.atlas_image").read_atlas_image(obj().pointgt.atlas)
    prev.tick()  # one tick of the UI timer: it finds the paint (headless, timers never fire by themselves)
    prev.run_pending()  # and the slices that follow transfer it
    after_auto = mod("scene.atlas_image").read_atlas_image(obj().pointgt.atlas)
    auto_changed = int((np.linalg.norm(after_auto - before_auto, axis=-1) > 0.05).sum())
    # undo the yellow square so the rest of the script sees only the red and green patches
    obj().pointgt.atlas.pixels.foreach_set(mod("scene.atlas_image").atlas_to_pixels(before_auto))
    obj().pointgt.atlas.update()
    return {"result": sorted(res), "changed_texels": int(changed.sum()), "green_pct": green_pct,
            "point": point.tolist(), "expect": expect, "auto_changed": auto_changed, "status": prev.status(obj())}


@step("save_reload_prepare")
def _():
    scene = bpy.context.scene
    scene.frame_start, scene.frame_end = 2, 3
    scene.render.filepath = "//frames/f_"
    path = os.path.join(work, "posed.blend")
    bpy.ops.wm.save_as_mainfile(filepath=path)  # model path becomes relative to it
    bpy.ops.render.render(animation=True)
    shutil.move(os.path.join(work, "frames"), os.path.join(work, "before"))
    return {"model_path": obj().pointgt.model_path, "before": sorted(os.listdir(os.path.join(work, "before")))}


@step("errors")
def _():
    scene = bpy.context.scene
    prev = mod("operators.preview")
    out = {}
    o = obj()
    scene.render.filepath = os.path.join(work, "err", "f_")
    os.makedirs(os.path.join(work, "err"), exist_ok=True)
    keep = os.path.join(work, "err", "f_0002.png")
    with open(keep, "wb") as fh:
        fh.write(b"an earlier good frame")
    # NaN positions from the mesh itself
    co = np.empty(len(o.data.vertices) * 3, np.float32)
    o.data.vertices.foreach_get("co", co)
    bad = co.copy()
    bad[:3] = np.nan
    o.data.vertices.foreach_set("co", bad)
    o.data.update()
    scene.frame_set(2)  # the preview must swallow it into the status
    prev.run_pending()
    out["nan_status"] = prev.status(o)
    out["nan_render"] = render_error(animation=True)
    out["kept"] = open(keep, "rb").read() == b"an earlier good frame"
    o.data.vertices.foreach_set("co", co)
    o.data.update()
    # a modifier that changes the point count and drops the ids
    gn = drop_ids_modifier(o, 0.2)
    bpy.context.view_layer.update()
    prev.run_pending()
    out["count_status"] = prev.status(o)
    out["count_render"] = render_error(write_still=False)
    o.modifiers.remove(gn)
    # a missing model file, then one from a newer PointGT (the model path counts once the model is not packed)
    packed = o.pointgt.packed_model
    o.pointgt.packed_model = None
    good = o.pointgt.model_path
    o.pointgt.model_path = os.path.join(work, "gone.pgt")
    out["missing_render"] = render_error(write_still=False)
    newer = os.path.join(work, "newer.pgt")
    with zipfile.ZipFile(model) as zin, zipfile.ZipFile(newer, "w") as zout:
        for item in zin.infolist():
            data = zin.read(item.filename)
            if item.filename == "pointgt.json":
                header = json.loads(data)
                header["format_version"] += 1
                data = json.dumps(header).encode()
            zout.writestr(item, data)
    o.pointgt.model_path = newer
    out["newer_status"] = prev.update_previews(scene, force=True).get("card", "")
    out["newer_render"] = render_error(write_still=False)
    o.pointgt.model_path = good
    o.pointgt.packed_model = packed
    out["recovered"] = prev.update_previews(scene, force=True).get("card", "")
    out["kept_end"] = open(keep, "rb").read() == b"an earlier good frame"
    return out


@step("draw_ui")
def _():
    calls = []

    class Layout:
        def __getattr__(self, name):
            def call(*args, **kw):
                if name == "prop":
                    assert args[1] in args[0].bl_rna.properties, f"no property {args[1]!r}"
                    calls.append(args[1])
                elif name == "operator":
                    m, op = args[0].split(".")
                    getattr(getattr(bpy.ops, m), op).get_rna_type()
                    calls.append(args[0])
                elif name == "label":
                    calls.append("label:" + kw.get("text", ""))
                return Layout()
            return call

    make_active(obj())
    panel = mod("ui.image_panel").POINTGT_PT_image
    fake = type("Fake", (), {"layout": Layout(), "draw_body": panel.draw_body})()  # the panel's own methods
    panel.draw(fake, bpy.context)
    return {"calls": calls}


@step("open_atlas")
def _():
    window = bpy.context.window_manager.windows[0]
    area = window.screen.areas[0]
    area.type = 'IMAGE_EDITOR'
    make_active(obj())
    with bpy.context.temp_override(window=window, area=area, region=area.regions[-1]):
        res = bpy.ops.pointgt.open_atlas()
    space = area.spaces.active
    paint = bpy.context.scene.tool_settings.image_paint
    return {"result": sorted(res), "image": space.image.name, "ui_mode": space.ui_mode,
            "canvas": paint.canvas.name if paint.canvas else "", "mode": paint.mode}


print("RESULTS: " + json.dumps(R))
