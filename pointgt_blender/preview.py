"""Live preview: each PointGT model gets an image '<object> preview' rendered from the scene camera, kept up to
date by persistent frame_change_post / depsgraph_update_post handlers (and, with a UI, a half-second timer that
notices painting). Strokes painted on a preview are transferred to the atlas texels they show.

Nothing is recomputed when nothing changed: the edit state is cached on the deformed positions, ids and atlas
pixels (frame_renderer.StateCache), and a preview is re-rendered only when that state, the camera or the size
changed. Writing the preview image triggers another depsgraph update; that one finds everything unchanged
(and `_busy` guards against synchronous re-entry). Handlers never raise: problems become a status string per
object (`status(obj)`), shown in the panels. Headless there is no timer; `update_previews` and the operators
are the synchronous path.
"""
from __future__ import annotations

import sys
from dataclasses import dataclass

import bpy
import numpy as np

from core.util.errors import InputError, PointGTError

from . import atlas_image, deps
from .camera import preview_size, scene_camera
from .properties import is_pointgt_object, poll_active_model

POLL_SECONDS = 0.5
_STATUS: dict[str, str] = {}
_busy = False
_rendering = False  # a render job runs: its frame changes must not trigger previews
COUNTS = {"rendered": 0, "transfers": 0}  # how often work was actually done (tests check the caching)


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
            from .paint_transfer import canonical_surface

            self._x_can = canonical_surface(self.state, self.result)
        return self._x_can


_RECORDS: dict[str, PreviewRecord] = {}


def status(obj) -> str:
    return _STATUS.get(obj.name, "")


def set_status(obj, text: str) -> None:
    _STATUS[obj.name] = text


def clear_caches() -> None:
    """Forget everything cached (after loading another .blend, or on unregister)."""
    _RECORDS.clear()
    _STATUS.clear()
    if "torch" in sys.modules and deps.torch_status().available:
        from . import frame_renderer, scene_inputs

        frame_renderer.STATES.clear()
        frame_renderer.MODELS.clear()
        scene_inputs.ATLASES.clear()


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
        _RECORDS.pop(obj.name, None)
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
    """The preview as the artist left it (display rgb [H, W, 3]) when it differs from what was rendered."""
    img = owned_preview_image(obj)
    if img is None or rec is None or rec.image != img.name:
        return None
    raw = _read_raw(img)
    if raw.shape == rec.written.shape and np.array_equal(raw, rec.written):
        return None
    h, w = rec.rendered.shape[:2]
    if tuple(img.size) != (w, h) or img.channels != 4:
        return None  # resized by hand: nothing to compare with
    return atlas_image.pixels_to_atlas(raw, h, w, linear=True)


