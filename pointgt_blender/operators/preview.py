"""Live preview: each PointGT model gets its own image '<object> preview' rendered from the scene camera, and
strokes painted on it are transferred to the atlas texels they show.

Never blocking: the handlers (handlers.py) only call `request` when something changed; `run_slice` (the UI timer,
or tests directly) then renders coarse-to-fine (64 px long side, doubled up to the preview resolution) as a
generator of small steps, each level written into the image, and a newer change cancels the running job.
Nothing is recomputed when nothing changed: the edit state is cached on the deformed positions, ids and atlas
pixels (frame_renderer.StateCache), and a preview is re-rendered only when that state, the camera, the size or K
changed. Problems become a status line per object (`status(obj)`), shown in the panels. `update_previews` and the
operators are the synchronous path (full size at once).
"""
from __future__ import annotations

import time
from dataclasses import dataclass

import bpy
import numpy as np

from core.util.errors import InputError, PointGTError

from ..scene import atlas_image
from ..bridge import checks, deps
from ..scene.camera import preview_size, scene_camera
from ..ui.properties import ModelOperator, is_pointgt_object
from .reporting import reports_errors
from ..scene.state import STATE

POLL_SECONDS = 0.5      # idle timer period: look for paint on the previews
SLICE_SECONDS = 0.05    # a timer call runs preview steps until this budget is spent
SLICE_INTERVAL = 0.02   # next timer call while a preview job is running
FIRST_LEVEL = 64        # coarse-to-fine: long side of the first preview level, then doubled
S = STATE
COUNTS = S.counts
_RECORDS = S.records
_STATUS = S.status


@dataclass
class PreviewRecord:
    """What the preview image of one object currently shows."""

    state: object           # the EditState it was rendered from
    key: tuple              # size, camera, background
    written: np.ndarray     # the raw pixels written into the image (to notice painting)
    rendered: np.ndarray    # display-space rgb [H, W, 3] (row 0 = top)
    result: dict            # render_edited output (trace: for the canonical surface map)
    image: str = ""         # the name of the image it was written into (an image this object owns)
    _x_can: np.ndarray | None = None

    def x_can(self) -> np.ndarray:
        """Canonical surface point [H, W, 3] of every preview pixel on the object (NaN elsewhere)."""
        if self._x_can is None:
            from ..bridge.paint_transfer import canonical_surface

            self._x_can = canonical_surface(self.state, self.result)
        return self._x_can



def status(obj) -> str:
    return S.status.get(obj.name, "")


def set_status(obj, text: str) -> None:
    S.status[obj.name] = text


def clear_caches() -> None:
    """Forget everything cached (after loading another .blend, or on unregister)."""
    S.clear()


def preview_objects(scene) -> list:
    """PointGT objects of the scene that get a preview (visible in the viewport)."""
    out = []
    for obj in scene.objects:
        if is_pointgt_object(obj):
            try:
                visible = obj.visible_get()
            except Exception:  # not in the current view layer
                visible = False
            if visible:
                out.append(obj)
    return out


def _image_pixels(rgb: np.ndarray) -> np.ndarray:
    """Display rgb [H, W, 3] (row 0 = top) -> raw pixels of the float preview image (linear, row 0 = bottom)."""
    return atlas_image.atlas_to_pixels(rgb)


OWNER = "pointgt_owner"  # custom property of a preview image: the name of the object it belongs to


def owned_preview_image(obj):
    """The object's preview image if this object owns it, else None. A duplicate (Shift+D, Alt+D) copies the
    pointer to the original's preview; the image's owner tag tells them apart, so a duplicate never draws into
    (nor reads paint from) another object's preview. An image whose owner is gone (renamed or deleted) is adopted."""
    img = obj.pointgt.preview_image
    if img is None:
        return None
    owner = img.get(OWNER)
    if owner == obj.name:
        return img
    other = bpy.data.objects.get(owner) if isinstance(owner, str) else None
    if other is not None and other is not obj and getattr(other, "pointgt", None) is not None \
            and other.pointgt.preview_image == img:
        return None  # a duplicate: it gets its own image
    img[OWNER] = obj.name
    return img


