"""What the headless Blender session scripts share (each runs as its own process with this folder on sys.path):
blocking torch as a Blender without PyTorch would, steps whose result or traceback is recorded for the test to
assert on, an empty scene with its camera above the card, and selecting objects. bpy is imported only inside the
functions, so a script can block torch before anything imports bpy."""
import sys
import traceback


class TorchBlocker:
    """Makes `import torch` fail as it would in a Blender without PyTorch."""

    def find_spec(self, name, path=None, target=None):
        if name == "torch" or name.startswith("torch."):
            raise ImportError(f"No module named '{name}' (blocked by the test)")
        return None


def block_torch() -> TorchBlocker:
    """Block torch from now on; `sys.meta_path.remove(blocker)` lifts it."""
    blocker = TorchBlocker()
    sys.meta_path.insert(0, blocker)
    return blocker


def recorder(results: dict, trace_chars: int = 2000):
    """A `@step(name)` decorator that runs the function at once and stores its result, or the error and the end
    of its traceback, in results[name]."""
    def step(name):
        def deco(fn):
            try:
                results[name] = fn()
            except Exception as exc:  # recorded, the test asserts on it
                results[name] = {"error": f"{type(exc).__name__}: {exc}",
                                 "trace": traceback.format_exc()[-trace_chars:]}
            return fn
        return deco
    return step


def camera_only_scene():
    """Every object but the cameras removed, the scene camera 3 units above the origin looking down −Z (at the
    card in the plane z = 0). Returns (scene, camera)."""
    import bpy

    scene = bpy.context.scene
    for o in list(bpy.data.objects):
        if o.type != 'CAMERA':
            bpy.data.objects.remove(o)
    cam = scene.camera
    cam.location = (0.0, 0.0, 3.0)
    cam.rotation_euler = (0.0, 0.0, 0.0)
    return scene, cam


def make_active(obj, *others):
    """Select obj and others, obj active."""
    import bpy

    for o in bpy.context.view_layer.objects:
        o.select_set(False)
    for o in (obj, *others):
        o.select_set(True)
    bpy.context.view_layer.objects.active = obj