def transfer_paint(scene, obj) -> tuple[int, int]:
    """Write the strokes painted on the object's preview into its atlas image. Returns (painted pixels,
    changed texels). Raises PointGTError with what to do when it cannot."""
    from . import paint_transfer, scene_inputs

    rec = _RECORDS.get(obj.name)
    s = obj.pointgt
    if rec is None:
        raise InputError(f"object '{obj.name}': its preview was not rendered in this session, so PointGT cannot "
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


def update_object(scene, depsgraph, obj, force: bool = False) -> str:
    """Bring one object's preview up to date. Returns what happened: 'unchanged', 'rendered', 'transferred'
    (+ rendered) or 'painted' (paint kept, transfer off). Raises PointGTError."""
    from . import frame_renderer, scene_inputs

    rec = _RECORDS.get(obj.name)
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
    state = frame_renderer.prepare(inputs)
    r = scene.render
    w, h = preview_size(obj.pointgt.preview_resolution, r.resolution_x, r.resolution_y)
    c2w, focal = scene_camera(scene, w, h, depsgraph)
    key = (w, h, c2w.tobytes(), focal, tuple(scene.pointgt.background))
    if not force and not did and rec is not None and rec.state is state and rec.key == key \
            and owned_preview_image(obj) is not None and rec.image == obj.pointgt.preview_image.name:
        return "unchanged"
    layer = frame_renderer.render_layer(state, c2w, h, w, focal)
    rgb, _ = frame_renderer.composite([layer], background=tuple(scene.pointgt.background))
    img = ensure_preview_image(obj, w, h)
    pixels = _image_pixels(rgb)
    img.pixels.foreach_set(pixels)
    img.update()
    COUNTS["rendered"] += 1
    _RECORDS[obj.name] = PreviewRecord(state=state, key=key, written=_read_raw(img), rendered=rgb,
                                       result=layer["result"], image=img.name)
    stats = layer["result"]["stats"]
    set_status(obj, f"Preview {w}x{h}: {stats['rays_shaded']} rays on the model, {stats['seconds'] * 1000:.0f} ms")
    return (did + "+rendered") if did else "rendered"


def update_previews(scene, depsgraph=None, force: bool = False, objects=None) -> dict:
    """Synchronous update of the previews (all previewed objects, or `objects`). Never raises: returns
    {object name: what happened or 'error: ...'}; the same text becomes the object's status."""
    global _busy
    if _busy:
        return {}
    _busy = True
    done = {}
    try:
        objs = preview_objects(scene) if objects is None else list(objects)
        if not objs:
            return done
        st = deps.torch_status()
        if not st.available:
            for obj in objs:
                set_status(obj, st.message)
                done[obj.name] = "error: " + st.message
            return done
        depsgraph = depsgraph or bpy.context.evaluated_depsgraph_get()
        for obj in objs:
            try:
                done[obj.name] = update_object(scene, depsgraph, obj, force=force)
            except PointGTError as exc:
                set_status(obj, str(exc))
                done[obj.name] = f"error: {exc}"
            except Exception as exc:  # a handler must never take Blender down
                msg = f"preview failed: {type(exc).__name__}: {exc}"
                set_status(obj, msg)
                done[obj.name] = f"error: {msg}"
    except Exception as exc:
        print(f"PointGT preview: {type(exc).__name__}: {exc}")
    finally:
        _busy = False
    return done


def _live(scene) -> bool:
    return (not _rendering and scene is not None and getattr(scene, "pointgt", None) is not None
            and scene.pointgt.live_preview)


@bpy.app.handlers.persistent
def on_frame_change(scene, depsgraph=None):
    if _live(scene):
        update_previews(scene, depsgraph)


@bpy.app.handlers.persistent
def on_depsgraph_update(scene, depsgraph=None):
    if _live(scene):
        update_previews(scene, depsgraph)


@bpy.app.handlers.persistent
def on_load(*_args):
    clear_caches()


@bpy.app.handlers.persistent
def on_undo(*_args):
    """undo_post / redo_post: the preview images may hold other pixels now; forget what was written into them, so
    the difference is never mistaken for paint (no atlas texel changes because of an undo)."""
    _RECORDS.clear()


@bpy.app.handlers.persistent
def on_save(*_args):
    """save_pre: painted atlases are packed again, or the .blend would keep the atlas as imported."""
    try:
        atlas_image.repack_painted_atlases()
    except Exception as exc:  # a save must never fail because of the add-on
        print(f"PointGT: could not pack the painted atlas: {type(exc).__name__}: {exc}")


@bpy.app.handlers.persistent
def on_render_start(*_args):
    global _rendering
    _rendering = True


@bpy.app.handlers.persistent
def on_render_end(*_args):
    global _rendering
    _rendering = False


def _poll():
    """UI timer: painting in the Image Editor may not tag the depsgraph; look for painted pixels here."""
    try:
        scene = bpy.context.scene
        if _live(scene):
            update_previews(scene)
    except Exception as exc:
        print(f"PointGT preview timer: {type(exc).__name__}: {exc}")
    return POLL_SECONDS


_HANDLERS = (("frame_change_post", on_frame_change), ("depsgraph_update_post", on_depsgraph_update),
             ("load_post", on_load), ("save_pre", on_save),
             ("undo_post", on_undo), ("redo_post", on_undo), ("render_init", on_render_start),
             ("render_complete", on_render_end), ("render_cancel", on_render_end))


def register_handlers():
    for name, fn in _HANDLERS:
        lst = getattr(bpy.app.handlers, name)
        if fn not in lst:
            lst.append(fn)
    if not bpy.app.background and not bpy.app.timers.is_registered(_poll):
        bpy.app.timers.register(_poll, first_interval=POLL_SECONDS, persistent=True)


def unregister_handlers():
    for name, fn in _HANDLERS:
        lst = getattr(bpy.app.handlers, name)
        if fn in lst:
            lst.remove(fn)
    if bpy.app.timers.is_registered(_poll):
        bpy.app.timers.unregister(_poll)
    clear_caches()


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


class POINTGT_OT_transfer_paint(bpy.types.Operator):
    """Write what was painted on the preview image into the atlas texels those pixels show"""
    bl_idname = "pointgt.transfer_paint"
    bl_label = "Transfer Preview Paint to Atlas"
    bl_options = {'REGISTER'}

    @classmethod
    def poll(cls, context):
        return poll_active_model(cls, context)

    def execute(self, context):
        obj = context.active_object
        if not deps.torch_status().available:
            self.report({'ERROR'}, deps.torch_status().message)
            return {'CANCELLED'}
        try:
            n_px, n_tex = transfer_paint(context.scene, obj)
        except PointGTError as exc:
            self.report({'ERROR'}, str(exc))
            return {'CANCELLED'}
        except Exception as exc:
            self.report({'ERROR'}, f"Transfer failed: {type(exc).__name__}: {exc}")
            return {'CANCELLED'}
        if n_px == 0:
            self.report({'WARNING'}, f"Nothing painted on the preview of '{obj.name}' (or only off the model)")
            return {'CANCELLED'}
        update_previews(context.scene, context.evaluated_depsgraph_get(), force=True, objects=[obj])
        self.report({'INFO'}, f"{n_px} painted preview pixels wrote {n_tex} atlas texels of '{obj.name}'")
        return {'FINISHED'}


class POINTGT_OT_single_user_atlas(bpy.types.Operator):
    """Give the active model its own copy of the atlas it shares with duplicates, so painting it leaves theirs"""
    bl_idname = "pointgt.single_user_atlas"
    bl_label = "Make Atlas Single-User"
    bl_options = {'REGISTER', 'UNDO'}

    @classmethod
    def poll(cls, context):
        if not poll_active_model(cls, context):
            return False
        if not atlas_users(context.active_object):
            cls.poll_message_set("No other model shares this atlas")
            return False
        return True

    def execute(self, context):
        obj = context.active_object
        try:
            obj.pointgt.atlas = atlas_image.copy_atlas_image(obj.pointgt.atlas, f"{obj.name} atlas")
        except Exception as exc:
            self.report({'ERROR'}, f"Copying the atlas of '{obj.name}' failed: {type(exc).__name__}: {exc}")
            return {'CANCELLED'}
        self.report({'INFO'}, f"'{obj.name}' now paints into its own atlas '{obj.pointgt.atlas.name}'")
        return {'FINISHED'}


CLASSES = (POINTGT_OT_refresh_preview, POINTGT_OT_transfer_paint, POINTGT_OT_single_user_atlas)
