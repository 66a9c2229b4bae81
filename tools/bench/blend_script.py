"""The Blender side of `python -m tools.bench.frames --blend-cold`: run by path with the bpy module (Blender as a
Python module), never imported. Prints one JSON line "RESULTS: {...}".

    python tools/bench/blend_script.py -- setup ADDON.zip MODEL.pgt WORK SIZE
    python tools/bench/blend_script.py -- open SCENE.blend OUT.png [WAIT_S]
    python tools/bench/blend_script.py -- parts SCENE.blend OUT.png

setup: installs the packaged add-on (saved in the user preferences, so a fresh Blender starts with it enabled),
builds an artist's scene — the model imported with its surface proxy, a disc painted into its atlas through the
proxy's UVs, a two-bone armature on the proxy (Automatic Weights) with the right bone turned 30°, the camera on the
model, the PointGT engine at SIZE × SIZE — and saves it twice: WORK/path.blend (the model read from the .pgt next
to it) and WORK/packed.blend (the model packed into the .blend, the import's default). Then it renders F12 once,
which compiles the numba kernels into the installed add-on's cache as an artist's first render ever does.

open: what an artist's Blender does: starts (import bpy), reads the user preferences (enables the add-on),
opens the .blend (the add-on's load_post handler runs: bridge/warmup.py), presses F12 (WAIT_S seconds later,
default 0), turns the bone 5° more and presses F12 again. Each step is timed from inside; whether the background
warm-up started on load, and whether it had finished when the first frame was done, is recorded.

parts: the same first image with the warm-up switched off and CPU seconds per part (open, torch's import, the
renderer's imports, then F12's steps), so each part is measured on its own.
"""
import json
import math
import os
import sys
import time

T0 = time.perf_counter()
PKG = "bl_ext.user_default.pointgt"


def _engine_error() -> str:
    import importlib

    return importlib.import_module(f"{PKG}.render.render_engine").LAST.get("error", "")


def _render(path: str) -> float:
    """F12 into `path`; its wall seconds. Raises when the PointGT engine reported an error."""
    import bpy

    scene = bpy.context.scene
    scene.render.filepath = path
    t = time.perf_counter()
    bpy.ops.render.render(write_still=True)
    took = time.perf_counter() - t
    err = _engine_error()
    if err or not os.path.isfile(path):
        raise RuntimeError(f"the PointGT render failed: {err or 'no image written'}")
    return took


def _pose(angle_deg: float) -> None:
    import bpy

    arm = next(o for o in bpy.data.objects if o.type == 'ARMATURE')
    pb = arm.pose.bones["right"]
    pb.rotation_mode = 'XYZ'
    pb.rotation_euler = (0.0, 0.0, math.radians(angle_deg))
    bpy.context.view_layer.update()


def setup(zip_path: str, model: str, work: str, size: int) -> dict:
    import bpy
    import numpy as np
    from mathutils import Vector

    sys.path.insert(0, os.path.join(os.path.dirname(os.path.abspath(__file__)), "..", "..", "tests",
                                    "pointgt_blender"))
    from script_common import install_addon, make_active, paint_through_uvs, two_bone_rig

    out = {"install": install_addon(zip_path)}
    bpy.ops.wm.save_userpref()  # a fresh Blender starts with the add-on enabled, as an artist's does
    scene = bpy.context.scene
    for o in list(bpy.data.objects):
        if o.type != 'CAMERA':
            bpy.data.objects.remove(o)
    r = scene.render
    r.engine = 'POINTGT'
    r.resolution_x = r.resolution_y = size
    r.resolution_percentage = 100
    r.image_settings.file_format = 'PNG'
    scene.view_settings.view_transform = 'Standard'
    scene.pointgt.live_preview = False  # F12 only (headless, the preview's timers would never run anyway)
    res = bpy.ops.pointgt.import_model(filepath=model, pack_model=False, preview_resolution=size, check_blank=False)
    if res != {'FINISHED'}:
        raise RuntimeError(f"import of {model} failed: {sorted(res)}")
    obj = bpy.context.active_object
    proxy = obj.pointgt.proxy
    if proxy is None or obj.pointgt.atlas is None:
        raise RuntimeError(f"{model}: the scene needs the model's atlas and surface proxy, and the import made none "
                           f"(its warning above says why); use a trained model with an atlas")
    co = np.array([v.co for v in proxy.data.vertices], np.float64)
    lo, hi = co.min(0), co.max(0)
    centre, diag = (lo + hi) / 2, float(np.linalg.norm(hi - lo))
    target = centre + np.array([0.25 * (hi[0] - lo[0]), 0.0, 0.0])  # on the half the right bone turns
    spot = co[np.linalg.norm(co - target, axis=1).argmin()]
    out["painted_texels"], _ = paint_through_uvs(proxy, obj.pointgt.atlas, spot, 0.15 * diag, (1.0, 0.0, 0.0))
    _, out["parent"] = two_bone_rig(proxy)
    _pose(30.0)
    cam = scene.camera
    eye = Vector(centre) + Vector((0.0, -1.0, 0.6)).normalized() * 1.6 * diag
    cam.location = eye
    cam.rotation_euler = (Vector(centre) - eye).to_track_quat('-Z', 'Y').to_euler()
    make_active(obj)
    bpy.ops.wm.save_as_mainfile(filepath=os.path.join(work, "path.blend"))
    make_active(obj)
    if bpy.ops.pointgt.pack_model() != {'FINISHED'}:
        raise RuntimeError("packing the model into the .blend failed")
    bpy.ops.wm.save_as_mainfile(filepath=os.path.join(work, "packed.blend"))
    out["first_render_ever_s"] = _render(os.path.join(work, "setup.png"))
    out["points"] = len(obj.data.vertices)
    return out


