"""Import a .pgt model as a vertex-only mesh (point ids as an attribute) plus its packed atlas image."""
import os

import bpy
import numpy as np
from bpy_extras.io_utils import ImportHelper

from core.modelfile.pgt import PgtFile
from core.util.errors import InputError, ModelFileError, PointGTError

from ..scene import atlas_image
from ..ui.properties import ID_ATTRIBUTE, ModelOperator
from .reporting import reports_errors

POINTS = "points/xyz"
ATLAS = "atlas/image"


def read_model(path: str) -> tuple[np.ndarray, np.ndarray | None, dict]:
    """Canonical points [N, 3] float32, atlas [H, W, 3] float32 display space (None if the model has none yet)
    and meta, all checked before anything is created in Blender."""
    with PgtFile(path) as f:
        if POINTS not in f.names:
            raise ModelFileError(f"{path}: has no '{POINTS}' array, so it holds no points; fit the model first")
        xyz = f.read(POINTS)
        atlas = f.read(ATLAS) if ATLAS in f.names else None
        meta = f.meta
    if xyz.ndim != 2 or xyz.shape[1] != 3 or xyz.shape[0] == 0 or xyz.dtype.kind != 'f':
        raise ModelFileError(f"{path}: '{POINTS}' must be float [N, 3] with N > 0, got {xyz.dtype} "
                             f"{list(xyz.shape)}; re-export the model")
    if not np.isfinite(xyz).all():
        raise ModelFileError(f"{path}: '{POINTS}' holds NaN or infinite coordinates; re-export the model")
    if atlas is not None:
        if atlas.ndim != 3 or atlas.shape[2] not in (3, 4) or 0 in atlas.shape or atlas.dtype.kind != 'f':
            raise ModelFileError(f"{path}: '{ATLAS}' must be float [H, W, 3], got {atlas.dtype} "
                                 f"{list(atlas.shape)}; re-export the model")
        if not np.isfinite(atlas).all():
            raise ModelFileError(f"{path}: '{ATLAS}' holds NaN or infinite texels; re-export the model")
    return xyz.astype(np.float32, copy=False), atlas, meta


def stored_path(path: str) -> str:
    """The model path as stored in the object: relative to the saved .blend ('//...') when possible."""
    path = os.path.abspath(path)
    if bpy.data.filepath:
        try:
            return bpy.path.relpath(path)
        except ValueError:  # another drive on Windows
            pass
    return path


def new_points_mesh(name: str, xyz: np.ndarray):
    """A mesh with one vertex per point (no edges or faces) and an INT point attribute `pointgt_id` = 0..N-1."""
    n = xyz.shape[0]
    mesh = bpy.data.meshes.new(name)
    mesh.vertices.add(n)
    mesh.vertices.foreach_set("co", np.ascontiguousarray(xyz, dtype=np.float32).reshape(-1))
    attr = mesh.attributes.new(ID_ATTRIBUTE, 'INT', 'POINT')
    attr.data.foreach_set("value", np.arange(n, dtype=np.int32))
    mesh.update()
    return mesh


def import_model(context, path: str, name: str = "", pack: bool = True, **settings):
    """Create the points object (+ packed atlas image) for the model at `path` and make it active.
    pack: also pack the model file into the .blend (model_pack). `settings`: preview_resolution, neighbors,
    correspondence, device. Raises PointGTError; on any error nothing is left behind."""
    path = bpy.path.abspath(path)
    if not os.path.isfile(path):
        raise ModelFileError(f"{path}: file not found; choose an existing .pgt model")
    xyz, atlas, meta = read_model(path)
    if "neighbors" not in settings:  # the K the model was trained with, unless the artist chose one
        k = (meta.get("model") or {}).get("k") if isinstance(meta, dict) else None
        if isinstance(k, int) and not isinstance(k, bool) and 1 <= k <= 256:
            settings["neighbors"] = k
    name = name or os.path.splitext(os.path.basename(path))[0]
    created = []  # (collection, datablock): removed again if anything below fails
    try:
        mesh = new_points_mesh(name, xyz)
        created.append((bpy.data.meshes, mesh))
        image = None
        if atlas is not None:
            image = atlas_image.new_atlas_image(f"{name} atlas", atlas)
            created.append((bpy.data.images, image))
        obj = bpy.data.objects.new(name, mesh)
        created.append((bpy.data.objects, obj))
        s = obj.pointgt
        s.is_model = True
        s.model_path = stored_path(path)
        s.point_count = xyz.shape[0]
        s.atlas = image
        if pack:
            from ..scene.model_pack import pack_file

            text = pack_file(path)
            if text.users == 0:
                created.append((bpy.data.texts, text))
            s.packed_model = text
        for key, value in settings.items():
            setattr(s, key, value)
        (context.collection or context.scene.collection).objects.link(obj)
        for other in context.selected_objects:
            other.select_set(False)
        obj.select_set(True)
        context.view_layer.objects.active = obj
    except Exception:
        for collection, block in reversed(created):
            collection.remove(block)
        raise
    return obj


