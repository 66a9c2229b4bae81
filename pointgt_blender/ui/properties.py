"""Per-object PointGT settings (`object.pointgt`): where the model lives and how to preview/render it."""
import bpy

from ..scene.evaluated import ID_ATTRIBUTE


# Blender 5 warns about '//' paths in string properties that do not declare support for them.
PATH_OPTIONS = {'PATH_SUPPORTS_BLEND_RELATIVE'} if bpy.app.version >= (5, 0, 0) else set()


class PointGTObjectSettings(bpy.types.PropertyGroup):
    is_model: bpy.props.BoolProperty(name="PointGT model", default=False,
                                     description="This object holds the points of a PointGT model")
    model_path: bpy.props.StringProperty(name="Model", subtype='FILE_PATH', options=PATH_OPTIONS,
                                         description="The .pgt model file (relative to the .blend when possible)")
    packed_model: bpy.props.PointerProperty(name="Packed model", type=bpy.types.Text,
                                            description="The model packed into the .blend (used instead of the "
                                                        "model file while set)")
    point_count: bpy.props.IntProperty(name="Points", min=0, description="Number of points in the model")
    atlas: bpy.props.PointerProperty(name="Atlas", type=bpy.types.Image,
                                     description="The paintable texture atlas of the model (packed in the .blend)")
    preview_resolution: bpy.props.IntProperty(name="Preview resolution", default=256, min=16, max=4096,
                                              description="Long side in pixels of the live preview")
    neighbors: bpy.props.IntProperty(name="K", default=20, min=1, max=256,
                                     description="Neighbour points per ray (the model was trained with its own K)")
    correspondence: bpy.props.EnumProperty(
        name="Correspondence", default='DEFORM_GRADIENT',
        items=[('DEFORM_GRADIENT', "Deform-gradient", "Map deformed surface points back through each neighbour's "
                                                      "local deformation, undoing its rotation and stretch (keeps "
                                                      "painted texture glued where the pose stretches the surface)"),
               ('DEFORM_AWARE', "Deform-aware", "Map deformed surface points back through their neighbours' "
                                                "displacements (the paper's: translations only)"),
               ('NAIVE', "Naive", "Attention-weighted canonical neighbours (ablation: texture drifts)")])
    occlusion: bpy.props.BoolProperty(
        name="Folds (occlusion)", default=True,
        description="Where a pose folds the surface over itself (a joint bent far, a part swung behind another), "
                    "each pixel shows only the front layer of the surface; costs a few percent more per frame")
    reshade: bpy.props.EnumProperty(
        name="Re-shade", default='OFF',
        items=[('OFF', "Off", "Posed parts keep the light they had at rest (emission or flat-lit captures)"),
               ('AUTO', "Auto", "Re-shade posed parts only when the model's atlas shows shading that follows the "
                                "surface's direction (a lit capture)"),
               ('ON', "On", "Re-shade posed parts by the shading fitted to the model's atlas: a part the pose "
                            "turns takes the light of its new direction")],
        description="A lit model's colours carry the light of its rest pose; re-shading makes a turned part "
                    "follow the light (off by default)")
    antialias: bpy.props.IntProperty(name="Anti-aliasing", default=2, min=1, max=4,
                                     description="Painted texels per pixel side, filtered like Cycles' pixel filter "
                                                 "(1 = one lookup per pixel: faster preview, jagged strokes)")
    device: bpy.props.EnumProperty(
        name="Device", default='CPU',
        items=[('CPU', "CPU", "Run the network on the processor"),
               ('CUDA', "CUDA", "Run the network on an NVIDIA GPU (needs a CUDA build of PyTorch)")])
    proxy: bpy.props.PointerProperty(name="Proxy", type=bpy.types.Object,
                                     description="The surface proxy mesh of this model (UV-mapped into the atlas; "
                                                 "the points follow it when bound with Surface Deform)")
    preview_image: bpy.props.PointerProperty(name="Preview", type=bpy.types.Image,
                                             description="The live preview of this model from the scene camera "
                                                         "(paint on it to paint the atlas)")


