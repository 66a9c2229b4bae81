"""Export the deformed points of the current frame: positions [M, 3] float32 and ids [M] int64 as .npy files."""
import io
import os

import bpy
import numpy as np
from bpy_extras.io_utils import ExportHelper

from core.util.atomic import atomic_write_bytes

from ..scene.evaluated import evaluated_points
from ..ui.properties import ModelOperator
from .reporting import reports_errors


def npy_bytes(array: np.ndarray) -> bytes:
    buf = io.BytesIO()
    np.save(buf, array, allow_pickle=False)
    return buf.getvalue()


def export_paths(filepath: str) -> tuple[str, str]:
    """`<base>_positions.npy` and `<base>_ids.npy` for a chosen path (a trailing .npy is dropped)."""
    base = bpy.path.abspath(filepath)
    if base.lower().endswith(".npy"):
        base = base[:-4]
    return f"{base}_positions.npy", f"{base}_ids.npy"


def export_deformed(obj, depsgraph, filepath: str, space: str = 'WORLD') -> tuple[str, str, int]:
    """Write the evaluated points atomically (existing files kept as .bak); returns both paths and M."""
    pos, ids = evaluated_points(obj, depsgraph, space)
    p_path, i_path = export_paths(filepath)
    atomic_write_bytes(p_path, npy_bytes(pos.astype(np.float32)))
    atomic_write_bytes(i_path, npy_bytes(ids.astype(np.int64)))
    return p_path, i_path, int(pos.shape[0])


class POINTGT_OT_export_deformed(ModelOperator, bpy.types.Operator, ExportHelper):
    """Save the deformed points of this frame as <name>_positions.npy [M,3] float32 and <name>_ids.npy [M] int64"""
    bl_idname = "pointgt.export_deformed"
    bl_label = "Export Deformed Points"
    bl_options = {'REGISTER'}

    filename_ext = ".npy"
    filter_glob: bpy.props.StringProperty(default="*.npy", options={'HIDDEN'})
    space: bpy.props.EnumProperty(name="Space", default='WORLD',
                                  items=[('WORLD', "World", "Positions in world space (as the cameras see them)"),
                                         ('LOCAL', "Object", "Positions in the object's own space")])

    def invoke(self, context, event):
        if not self.filepath:
            self.filepath = f"{context.active_object.name}_frame{context.scene.frame_current:04d}.npy"
        return ExportHelper.invoke(self, context, event)

    @reports_errors("Exporting '{obj}'")
    def execute(self, context):
        obj = context.active_object
        p_path, i_path, m = export_deformed(obj, context.evaluated_depsgraph_get(), self.filepath, self.space)
        self.report({'INFO'}, f"Wrote {m} points to {os.path.basename(p_path)} and {os.path.basename(i_path)}")
        return {'FINISHED'}


CLASSES = (POINTGT_OT_export_deformed,)