def ensure_preview_image(obj, width: int, height: int):
    """The object's own preview image at `width` x `height` (created or resized as needed)."""
    s = obj.pointgt
    img = owned_preview_image(obj)
    if img is None:
        img = bpy.data.images.new(f"{obj.name} preview", width=width, height=height, alpha=True, float_buffer=True)
        img.colorspace_settings.name = "Linear Rec.709"
        img[OWNER] = obj.name
        s.preview_image = img
        S.records.pop(obj.name, None)
    elif tuple(img.size) != (width, height):
        img.scale(width, height)
    return img


def atlas_users(obj) -> list:
    """The other PointGT objects that paint into the same atlas image as `obj` (duplicates share it until
    Make Atlas Single-User gives one its own copy)."""
    img = obj.pointgt.atlas
    if img is None:
        return []
    return [o for o in bpy.data.objects if o is not obj and is_pointgt_object(o) and o.pointgt.atlas == img]


def _read_raw(image) -> np.ndarray:
    w, h = image.size
    buf = np.empty(w * h * image.channels, dtype=np.float32)
    image.pixels.foreach_get(buf)
    return buf


def _painted_preview(obj, rec: PreviewRecord) -> np.ndarray | None:
    """The preview as the artist left it (display rgb [H, W, 3]) when it differs from what was rendered. Only
    the object's own image is looked at, and only while it shows the full-resolution level (strokes on a coarse
    level are painted over by the next level)."""
    img = owned_preview_image(obj)
    last = S.written.get(obj.name)
    if img is None or rec is None or rec.image != img.name or last is None or last is not rec.written:
        return None
    raw = _read_raw(img)
    if raw.shape == last.shape and np.array_equal(raw, last):
        return None
    h, w = rec.rendered.shape[:2]
    if tuple(img.size) != (w, h) or img.channels != 4:
        return None  # resized by hand: nothing to compare with
    return atlas_image.pixels_to_atlas(raw, h, w, linear=True)


def transfer_paint(scene, obj) -> tuple[int, int]:
    """Write the strokes painted on the object's preview into its atlas image. Returns (painted pixels,
    changed texels). Raises PointGTError with what to do when it cannot."""
    from ..bridge import paint_transfer
    from ..scene import scene_inputs

    rec = S.records.get(obj.name)
    s = obj.pointgt
    if rec is None:
        raise InputError(f"object '{obj.name}': its preview was not rendered since this .blend was opened, so PointGT cannot "
                         f"tell what was painted on it; re-render the preview, then paint on it")
    if s.atlas is None or rec.state.bundle.atlas is None:
        raise InputError(f"object '{obj.name}': the model has no atlas to paint into; fit one (`pointgt atlas`) "
                         f"and re-import")
    painted = _painted_preview(obj, rec)
    if painted is None:
        return 0, 0
    current = scene_inputs.ATLASES.read(s.atlas)
    new, changed, n_px = paint_transfer.transfer(rec.state.bundle.atlas, current, painted, rec.rendered, rec.x_can(),
                                                 threshold=scene.pointgt.transfer_threshold)
    if changed.any():
        write_texels(s.atlas, new, changed)
        COUNTS["transfers"] += 1
    return n_px, int(changed.sum())


def write_texels(image, atlas: np.ndarray, changed: np.ndarray) -> None:
    """Write atlas [A, B, 3] (display space, row 0 = top) into `image` where changed [A, B]; other texels keep
    their exact stored values."""
    w, h = image.size
    raw = _read_raw(image).reshape(h, w, image.channels)
    rows = changed[::-1]  # Blender rows start at the bottom
    raw[rows, :3] = atlas_image.srgb_to_linear(atlas[::-1][rows])
    image.pixels.foreach_set(raw.reshape(-1))
    image.update()


def preview_levels(width: int, height: int, first: int = FIRST_LEVEL) -> list[tuple[int, int]]:
    """Coarse-to-fine sizes (w, h) of a width x height preview: long side `first`, doubled until the full size
    (always the last entry); the aspect ratio is kept."""
    long_side = max(width, height)
    sizes, side = [], max(int(first), 1)
    while side < long_side:
        sizes.append((max(1, round(width * side / long_side)), max(1, round(height * side / long_side))))
        side *= 2
    return sizes + [(width, height)]


