"""The PointGT tab in the 3D Viewport sidebar: dependency status, import, model settings, rig and export."""
import bpy

from ..operators import preview
from .preferences import SidebarPanel
from .properties import is_pointgt_object


class POINTGT_PT_main(SidebarPanel, bpy.types.Panel):
    bl_idname = "POINTGT_PT_main"
    bl_space_type = 'VIEW_3D'

    def draw_body(self, context, layout):
        layout.operator("pointgt.import_model", icon='IMPORT')
        obj = context.active_object
        if not is_pointgt_object(obj):
            layout.label(text="Select an imported model for more", icon='INFO')
            return
        s = obj.pointgt
        col = layout.column()
        col.prop(s, "model_path")
        row = col.row(align=True)
        if s.packed_model is not None:
            row.label(text=f"Packed in the .blend ({s.packed_model.name})", icon='PACKAGE')
            row.operator("pointgt.unpack_model", text="", icon='UGLYPACKAGE')
        else:
            row.label(text="Not packed: the .blend needs the file", icon='ERROR')
            row.operator("pointgt.pack_model", text="", icon='PACKAGE')
        text = preview.status(obj)
        if text.startswith("Warning"):
            col.label(text=text, icon='ERROR')
        col.label(text=f"{s.point_count} points")
        col.prop(s, "atlas")
        shared = preview.atlas_users(obj)
        if shared:
            col.label(text=f"Atlas shared with {len(shared)} other model(s)", icon='LINKED')
            col.operator("pointgt.single_user_atlas", icon='DUPLICATE')
        col.prop(s, "preview_resolution")
        col.prop(s, "neighbors")
        col.prop(s, "correspondence")
        col.prop(s, "occlusion")
        col.prop(s, "reshade")
        col.prop(s, "antialias")
        row = col.row(align=True)
        row.prop(s, "device")
        row.operator("pointgt.check_device", text="", icon='CHECKMARK')

        layout.label(text="Rig")
        col = layout.column(align=True)
        col.operator("pointgt.add_proxy", icon='MESH_ICOSPHERE')
        col.operator("pointgt.add_lattice", icon='OUTLINER_OB_LATTICE')
        col.operator("pointgt.bind_armature", text="Bind to Armature (envelopes)",
                     icon='OUTLINER_OB_ARMATURE').mode = 'ENVELOPE'
        col.operator("pointgt.bind_armature", text="Bind to Armature (proxy weights)",
                     icon='MOD_DATA_TRANSFER').mode = 'PROXY'
        col.operator("pointgt.reset_canonical", icon='LOOP_BACK')
        layout.operator("pointgt.export_deformed", icon='EXPORT')
        layout.operator("pointgt.setup_composite", icon='NODE_COMPOSITING')


CLASSES = (POINTGT_PT_main,)
