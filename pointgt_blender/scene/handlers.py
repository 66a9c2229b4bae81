"""Every Blender handler, timer and draw handler of the add-on, in one place.

Handlers do at most a cheap step: a change to the scene (depsgraph update, frame change) only marks the previews
dirty (`preview.request`, constant time); the preview itself is rendered coarse-to-fine by the UI timer
(`preview.tick` -> `preview.run_slice`) in slices of about 50 ms when Blender is idle, and a newer change cancels
the running one. So a script's batch of operator calls (each a depsgraph update) costs nothing until Blender
is idle again. Headless (`blender -b`, the bpy module) timers never fire; `preview.run_pending()` runs the
slices. Each handler call's duration is kept in `STATE.handler_ms` (tests hold it to <= 100 ms).
"""
from __future__ import annotations

import os
import time

import bpy

from core.util.errors import PointGTError

from . import atlas_image
from ..operators import model_import, preview
from .state import STATE

FIRST_TICK = 0.05  # after a change, the timer looks again this soon (seconds)


def _timed(fn):
    """Run the handler body, never raise, and record how long it took."""
    def wrapper(*args):
        t0 = time.perf_counter()
        try:
            fn(*args)
        except Exception as exc:  # a handler must never take Blender down
            print(f"PointGT {fn.__name__}: {type(exc).__name__}: {exc}")
        finally:
            STATE.handler_ms.append((time.perf_counter() - t0) * 1000.0)
            del STATE.handler_ms[:-1000]
    wrapper.__name__ = fn.__name__
    wrapper.__doc__ = fn.__doc__
    return bpy.app.handlers.persistent(wrapper)


def _preview_only(depsgraph) -> bool:
    """The update holds nothing but preview images (written by the preview itself): nothing to redo."""
    if depsgraph is None:
        return False
    ids = [u.id for u in depsgraph.updates]
    return bool(ids) and all(isinstance(i, bpy.types.Image) and i.original.get(preview.OWNER) is not None
                             for i in ids)


def _wake():
    """Bring the next timer call forward (UI only; headless there are no timers)."""
    if bpy.app.background:
        return
    if bpy.app.timers.is_registered(preview.tick):
        bpy.app.timers.unregister(preview.tick)
    bpy.app.timers.register(preview.tick, first_interval=FIRST_TICK, persistent=True)


@_timed
def on_frame_change(scene, depsgraph=None):
    if preview.live(scene):
        preview.request(scene)
        _wake()


@_timed
def on_depsgraph_update(scene, depsgraph=None):
    if preview.live(scene) and not _preview_only(depsgraph):
        preview.request(scene)
        _wake()


@_timed
def on_load(*_args):
    STATE.clear()
    _start_warmup()


def _start_warmup():
    """The opened .blend's PointGT objects with a model (packed into the .blend, or a file on disk): import torch,
    extract the packed models, load the models and run the compiled kernels once in the background
    (bridge/warmup.py), so the first frame does not pay for it. Here only the packed bytes are read; checking and
    writing them is left to the thread."""
    from ..bridge import warmup
    from ..ui.properties import is_pointgt_object
    from .model_pack import extraction

    models, extract = [], []
    for obj in bpy.data.objects:
        if not is_pointgt_object(obj):
            continue
        device = obj.pointgt.device.lower()
        if obj.pointgt.packed_model is not None:
            try:
                path, fn = extraction(obj.pointgt.packed_model)
            except PointGTError:  # no packed bytes: the frame reports it
                continue
            models.append((path, device))
            if fn is not None:
                extract.append(fn)
        elif obj.pointgt.model_path:
            path = os.path.normpath(bpy.path.abspath(obj.pointgt.model_path, library=obj.library))
            if os.path.isfile(path):
                models.append((path, device))
    warmup.start(models, extract)


@_timed
def on_undo(*_args):
    """undo_post / redo_post: the preview images may hold other pixels now; forget what was written into them, so
    the difference is never mistaken for paint (no atlas texel changes because of an undo)."""
    STATE.forget_previews()
    scene = bpy.context.scene
    if preview.live(scene):
        preview.request(scene)


@_timed
def on_save(filepath="", *_args):
    """save_pre: painted atlases are packed again (or the .blend would keep the atlas as imported); model paths
    become relative to where the .blend is saved."""
    atlas_image.repack_painted_atlases()
    model_import.relative_model_paths(filepath)


@_timed
def on_render_start(*_args):
    STATE.rendering = True
    STATE.cancel()


@_timed
def on_render_pre(scene, *_args):
    """render_pre: with Composite with Scene on and another engine rendering, the PointGT layer of this frame."""
    if scene is None or not scene.pointgt.composite or scene.render.engine == 'POINTGT':
        return
    from ..render import composite
    from ..bridge import deps

    st = deps.torch_status()
    if not st.available:
        print(f"PointGT: the PointGT layer is not rendered: {st.message}")
        return
    try:
        composite.update_layer(scene)
    except Exception as exc:
        composite.clear_layer(scene)  # never a stale model from an earlier frame
        STATE.status["__composite__"] = f"PointGT layer failed: {type(exc).__name__}: {exc}"
        raise


@_timed
def on_render_end(*_args):
    STATE.rendering = False


HANDLERS = (("frame_change_post", on_frame_change), ("depsgraph_update_post", on_depsgraph_update),
            ("load_post", on_load), ("save_pre", on_save), ("undo_post", on_undo), ("redo_post", on_undo),
            ("render_init", on_render_start), ("render_pre", on_render_pre), ("render_complete", on_render_end),
            ("render_cancel", on_render_end))


_DRAW = []  # (space type, handle) of the draw handlers added by register_handlers


def register_handlers():
    from ..ui import image_panel

    if not _DRAW:  # the chart outlines over a model's atlas in the Image Editor (drawn only where a GPU draws)
        _DRAW.append((bpy.types.SpaceImageEditor, bpy.types.SpaceImageEditor.draw_handler_add(
            image_panel.draw_chart_outlines, (), 'WINDOW', 'POST_PIXEL')))
    for name, fn in HANDLERS:
        lst = getattr(bpy.app.handlers, name)
        if fn not in lst:
            lst.append(fn)
    if not bpy.app.background and not bpy.app.timers.is_registered(preview.tick):
        bpy.app.timers.register(preview.tick, first_interval=preview.POLL_SECONDS, persistent=True)


def unregister_handlers():
    while _DRAW:
        space, handle = _DRAW.pop()
        space.draw_handler_remove(handle, 'WINDOW')
    for name, fn in HANDLERS:
        lst = getattr(bpy.app.handlers, name)
        if fn in lst:
            lst.remove(fn)
    if bpy.app.timers.is_registered(preview.tick):
        bpy.app.timers.unregister(preview.tick)
    STATE.clear()