def _upsample(rgb: np.ndarray, height: int, width: int) -> np.ndarray:
    """Nearest-neighbour resize of rgb [h, w, 3] to [height, width, 3] (a coarse level shown at full size)."""
    h, w = rgb.shape[:2]
    rows = np.minimum((np.arange(height) + 0.5) * h / height, h - 1).astype(np.int64)
    cols = np.minimum((np.arange(width) + 0.5) * w / width, w - 1).astype(np.int64)
    return rgb[rows][:, cols]


def object_steps(scene, depsgraph, obj, force: bool = False, levels: bool = True):
    """Bring one object's preview up to date, as a generator of small steps (each yield is a point where the
    work may stop for a while or be cancelled). Its return value says what happened: 'unchanged', 'rendered',
    'transferred+rendered' or 'painted' (paint kept, transfer off). Raises PointGTError.
    levels: render coarse-to-fine (`preview_levels`), writing each level into the image; else only the full
    size."""
    from ..bridge import frame_renderer
    from ..scene import scene_inputs

    name = obj.name
    rec = S.records.get(name)
    did = ""
    if rec is not None and not force and _painted_preview(obj, rec) is not None:
        # the artist painted on the preview: transfer before anything re-renders over it
        if not scene.pointgt.auto_transfer or obj.pointgt.atlas is None:
            set_status(obj, "The preview was painted and is kept: Transfer Preview Paint to Atlas, or Re-render "
                            "Preview to discard the strokes")
            return "painted"
        transfer_paint(scene, obj)
        did = "transferred"
    scene_inputs.check_device(obj)
    inputs = scene_inputs.object_inputs(obj, depsgraph)
    r = scene.render
    w, h = preview_size(obj.pointgt.preview_resolution, r.resolution_x, r.resolution_y)
    c2w, focal = scene_camera(scene, w, h, depsgraph)
    background = tuple(scene.pointgt.background)
    key = (w, h, c2w.tobytes(), focal, background, int(inputs.k))
    warning = checks.pose_warning(obj.name, inputs.positions, inputs.rest_extent, c2w, focal, w, h)
    yield "inputs"
    state = frame_renderer.prepare(inputs)  # loads the model the first time (seconds), else a cache hit
    img = owned_preview_image(obj)
    if not force and not did and rec is not None and rec.state is state and rec.key == key and img is not None \
            and rec.image == img.name and S.written.get(name) is rec.written:
        return "unchanged"
    t0 = time.perf_counter()
    sizes = preview_levels(w, h) if levels else [(w, h)]
    for level, (lw, lh) in enumerate(sizes, 1):
        yield "level"
        f = focal * lw / w
        trace = frame_renderer.trace_layer(state, c2w, lh, lw, f, k=inputs.k)
        yield "traced"
        layer = frame_renderer.render_layer(state, c2w, lh, lw, f, k=inputs.k, trace=trace)
        rgb, _ = frame_renderer.composite([layer], background=background)
        final = (lw, lh) == (w, h)
        img = ensure_preview_image(obj, w, h)
        img.pixels.foreach_set(_image_pixels(rgb if final else _upsample(rgb, h, w)))
        img.update()
        written = _read_raw(img)
        S.written[name] = written
        S.counts["levels"] += 1
        if not final:
            set_status(obj, f"Preview {w}x{h}: refining ({lw}x{lh} shown, level {level} of {len(sizes)})")
            continue
        S.counts["rendered"] += 1
        S.records[name] = PreviewRecord(state=state, key=key, written=written, rendered=rgb,
                                        result=layer["result"], image=img.name)
        stats = layer["result"]["stats"]
        set_status(obj, f"Warning: {warning}" if warning else
                   f"Preview {w}x{h}: {stats['rays_shaded']} rays on the model, "
                   f"{(time.perf_counter() - t0) * 1000:.0f} ms")
    return (did + "+rendered") if did else "rendered"


def update_object(scene, depsgraph, obj, force: bool = False) -> str:
    """`object_steps` run to the end at full size only (the synchronous path: operators, tests)."""
    steps = object_steps(scene, depsgraph, obj, force=force, levels=False)
    try:
        while True:
            next(steps)
    except StopIteration as stop:
        return stop.value


