"""Run in a fresh bpy subprocess by test_addon_capture_camera.py; prints one JSON line "RESULTS: {...}".

argv after "--": zip model.pgt camera.json workdir
camera.json: {"c2w": 4x4, "intrinsics": [fx, fy, cx, cy], "width", "height"} — one view of a capture, as
core.images.dataset.load_cameras read it. The installed add-on's camera_settings / pixel_aspect set the scene
camera to it; the PointGT engine renders it (transparent film) into a float EXR, saved as <workdir>/engine.npy
(RGBA, scene-linear premultiplied, rows top-down).
"""
import importlib
import json
import os
import sys

import numpy as np

import bpy  # noqa: E402
from script_common import install_addon, recorder  # noqa: E402

zip_path, model, camera_json, work = sys.argv[sys.argv.index("--") + 1:]
R = {}
PKG = "bl_ext.user_default.pointgt"
step = recorder(R)
CAM = json.loads(open(camera_json, encoding="utf-8").read())
W, H = int(CAM["width"]), int(CAM["height"])


def mod(name):
    return importlib.import_module(f"{PKG}.{name}")


@step("install")
def _():
    return install_addon(zip_path)


@step("scene")
def _():
    scene = bpy.context.scene
    for o in list(bpy.data.objects):
        bpy.data.objects.remove(o)
    data = bpy.data.cameras.new("capture")
    cam = bpy.data.objects.new("capture", data)
    scene.collection.objects.link(cam)
    scene.camera = cam
    r = scene.render
    r.engine = 'POINTGT'
    r.resolution_x, r.resolution_y, r.resolution_percentage = W, H, 100
    r.film_transparent = True
    r.dither_intensity = 0.0
    r.image_settings.file_format = 'OPEN_EXR'
    r.image_settings.color_mode = 'RGBA'
    r.image_settings.color_depth = '32'
    r.image_settings.exr_codec = 'NONE'
    scene.view_settings.view_transform = 'Standard'
    scene.view_settings.look = 'None'
    res = bpy.ops.pointgt.import_model(filepath=model, preview_resolution=W)
    return {"import": sorted(res), "engine": r.engine}


@step("camera")
def _():
    scene = bpy.context.scene
    cam_mod = mod("scene.camera")
    Intrinsics = mod("core.images.intrinsics").Intrinsics  # the add-on's vendored core
    k = Intrinsics(*CAM["intrinsics"])
    cam = scene.camera
    cam.matrix_world = __import__("mathutils").Matrix(CAM["c2w"])
    for name, value in cam_mod.camera_settings(k, W, H).items():
        setattr(cam.data, name, value)
    scene.render.pixel_aspect_x, scene.render.pixel_aspect_y = cam_mod.pixel_aspect(k)
    bpy.context.view_layer.update()
    c2w, got = cam_mod.scene_camera(scene, W, H)
    got = got.as_list() if isinstance(got, Intrinsics) else [got, got, W / 2, H / 2]
    return {"intrinsics": got, "c2w_err": float(np.abs(c2w - np.asarray(CAM["c2w"])).max()),
            "aspect": [scene.render.pixel_aspect_x, scene.render.pixel_aspect_y]}


@step("render")
def _():
    scene = bpy.context.scene
    path = os.path.join(work, "engine.exr")
    scene.render.filepath = path
    bpy.ops.render.render(write_still=True)
    last = dict(mod("render.render_engine").LAST)
    img = bpy.data.images.load(path)
    img.colorspace_settings.name = 'Linear Rec.709'
    px = np.empty(W * H * 4, np.float32)
    img.pixels.foreach_get(px)
    np.save(os.path.join(work, "engine.npy"), px.reshape(H, W, 4)[::-1])
    return {"error": last.get("error"), "warning": last.get("warning"), "size": list(img.size)}


print("RESULTS: " + json.dumps(R))