def open_and_render(blend: str, png: str, wait: float = 0.0) -> dict:
    """Open `blend` as a fresh Blender does and press F12 (after `wait` seconds: an artist looking at the file),
    then again in a new pose. Wall seconds per step; CPU seconds (process_time: every thread of the process, so
    the warm-up's too) from opening to the first image and of the first F12."""
    import bpy

    t_bpy = time.perf_counter()
    bpy.ops.wm.read_userpref()  # the bpy module starts with factory preferences; Blender reads the saved ones
    t_prefs = time.perf_counter()
    if PKG not in bpy.context.preferences.addons:
        raise RuntimeError("the PointGT add-on is not enabled by the saved preferences; run the setup first")
    c_open = time.process_time()
    bpy.ops.wm.open_mainfile(filepath=blend)
    t_open = time.perf_counter()
    import importlib

    warmup = importlib.import_module(f"{PKG}.bridge.warmup")
    started = warmup._thread is not None
    handler_ms = max(importlib.import_module(f"{PKG}.scene.state").STATE.handler_ms, default=0.0)
    if wait > 0:
        time.sleep(wait)
    warm_before = started and not warmup._thread.is_alive()
    c_f12 = time.process_time()
    first = _render(png)
    c_image = time.process_time()
    warm_done = started and not warmup._thread.is_alive()
    _pose(35.0)
    second = _render(png[:-4] + "_2.png")
    warmup.wait()
    return {"import_bpy_s": t_bpy - T0, "prefs_s": t_prefs - t_bpy, "open_s": t_open - t_prefs,
            "first_frame_s": first, "first_frame_cpu_s": c_image - c_f12,
            "open_to_image_s": t_open - t_prefs + first, "open_to_image_cpu_s": c_image - c_open,
            "second_frame_s": second, "wait_s": wait,
            "warmup_started_on_load": started, "warmup_done_before_f12": warm_before,
            "warmup_done_by_first_image": warm_done,
            "warmup_error": warmup.last_error, "open_handlers_max_ms": handler_ms}


def parts(blend: str, png: str) -> dict:
    """Where the first image's time goes, CPU seconds per part, one after another in the main thread: the
    warm-up is switched off, torch and the renderer are imported first, then F12 with its steps timed."""
    import importlib

    import bpy

    bpy.ops.wm.read_userpref()
    importlib.import_module(f"{PKG}.bridge.warmup").start = lambda *args, **kwargs: False
    cpu = {}

    def timed(label, fn):
        def wrapper(*args, **kwargs):
            c = time.process_time()
            try:
                return fn(*args, **kwargs)
            finally:
                cpu[label] = cpu.get(label, 0.0) + time.process_time() - c
        return wrapper

    timed("open", bpy.ops.wm.open_mainfile)(filepath=blend)
    timed("import torch", importlib.import_module)("torch")
    fr = timed("renderer imports (numba included)", importlib.import_module)(f"{PKG}.bridge.frame_renderer")
    si = importlib.import_module(f"{PKG}.scene.scene_inputs")
    si.object_inputs = timed("object inputs (points, atlas, packed model extracted)", si.object_inputs)
    fr.MODELS.get = timed("model load", fr.MODELS.get)
    fr.prepare = timed("edit state (deformation gradients)", fr.prepare)  # its model load is subtracted below
    fr.trace_layer = timed("trace (neighbours, attention; numba's cache loaded)", fr.trace_layer)
    fr.render_layer = timed("shading (decoder, texture lookups)", fr.render_layer)
    c = time.process_time()
    _render(png)
    f12 = time.process_time() - c
    cpu["edit state (deformation gradients)"] -= cpu["model load"]
    cpu["rest of F12"] = f12 - sum(v for k, v in cpu.items() if k not in ("open", "import torch",
                                                                         "renderer imports (numba included)"))
    return {"parts_cpu_s": cpu}


def main() -> None:
    args = sys.argv[sys.argv.index("--") + 1:]
    if args[0] == "setup":
        res = setup(args[1], os.path.abspath(args[2]), os.path.abspath(args[3]), int(args[4]))
    elif args[0] == "open":
        wait = float(args[3]) if len(args) > 3 else 0.0
        res = open_and_render(os.path.abspath(args[1]), os.path.abspath(args[2]), wait)
    elif args[0] == "parts":
        res = parts(os.path.abspath(args[1]), os.path.abspath(args[2]))
    else:
        raise SystemExit(f"unknown mode {args[0]!r}: setup, open or parts")
    print("RESULTS: " + json.dumps(res))


if __name__ == "__main__":
    main()
