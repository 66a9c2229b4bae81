"""Back to the canonical pose: switch off (or remove) deform modifiers, optionally restore the point positions
from the model file (after the mesh itself was edited)."""
import bpy
import numpy as np

from core.util.errors import InputError

from ..scene.evaluated import read_points
from .model_import import read_model
from ..ui.properties import ModelOperator, not_object_mode
from .reporting import reports_errors

DEFORM_MODIFIERS = {'ARMATURE', 'LATTICE', 'CAST', 'CURVE', 'DISPLACE', 'HOOK', 'LAPLACIANDEFORM', 'MESH_DEFORM',
                    'SIMPLE_DEFORM', 'SMOOTH', 'CORRECTIVE_SMOOTH', 'LAPLACIANSMOOTH', 'SURFACE_DEFORM', 'WARP',
                    'WAVE', 'SHRINKWRAP', 'MESH_CACHE', 'MESH_SEQUENCE_CACHE', 'NODES'}


def reset_modifiers(obj, action: str = 'DISABLE') -> int:
    """'DISABLE' hides deform modifiers in viewport and render (reversible), 'REMOVE' deletes them; returns how
    many were affected. Lattice and armature objects themselves are left alone."""
    hits = [m for m in obj.modifiers if m.type in DEFORM_MODIFIERS]
    for mod in hits:
        if action == 'REMOVE':
            obj.modifiers.remove(mod)
        else:
            mod.show_viewport = False
            mod.show_render = False
    return len(hits)


def restore_positions(obj) -> int:
    """Write the model's canonical positions back into the mesh, matched by point id (works after points were
    deleted or duplicated in Edit Mode); returns the number of points written."""
    from ..scene.scene_inputs import model_file

    xyz, _atlas, _meta = read_model(model_file(obj))
    _pos, ids = read_points(obj.data)
    if ids is None:
        raise InputError(f"object '{obj.name}' lost its 'pointgt_id' attribute; re-import the model")
    if ids.size and (ids.min() < 0 or ids.max() >= len(xyz)):
        raise InputError(f"object '{obj.name}': point ids do not match {obj.pointgt.model_path} "
                         f"({len(xyz)} points); is it the right model file?")
    obj.data.vertices.foreach_set("co", np.ascontiguousarray(xyz[ids]).reshape(-1))
    obj.data.update()
    return int(ids.size)


# What Reset does with the deform modifiers (Armature, Lattice, ...) of the points.
DEFORMER_ACTIONS = [('DISABLE', "Disable", "Switch deform modifiers off (turn them back on in the modifier panel)"),
                    ('REMOVE', "Remove", "Delete deform modifiers")]


class POINTGT_OT_reset_canonical(ModelOperator, bpy.types.Operator):
    """Show the points in their canonical (unposed) positions"""
    bl_idname = "pointgt.reset_canonical"
    bl_label = "Reset to Canonical"

    action: bpy.props.EnumProperty(name="Deformers", default='DISABLE', items=DEFORMER_ACTIONS)
    restore_positions: bpy.props.BoolProperty(
        name="Restore positions from model", default=False,
        description="Also reload the point positions from the .pgt file (undo edits made in Edit Mode)")

    poll_reason = staticmethod(not_object_mode)

    @reports_errors("Resetting '{obj}'")
    def execute(self, context):
        obj = context.active_object
        n = reset_modifiers(obj, self.action)
        msg = f"{'Removed' if self.action == 'REMOVE' else 'Disabled'} {n} deform modifier(s) on '{obj.name}'"
        if self.restore_positions:
            msg += f"; restored {restore_positions(obj)} point positions"
        self.report({'INFO'}, msg)
        return {'FINISHED'}


CLASSES = (POINTGT_OT_reset_canonical,)