class POINTGT_OT_import_model(bpy.types.Operator, ImportHelper):
    """Import a PointGT model (.pgt) as points you can rig, with its paintable atlas"""
    bl_idname = "pointgt.import_model"
    bl_label = "Import PointGT Model"
    bl_options = {'REGISTER', 'UNDO'}

    filename_ext = ".pgt"
    filter_glob: bpy.props.StringProperty(default="*.pgt", options={'HIDDEN'})
    preview_resolution: bpy.props.IntProperty(name="Preview resolution", default=256, min=16, max=4096)
    neighbors: bpy.props.IntProperty(name="K", default=20, min=1, max=256,
                                     description="Neighbour points per ray (unset: the K the model was trained with)")
    correspondence: bpy.props.EnumProperty(
        name="Correspondence", default='DEFORM_GRADIENT',
        items=[('DEFORM_GRADIENT', "Deform-gradient", ""), ('DEFORM_AWARE', "Deform-aware", ""), ('NAIVE', "Naive", "")])
    device: bpy.props.EnumProperty(name="Device", default='CPU', items=[('CPU', "CPU", ""), ('CUDA', "CUDA", "")])
    pack_model: bpy.props.BoolProperty(name="Pack model into .blend", default=True,
                                       description="Keep a copy of the .pgt inside the .blend, so the .blend renders "
                                                   "without the model file (Unpack Model writes it out again)")
    add_proxy: bpy.props.BoolProperty(name="Surface proxy", default=True,
                                      description="Also make the surface proxy mesh (UV-mapped into the atlas, "
                                                  "paintable in 3-D) and let the points follow it")
    proxy_faces: bpy.props.IntProperty(name="Proxy faces", default=4000, min=50, max=200000)
    check_blank: bpy.props.BoolProperty(name="Check the model renders", default=True,
                                        description="Render the model small from six sides and warn when it shows "
                                                    "nothing (needs PyTorch; the first check also loads it)")

    def execute(self, context):
        try:
            settings = dict(preview_resolution=self.preview_resolution, correspondence=self.correspondence,
                            device=self.device)
            if self.properties.is_property_set("neighbors"):
                settings["neighbors"] = self.neighbors
            obj = import_model(context, self.filepath, pack=self.pack_model, **settings)
        except PointGTError as exc:
            self.report({'ERROR'}, str(exc))
            return {'CANCELLED'}
        except Exception as exc:  # never let an unexpected error take Blender down
            self.report({'ERROR'}, f"Importing {self.filepath} failed: {type(exc).__name__}: {exc}")
            return {'CANCELLED'}
        atlas = obj.pointgt.atlas
        extra = f", atlas {atlas.size[0]}x{atlas.size[1]}" if atlas else " (the model has no atlas yet)"
        extra += ", packed into the .blend" if obj.pointgt.packed_model else ""
        if self.add_proxy and obj.pointgt.atlas is not None:
            from .proxy import add_proxy

            try:
                proxy = add_proxy(context, obj, bpy.path.abspath(self.filepath), self.proxy_faces)
                extra += f", proxy '{proxy.name}' ({len(proxy.data.polygons)} faces)"
            except PointGTError as exc:
                self.report({'WARNING'}, f"No surface proxy: {exc}")
            except Exception as exc:
                self.report({'WARNING'}, f"No surface proxy: {type(exc).__name__}: {exc}")
            context.view_layer.objects.active = obj
        self.report({'INFO'}, f"Imported '{obj.name}': {obj.pointgt.point_count} points{extra}")
        warning = blank_warning(obj) if self.check_blank else ""
        if warning:
            self.report({'WARNING'}, warning)
        return {'FINISHED'}


