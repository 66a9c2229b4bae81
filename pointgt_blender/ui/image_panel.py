"""The PointGT tab in the Image Editor sidebar: the model's preview and atlas images (the atlas opens ready for
Texture Paint), preview settings, re-render, transfer of preview paint, and Render Animation; and the chart
outlines drawn over a model's atlas (`draw_chart_outlines`, a draw handler that scene/handlers.py registers)."""
import bpy

from ..operators import preview
from .preferences import SidebarPanel
from .properties import NO_ACTIVE_MODEL, is_pointgt_object


def panel_object(context):
    """The PointGT model the Image Editor is about: the active object, or the model whose preview or atlas the
    editor shows."""
    obj = context.active_object
    if is_pointgt_object(obj):
        return obj
    image = getattr(context.space_data, "image", None)
    if image is not None:
        for o in context.scene.objects:
            if is_pointgt_object(o) and image in (o.pointgt.atlas, o.pointgt.preview_image):
                return o
    return None


def atlas_owner(scene, image):
    """The PointGT model whose atlas `image` is (the first, when duplicates share it), or None."""
    if image is None:
        return None
    for o in scene.objects:
        if is_pointgt_object(o) and o.pointgt.atlas == image:
            return o
    return None


def shown_outlines(context):
    """Chart outlines [S, 2, 2] float32 in UV space to draw over the Image Editor of `context` (its space and
    scene), or None when there is nothing to draw: outlines off, or the editor does not show a model's atlas.
    Errors reading the model (a missing file) also give None: the overlay never stands in the way."""
    from ..scene import chart_outlines
    from ..scene.scene_inputs import model_file

    scene, space = context.scene, context.space_data
    if scene is None or getattr(space, "type", "") != 'IMAGE_EDITOR' or not scene.pointgt.chart_outlines:
        return None
    obj = atlas_owner(scene, space.image)
    if obj is None:
        return None
    try:
        return chart_outlines.model_outlines(model_file(obj))
    except Exception:  # a missing or damaged model file: the panels say so, the overlay stays quiet
        return None


def draw_chart_outlines():
    """SpaceImageEditor draw handler (POST_PIXEL): the chart outlines over the atlas, mapped through the editor's
    pan and zoom. Blender calls it only where it draws (never headless)."""
    from ..scene import chart_outlines

    context = bpy.context
    seg = shown_outlines(context)
    if seg is None or not len(seg) or context.region is None:
        return
    v2d = context.region.view2d
    origin, corner = v2d.view_to_region(0.0, 0.0, clip=False), v2d.view_to_region(1.0, 1.0, clip=False)
    if origin == corner:  # the view is not set up yet (nothing drawn so far)
        return
    import gpu
    from gpu_extras.batch import batch_for_shader

    shader = gpu.shader.from_builtin('UNIFORM_COLOR')
    batch = batch_for_shader(shader, 'LINES', {"pos": chart_outlines.to_region(seg, origin, corner)})
    gpu.state.blend_set('ALPHA')
    shader.uniform_float("color", tuple(context.scene.pointgt.outline_colour))
    batch.draw(shader)
    gpu.state.blend_set('NONE')


def show_image(context, image, paint: bool) -> None:
    """Show `image` in the context's Image Editor; with `paint`, switch it to Paint mode with the image as the
    paint canvas."""
    space = context.space_data
    space.image = image
    if paint:
        space.ui_mode = 'PAINT'
        settings = context.scene.tool_settings.image_paint
        settings.mode = 'IMAGE'
        settings.canvas = image


class _ImageEditorOp:
    @classmethod
    def poll(cls, context):
        if getattr(context.space_data, "type", "") != 'IMAGE_EDITOR':
            cls.poll_message_set("Run this from the Image Editor")
            return False
        if panel_object(context) is None:
            cls.poll_message_set(NO_ACTIVE_MODEL)
            return False
        return True


class POINTGT_OT_open_atlas(_ImageEditorOp, bpy.types.Operator):
    """Show the model's atlas in this Image Editor, ready for Texture Paint"""
    bl_idname = "pointgt.open_atlas"
    bl_label = "Paint Atlas"
    bl_options = {'REGISTER'}

    def execute(self, context):
        obj = panel_object(context)
        if obj.pointgt.atlas is None:
            self.report({'ERROR'}, f"'{obj.name}' has no atlas (the model was saved before `pointgt atlas` ran)")
            return {'CANCELLED'}
        show_image(context, obj.pointgt.atlas, paint=True)
        return {'FINISHED'}


class POINTGT_OT_open_preview(_ImageEditorOp, bpy.types.Operator):
    """Show the model's live preview in this Image Editor (paint on it to paint the atlas where you look)"""
    bl_idname = "pointgt.open_preview"
    bl_label = "Show Preview"
    bl_options = {'REGISTER'}

    paint: bpy.props.BoolProperty(name="Paint", default=True, description="Switch to Paint mode on the preview")

    def execute(self, context):
        obj = panel_object(context)
        if obj.pointgt.preview_image is None:
            done = preview.update_previews(context.scene, context.evaluated_depsgraph_get(), force=True, objects=[obj])
            if obj.pointgt.preview_image is None:
                self.report({'ERROR'}, done.get(obj.name, "the preview could not be rendered"))
                return {'CANCELLED'}
        show_image(context, obj.pointgt.preview_image, paint=self.paint)
        return {'FINISHED'}


class POINTGT_PT_image(SidebarPanel, bpy.types.Panel):
    bl_idname = "POINTGT_PT_image"
    bl_space_type = 'IMAGE_EDITOR'

    def draw_body(self, context, layout):
        obj = panel_object(context)
        if obj is None:
            layout.label(text="Select an imported model", icon='INFO')
            return
        s, scene = obj.pointgt, context.scene
        layout.label(text=obj.name, icon='OUTLINER_OB_MESH')
        row = layout.row(align=True)
        row.operator("pointgt.open_preview", icon='RESTRICT_RENDER_OFF')
        row.operator("pointgt.open_atlas", icon='TPAINT_HLT')
        col = layout.column()
        col.prop(s, "preview_image")
        col.prop(s, "atlas")
        row = col.row(align=True)
        row.prop(scene.pointgt, "chart_outlines")
        row.prop(scene.pointgt, "outline_colour", text="")
        shared = preview.atlas_users(obj)
        if shared:
            box = col.box()
            box.label(text=f"Atlas shared with {', '.join(o.name for o in shared[:3])}"
                           f"{' ...' if len(shared) > 3 else ''}: painting changes both", icon='LINKED')
            box.operator("pointgt.single_user_atlas", icon='DUPLICATE')
        col.prop(s, "preview_resolution")
        col.prop(s, "correspondence")
        col.prop(s, "occlusion")
        col.prop(s, "reshade")
        col.prop(s, "antialias")
        col.prop(scene.pointgt, "live_preview")
        col.prop(scene.pointgt, "auto_transfer")
        col.operator("pointgt.refresh_preview", icon='FILE_REFRESH')
        col.operator("pointgt.transfer_paint", icon='BRUSH_DATA')
        text = preview.status(obj)
        if text:
            layout.label(text=text, icon='INFO')
        box = layout.box()
        box.prop(scene.render, "engine")
        row = box.row(align=True)
        row.operator("render.render", text="Render Image", icon='RENDER_STILL')
        row.operator("render.render", text="Render Animation", icon='RENDER_ANIMATION').animation = True


CLASSES = (POINTGT_OT_open_atlas, POINTGT_OT_open_preview, POINTGT_PT_image)
