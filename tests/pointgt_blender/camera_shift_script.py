"""Run with the Python that has bpy: `python camera_shift_script.py -- REPO`. Projects points through the add-on's
camera (pointgt_blender/scene/camera.py -> core Intrinsics -> core.images.cameras.project_points) and through Blender's
own `world_to_camera_view` for shifted lenses, sensor fits and non-square renders; prints RESULTS: <json>."""
import json
import sys

repo = sys.argv[sys.argv.index("--") + 1]
sys.path.insert(0, repo)

import bpy  # noqa: E402
import numpy as np  # noqa: E402
import torch  # noqa: E402
from bpy_extras.object_utils import world_to_camera_view  # noqa: E402
from mathutils import Vector  # noqa: E402

from core.images.cameras import project_points  # noqa: E402
from pointgt_blender.scene.camera import scene_camera  # noqa: E402

bpy.ops.wm.read_factory_settings(use_empty=True)
scene = bpy.context.scene
data = bpy.data.cameras.new("cam")
cam = bpy.data.objects.new("cam", data)
scene.collection.objects.link(cam)
scene.camera = cam
cam.location = (3.0, -2.0, 1.5)
cam.rotation_euler = (1.1, 0.1, 0.9)
cases = [(64, 48, 'AUTO', 0.1, -0.05, 1.0, 1.0), (48, 64, 'AUTO', -0.2, 0.15, 1.0, 1.0),
         (80, 40, 'VERTICAL', 0.05, 0.1, 1.0, 1.0), (40, 80, 'HORIZONTAL', 0.3, 0.0, 1.0, 1.0),
         (50, 50, 'AUTO', 0.0, 0.0, 1.0, 1.0), (64, 48, 'AUTO', 0.1, 0.05, 1.0, 1.5),  # AUTO turns vertical
         (40, 60, 'VERTICAL', -0.1, 0.2, 2.0, 1.0)]
out = []
for w, h, fit, sx, sy, ax, ay in cases:
    scene.render.resolution_x, scene.render.resolution_y = w, h
    scene.render.pixel_aspect_x, scene.render.pixel_aspect_y = ax, ay
    data.sensor_fit, data.shift_x, data.shift_y, data.lens = fit, sx, sy, 35.0
    bpy.context.view_layer.update()
    c2w, focal = scene_camera(scene, w, h)
    pts = np.random.default_rng(0).uniform(-1, 1, size=(50, 3))
    px, _ = project_points(torch.tensor(pts), torch.tensor(c2w, dtype=torch.float64), h, w, focal)
    err = 0.0
    for p, q in zip(pts, px.numpy()):
        v = world_to_camera_view(scene, cam, Vector(p))  # x right, y up, both 0..1 over the frame
        err = max(err, abs(v.x * w - q[0]), abs((1.0 - v.y) * h - q[1]))
    out.append({"case": [w, h, fit, sx, sy, ax, ay], "max_px_err": err, "kind": type(focal).__name__})
# a dataset camera (off-centre principal point) -> Blender settings -> the add-on's camera: the same intrinsics
from core.images.cameras import Intrinsics  # noqa: E402
from pointgt_blender.scene.camera import camera_settings, pixel_aspect  # noqa: E402

for w, h, k in [(64, 48, Intrinsics(70.0, 70.0, 29.5, 26.0)), (40, 72, Intrinsics(55.0, 55.0, 21.0, 33.5)),
                (48, 40, Intrinsics(52.0, 60.0, 21.0, 23.5))]:
    scene.render.resolution_x, scene.render.resolution_y = w, h
    scene.render.pixel_aspect_x, scene.render.pixel_aspect_y = pixel_aspect(k)
    for name, value in camera_settings(k, w, h).items():
        setattr(data, name, value)
    bpy.context.view_layer.update()
    _, got = scene_camera(scene, w, h)
    pts = np.random.default_rng(1).uniform(-1, 1, size=(30, 3))
    px, _ = project_points(torch.tensor(pts), torch.tensor(scene_camera(scene, w, h)[0], dtype=torch.float64),
                           h, w, k)
    err = max(max(abs(v.x * w - q[0]), abs((1.0 - v.y) * h - q[1]))
              for v, q in ((world_to_camera_view(scene, cam, Vector(p)), q) for p, q in zip(pts, px.numpy())))
    out.append({"case": [w, h, "dataset", *k.as_list()], "max_px_err": err, "kind": type(got).__name__,
                "intrinsics_err": max(abs(a - b) for a, b in zip(got.as_list(), k.as_list()))})
print("RESULTS: " + json.dumps(out))
