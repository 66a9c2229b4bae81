"""Cycles (CPU) settings and the view-rendering loop (needs bpy)."""
from __future__ import annotations

import contextlib
import os
import sys
import time
from pathlib import Path

import bpy
import numpy as np
from mathutils import Matrix

# Cycles samples per pixel, lit or not: 64 keeps the test views' own Monte Carlo noise far below any model's error
# (object PSNR against a 1024-sample render of the same views: 37-54 dB over the scene library, where 16 samples
# gave 29-45 dB; `python -m tools.bench.gt_noise`, docs/results.md "Noise in the ground truth")
DEFAULT_SAMPLES = 64


def setup_cycles(scene, size: int, samples: int, lit: bool, filter_width: float | None = None) -> None:
    """Cycles on the CPU, no denoiser, transparent film, Standard view (PNG = sRGB encoding of linear), 8-bit
    RGBA PNGs, no dithering (so a constant emission colour gives one exact pixel value)."""
    scene.render.engine = "CYCLES"
    cyc = scene.cycles
    cyc.device = "CPU"
    cyc.samples = int(samples)
    cyc.use_adaptive_sampling = False
    cyc.use_denoising = False
    cyc.seed = 0
    if filter_width is not None:
        cyc.filter_width = float(filter_width)  # tiny width: each sample goes through the pixel centre
    if lit:
        cyc.max_bounces, cyc.diffuse_bounces, cyc.glossy_bounces = 3, 2, 1
    else:
        cyc.max_bounces = 0  # emission seen directly; bounces would only cost time
    r = scene.render
    r.film_transparent = True
    r.resolution_x = r.resolution_y = int(size)
    r.resolution_percentage = 100
    r.dither_intensity = 0.0
    r.use_persistent_data = True
    r.image_settings.file_format = "PNG"
    r.image_settings.color_mode = "RGBA"
    r.image_settings.color_depth = "8"
    scene.display_settings.display_device = "sRGB"
    scene.view_settings.view_transform = "Standard"
    scene.view_settings.look = "None"
    scene.view_settings.exposure = 0.0
    scene.view_settings.gamma = 1.0


def add_lights(scene) -> None:
    """The lit variant: a sun from above-front plus a dim grey world (still a transparent film)."""
    sun = bpy.data.lights.new("sun", "SUN")
    sun.energy = 3.0
    obj = bpy.data.objects.new("sun", sun)
    obj.rotation_euler = (0.8, 0.2, 0.6)
    scene.collection.objects.link(obj)
    world = bpy.data.worlds.new("world")
    world.use_nodes = True
    bg = world.node_tree.nodes.get("Background")
    bg.inputs["Color"].default_value = (0.25, 0.25, 0.25, 1.0)
    scene.world = world


def add_camera(scene, camera_angle_x: float, name: str = "camera"):
    cam = bpy.data.cameras.new(name)
    cam.sensor_fit = "HORIZONTAL"
    cam.angle = float(camera_angle_x)
    cam.clip_start, cam.clip_end = 0.05, 100.0
    obj = bpy.data.objects.new(name, cam)
    scene.collection.objects.link(obj)
    scene.camera = obj
    return obj


@contextlib.contextmanager
def quiet_stdout():
    """Cycles prints a status line per tile on the C-level stdout; hide it so our progress stays readable."""
    sys.stdout.flush()
    saved = os.dup(1)
    devnull = os.open(os.devnull, os.O_WRONLY)
    try:
        os.dup2(devnull, 1)
        yield
    finally:
        os.dup2(saved, 1)
        os.close(saved)
        os.close(devnull)


def open_scene(scene_dir):
    """Opens a scene made by `pointgt make-scene` (its scene.blend, quietly) in place of Blender's current file.
    Returns (spec, obj): its checked scene.json and the scene's object (the true mesh, at rest)."""
    from tools.scenes.spec import load_scene_spec

    spec = load_scene_spec(scene_dir)
    with quiet_stdout():
        bpy.ops.wm.open_mainfile(filepath=str(Path(scene_dir) / "scene.blend"))
    return spec, bpy.data.objects[spec["object"]]


def world_vertices(obj, mesh=None) -> np.ndarray:
    """The vertices of `mesh` (default: the object's own mesh, at rest) in world space through the object's
    matrix -> [V, 3] float64."""
    me = obj.data if mesh is None else mesh
    co = np.empty(len(me.vertices) * 3, dtype=np.float32)
    me.vertices.foreach_get("co", co)
    mw = np.array(obj.matrix_world, dtype=np.float64)
    return co.reshape(-1, 3).astype(np.float64) @ mw[:3, :3].T + mw[:3, 3]


def render_views(scene, camera, c2ws: np.ndarray, out_dir: Path, split: str, log=print) -> list[dict]:
    """Render one PNG per camera-to-world matrix [V, 4, 4] into out_dir/split/r_<i>.png.

    Returns the NeRF-synthetic frame entries: file_path "./<split>/r_<i>" (no extension) + transform_matrix.
    """
    (out_dir / split).mkdir(parents=True, exist_ok=True)
    frames = []
    start = time.perf_counter()
    total = len(c2ws)
    for i, c2w in enumerate(c2ws):
        camera.matrix_world = Matrix(np.asarray(c2w).tolist())
        scene.render.filepath = str(out_dir / split / f"r_{i}.png")
        with quiet_stdout():
            bpy.ops.render.render(write_still=True)
        frames.append({"file_path": f"./{split}/r_{i}", "transform_matrix": np.asarray(c2w).tolist()})
        log(f"  {split}: {i + 1}/{total} views, {time.perf_counter() - start:.1f} s")
    return frames
