"""Move the first frame's one-off costs off the first frame: after a .blend with PointGT objects is opened, a
background thread imports torch and the renderer, extracts the models packed into the .blend, loads the
objects' models into the model cache, and runs tiny deformed frames of each (`core.frames.edited.warm_up`, which
loads the compiled kernels from numba's cache and builds the model's cached canonical neighbourhoods). No bpy
here: the handler reads the model paths (and packed models' bytes) in Blender's main thread and hands them over.

The first frame then finds all of it done, or waits on the model cache's lock for the part still running instead
of doing it twice. Errors are kept (`last_error`), never raised: the frame itself reports them as it always did.
"""
from __future__ import annotations

import threading

from . import deps

_thread: threading.Thread | None = None
last_error: str = ""
done_paths: list[str] = []


def start(models: list[tuple[str, str]], extract=()) -> bool:
    """Warm up in a background thread: models [(absolute .pgt path, device 'cpu' | 'cuda')]; extract: functions
    without bpy that write a packed model to its path first (scene/model_pack.py `extraction`). Returns False
    (and does nothing) when nothing is to be done or a warm-up is still running."""
    global _thread
    if not models or (_thread is not None and _thread.is_alive()):
        return False
    # not a daemon: Python's exit waits for it rather than stopping torch mid-operation
    _thread = threading.Thread(target=_run, args=(list(dict.fromkeys(models)), list(extract)),
                               name="pointgt-warmup")
    _thread.start()
    return True


def wait(timeout: float | None = None) -> bool:
    """Block until the running warm-up (if any) ends; True when none is running afterwards."""
    t = _thread
    if t is not None:
        t.join(timeout)
        return not t.is_alive()
    return True


def _run(models: list[tuple[str, str]], extract: list) -> None:
    global last_error
    try:
        if not deps.torch_status().available:
            return
        for fn in extract:
            fn()
        from . import frame_renderer
        from core.frames.edited import warm_up

        for path, device in models:
            warm_up(frame_renderer.MODELS.get(path, device))
            done_paths.append(path)
    except Exception as exc:  # never let a background thread take the add-on down
        last_error = f"{type(exc).__name__}: {exc}"