class PointGTSceneSettings(bpy.types.PropertyGroup):
    live_preview: bpy.props.BoolProperty(
        name="Live preview", default=True,
        description="Re-render the preview images when the points move, the frame changes or the atlas is painted")
    auto_transfer: bpy.props.BoolProperty(
        name="Transfer preview paint", default=True,
        description="Strokes painted on a preview image are written into the atlas texels those pixels show")
    transfer_threshold: bpy.props.FloatProperty(
        name="Paint threshold", default=0.02, min=0.0, max=1.0,
        description="A preview pixel counts as painted when its colour changed by more than this")
    composite: bpy.props.BoolProperty(
        name="Composite with scene", default=False,
        description="Before each frame Cycles or EEVEE renders, render the PointGT models into the 'PointGT layer' "
                    "and 'PointGT depth' images that the compositor merges with the scene by depth")
    background: bpy.props.FloatVectorProperty(
        name="Background", subtype='COLOR_GAMMA', size=3, default=(1.0, 1.0, 1.0), min=0.0, max=1.0,
        description="Colour behind the models in previews and renders (Film > Transparent renders alpha instead)")
    chart_outlines: bpy.props.BoolProperty(
        name="Chart outlines", default=True,
        description="Draw the outlines of the atlas's charts over a model's atlas in the Image Editor, so you can "
                    "tell which texels belong together while painting")
    outline_colour: bpy.props.FloatVectorProperty(
        name="Outline colour", subtype='COLOR_GAMMA', size=4, default=(1.0, 0.0, 1.0, 0.8), min=0.0, max=1.0,
        description="Colour and opacity of the chart outlines")


def is_pointgt_object(obj) -> bool:
    return (obj is not None and obj.type == 'MESH' and obj.pointgt.is_model
            and ID_ATTRIBUTE in obj.data.attributes)


NO_ACTIVE_MODEL = "Make an imported PointGT model the active object"


def poll_active_model(cls, context) -> bool:
    """Operator poll: the active object is an imported PointGT model, else the tooltip says what to do."""
    if is_pointgt_object(context.active_object):
        return True
    cls.poll_message_set(NO_ACTIVE_MODEL)
    return False


def poll_model_unless(cls, context, reason) -> bool:
    """Operator poll: the active object is an imported PointGT model and `reason(context)` finds nothing against
    running (returns None or ""); else its message (or NO_ACTIVE_MODEL) becomes the tooltip."""
    if not poll_active_model(cls, context):
        return False
    why = reason(context)
    if why:
        cls.poll_message_set(why)
        return False
    return True


class ModelOperator:
    """Mixin for operators on the active PointGT model: poll() needs one, then asks `poll_reason(context)` for a
    message when the operator cannot run now (the tooltip shows it), None when it can. They change the scene, so by
    default they register and can be undone; an operator that changes nothing Undo can restore sets its own."""

    bl_options = {'REGISTER', 'UNDO'}

    @staticmethod
    def poll_reason(context) -> str | None:
        return None

    @classmethod
    def poll(cls, context):
        return poll_model_unless(cls, context, cls.poll_reason)


def not_object_mode(context) -> str | None:
    """A `poll_model_unless` reason: operators that change the mesh or its modifiers run in Object Mode."""
    return None if context.mode == 'OBJECT' else "Switch to Object Mode first"


CLASSES = (PointGTObjectSettings, PointGTSceneSettings)


def register_properties():
    bpy.types.Object.pointgt = bpy.props.PointerProperty(type=PointGTObjectSettings)
    bpy.types.Scene.pointgt = bpy.props.PointerProperty(type=PointGTSceneSettings)


def unregister_properties():
    del bpy.types.Scene.pointgt
    del bpy.types.Object.pointgt