def _job(scene, depsgraph, objects, force: bool, levels: bool, done: dict):
    """Preview work for several objects as one generator of steps; results (or 'error: ...') go into `done`,
    the same text into each object's status. Never raises."""
    objs = preview_objects(scene) if objects is None else list(objects)
    if not objs:
        return
    st = deps.torch_status()
    if not st.available:
        for obj in objs:
            set_status(obj, st.message)
            done[obj.name] = "error: " + st.message
        return
    depsgraph = depsgraph or bpy.context.evaluated_depsgraph_get()
    for obj in objs:
        try:
            name = obj.name
            done[name] = yield from object_steps(scene, depsgraph, obj, force=force, levels=levels)
        except PointGTError as exc:
            set_status(obj, str(exc))
            done[name] = f"error: {exc}"
        except ReferenceError:  # the object was deleted while the job waited
            continue
        except Exception as exc:  # a preview must never take Blender down
            msg = f"preview failed: {type(exc).__name__}: {exc}"
            set_status(obj, msg)
            done[name] = f"error: {msg}"


def update_previews(scene, depsgraph=None, force: bool = False, objects=None) -> dict:
    """Synchronous update of the previews (all previewed objects, or `objects`) at full size. Never raises:
    returns {object name: what happened or 'error: ...'}; the same text becomes the object's status."""
    if S.busy:
        return {}
    if S.job is not None:  # a running slice job would finish with what it read before this update
        S.cancel()
        S.dirty = True
    S.busy = True
    done = {}
    n = max(len(preview_objects(scene) if objects is None else list(objects)), 1)
    # this path blocks Blender (an operator waits for it): the window manager's progress shows how far it is
    wm = getattr(bpy.context, "window_manager", None)
    S.progress = []
    try:
        if wm is not None:
            wm.progress_begin(0.0, 1.0)
        for label in _job(scene, depsgraph, objects, force, False, done):
            S.progress.append(min((len(done) + SYNC_STAGES.get(label, 0.0)) / n, 1.0))
            if wm is not None:
                wm.progress_update(S.progress[-1])
        S.progress.append(1.0)
    except Exception as exc:
        print(f"PointGT preview: {type(exc).__name__}: {exc}")
    finally:
        S.busy = False
        if wm is not None:
            wm.progress_end()
    return done


SYNC_STAGES = {"inputs": 0.05, "level": 0.15, "traced": 0.65}  # how far one object's preview is at each step


def live(scene) -> bool:
    """The live preview is on for `scene` and no render job runs."""
    return (not S.rendering and scene is not None and getattr(scene, "pointgt", None) is not None
            and scene.pointgt.live_preview)


def request(scene) -> None:
    """Something the previews show may have changed: remember it and cancel the running job (its result would
    be stale). Constant time: the handlers call this and nothing else."""
    S.dirty = True
    S.generation += 1
    S.scene = scene.name
    S.counts["requests"] += 1


def run_slice(budget: float = SLICE_SECONDS) -> bool:
    """One time slice of preview work (the UI timer calls it when Blender is idle; tests call it directly): starts
    a job for the latest change, cancels one made stale by a newer change, and runs its steps until `budget`
    seconds are spent (at least one step). Returns True while work remains."""
    if S.rendering or S.busy:
        return S.dirty or S.job is not None
    if S.job is not None and S.job_generation != S.generation:
        S.cancel()  # a newer change: start over from the new state
    if S.job is None:
        if not S.dirty:
            return False
        scene = bpy.data.scenes.get(S.scene) or bpy.context.scene
        S.dirty = False
        if not live(scene):
            return False
        S.job = _job(scene, None, None, False, True, {})
        S.job_generation = S.generation
        S.counts["jobs"] += 1
    t0 = time.perf_counter()
    S.busy = True
    try:
        while True:
            next(S.job)
            if time.perf_counter() - t0 >= budget:
                return True
    except StopIteration:
        S.job = None
        return S.dirty
    except Exception as exc:  # never let the timer die
        print(f"PointGT preview: {type(exc).__name__}: {exc}")
        S.job = None
        return S.dirty
    finally:
        S.busy = False