def blank_warning(obj) -> str:
    """The renderer's warning when the object's model renders blank ('' when it shows something, or when PyTorch
    is missing: then nothing can be checked). The warning also becomes the object's status line."""
    from ..bridge import deps

    if not deps.torch_status().available:
        return ""
    from ..bridge import frame_renderer
    from . import preview
    from ..scene import scene_inputs

    try:
        warning = frame_renderer.blank_warning(scene_inputs.model_file(obj), obj.pointgt.device.lower(),
                                               label=os.path.basename(bpy.path.abspath(obj.pointgt.model_path)))
    except PointGTError as exc:
        warning = str(exc)
    if warning:
        preview.set_status(obj, f"Warning: {warning}")
    return warning


class POINTGT_OT_pack_model(ModelOperator, bpy.types.Operator):
    """Pack the model file into the .blend, so the .blend renders without it"""
    bl_idname = "pointgt.pack_model"
    bl_label = "Pack Model"

    @staticmethod
    def poll_reason(context):
        return "The model is packed already" if context.active_object.pointgt.packed_model is not None else None

    @reports_errors("Packing the model of '{obj}'")
    def execute(self, context):
        from ..scene.model_pack import pack_file

        obj = context.active_object
        path = bpy.path.abspath(obj.pointgt.model_path)
        if not os.path.isfile(path):
            raise ModelFileError(f"{path}: model file not found; point the Model setting to the .pgt first")
        read_model(path)  # refuse a damaged file
        obj.pointgt.packed_model = pack_file(path)
        self.report({'INFO'}, f"Packed {os.path.basename(path)} into the .blend")
        return {'FINISHED'}


class POINTGT_OT_unpack_model(ModelOperator, bpy.types.Operator):
    """Write the packed model to a .pgt file and use that file instead of the packed copy"""
    bl_idname = "pointgt.unpack_model"
    bl_label = "Unpack Model"

    filepath: bpy.props.StringProperty(name="File", subtype='FILE_PATH',
                                       description="Where to write the model (default: the model path, or "
                                                   "'//<name>.pgt' next to the .blend)")

    @staticmethod
    def poll_reason(context):
        return "The model is not packed" if context.active_object.pointgt.packed_model is None else None

    @reports_errors("Unpacking the model of '{obj}'")
    def execute(self, context):
        from ..scene.model_pack import unpack

        obj = context.active_object
        target = self.filepath or obj.pointgt.model_path or f"//{obj.name}.pgt"
        if target.startswith("//") and not bpy.data.filepath:
            raise InputError("save the .blend first, or choose an absolute file to unpack into")
        path = unpack(obj, target)
        self.report({'INFO'}, f"Wrote the model of '{obj.name}' to {path}")
        return {'FINISHED'}


def relative_to(path: str, blend_path: str) -> str:
    """`path` ('//'-relative to the current .blend, or absolute) re-expressed relative to `blend_path`."""
    absolute = os.path.normpath(bpy.path.abspath(path))
    try:
        return "//" + os.path.relpath(absolute, os.path.dirname(os.path.abspath(blend_path)))
    except ValueError:  # another drive on Windows: keep it absolute
        return absolute


def relative_model_paths(filepath: str) -> None:
    """Called before saving to `filepath`: models imported before the .blend had a location get paths relative
    to where it is saved now (when Blender's 'Default relative paths' preference is on), so a project folder can
    move."""
    if not filepath or not bpy.context.preferences.filepaths.use_relative_paths:
        return
    for obj in bpy.data.objects:
        s = getattr(obj, "pointgt", None)
        if s is not None and s.is_model and s.model_path:
            s.model_path = relative_to(s.model_path, filepath)


def menu_import(self, context):
    self.layout.operator(POINTGT_OT_import_model.bl_idname, text="PointGT Model (.pgt)")


CLASSES = (POINTGT_OT_import_model, POINTGT_OT_pack_model, POINTGT_OT_unpack_model)


def register_menus():
    bpy.types.TOPBAR_MT_file_import.append(menu_import)


def unregister_menus():
    bpy.types.TOPBAR_MT_file_import.remove(menu_import)
