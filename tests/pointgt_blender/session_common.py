"""What the headless Blender session scripts share (each runs as its own process with this folder on sys.path):
steps whose result or traceback is recorded for the test to assert on, and selecting objects."""
import traceback

import bpy


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


def make_active(obj, *others):
    """Select obj and others, obj active."""
    for o in bpy.context.view_layer.objects:
        o.select_set(False)
    for o in (obj, *others):
        o.select_set(True)
    bpy.context.view_layer.objects.active = obj