def look_for_paint(scene) -> bool:
    """Painting in the Image Editor may not tag the depsgraph: compare each preview with what was written into
    it (one pixel read per preview) and request an update when one was painted. Returns whether one was."""
    for obj in preview_objects(scene):
        rec = S.records.get(obj.name)
        if rec is not None and _painted_preview(obj, rec) is not None:
            request(scene)
            return True
    return False


def tick():
    """The UI timer: a slice of preview work while there is some, else a look for paint every POLL_SECONDS."""
    try:
        if run_slice():
            return SLICE_INTERVAL
        scene = bpy.context.scene
        if live(scene) and look_for_paint(scene):
            return SLICE_INTERVAL
    except Exception as exc:
        print(f"PointGT preview timer: {type(exc).__name__}: {exc}")
    return POLL_SECONDS


def run_pending(max_slices: int = 100000) -> int:
    """Run slices until no preview work is left (what the timer does over time; headless there is no timer).
    Returns the number of slices."""
    n = 0
    while n < max_slices and run_slice():
        n += 1
    return n


def _target_objects(context) -> list:
    obj = context.active_object
    return [obj] if is_pointgt_object(obj) else preview_objects(context.scene)


class POINTGT_OT_refresh_preview(bpy.types.Operator):
    """Render the preview of the active PointGT model (or of all models) again from the scene camera"""
    bl_idname = "pointgt.refresh_preview"
    bl_label = "Re-render Preview"
    bl_options = {'REGISTER'}

    def execute(self, context):
        objs = _target_objects(context)
        if not objs:
            self.report({'ERROR'}, "No visible PointGT model in the scene; import one first")
            return {'CANCELLED'}
        done = update_previews(context.scene, context.evaluated_depsgraph_get(), force=True, objects=objs)
        errors = [f"{name}: {what[7:]}" for name, what in done.items() if what.startswith("error: ")]
        if errors:
            self.report({'ERROR'}, "; ".join(errors))
            return {'CANCELLED'}
        self.report({'INFO'}, "; ".join(status(o) for o in objs))
        return {'FINISHED'}


class POINTGT_OT_transfer_paint(ModelOperator, bpy.types.Operator):
    """Write what was painted on the preview image into the atlas texels those pixels show"""
    bl_idname = "pointgt.transfer_paint"
    bl_label = "Transfer Preview Paint to Atlas"
    bl_options = {'REGISTER'}

    @reports_errors("Transferring the preview paint of '{obj}'")
    def execute(self, context):
        obj = context.active_object
        if not deps.torch_status().available:
            raise InputError(deps.torch_status().message)
        n_px, n_tex = transfer_paint(context.scene, obj)
        if n_px == 0:
            self.report({'WARNING'}, f"Nothing painted on the preview of '{obj.name}' (or only off the model)")
            return {'CANCELLED'}
        update_previews(context.scene, context.evaluated_depsgraph_get(), force=True, objects=[obj])
        self.report({'INFO'}, f"{n_px} painted preview pixels wrote {n_tex} atlas texels of '{obj.name}'")
        return {'FINISHED'}


class POINTGT_OT_single_user_atlas(ModelOperator, bpy.types.Operator):
    """Give the active model its own copy of the atlas it shares with duplicates, so painting it leaves theirs"""
    bl_idname = "pointgt.single_user_atlas"
    bl_label = "Make Atlas Single-User"

    @staticmethod
    def poll_reason(context):
        return None if atlas_users(context.active_object) else "No other model shares this atlas"

    @reports_errors("Copying the atlas of '{obj}'")
    def execute(self, context):
        obj = context.active_object
        obj.pointgt.atlas = atlas_image.copy_atlas_image(obj.pointgt.atlas, f"{obj.name} atlas")
        self.report({'INFO'}, f"'{obj.name}' now paints into its own atlas '{obj.pointgt.atlas.name}'")
        return {'FINISHED'}


CLASSES = (POINTGT_OT_refresh_preview, POINTGT_OT_transfer_paint, POINTGT_OT_single_user_atlas)
