"""Rig helpers: a Lattice around the points, and binding the points to an Armature (bone envelopes, or
weights transferred from a proxy mesh). Points have no faces, so automatic (heat) weights are not an option."""
import bpy
import numpy as np

from core.util.errors import InputError

from ..scene.evaluated import to_world
from ..ui.properties import ModelOperator
from .reporting import reports_errors

LATTICE_MODIFIER = "PointGT Lattice"
ARMATURE_MODIFIER = "PointGT Armature"
TRANSFER_MODIFIER = "PointGT Weight Transfer"


def rest_points_world(obj) -> np.ndarray:
    """The object's undeformed points in world space [N, 3] float32."""
    mesh = obj.data
    co = np.empty(len(mesh.vertices) * 3, dtype=np.float32)
    mesh.vertices.foreach_get("co", co)
    return to_world(co.reshape(-1, 3), obj.matrix_world)


def padded_box(points: np.ndarray, margin: float) -> tuple[np.ndarray, np.ndarray]:
    """Centre [3] and size [3] of the bounding box of points [N, 3], grown by `margin` (fraction of the size)
    per side; flat or single-point clouds get a small non-zero thickness so nothing divides by zero."""
    lo, hi = points.min(axis=0).astype(np.float64), points.max(axis=0).astype(np.float64)
    size = (hi - lo) * (1.0 + 2.0 * margin)
    floor = max(float(size.max()) * 1e-3, 1e-4)
    return (lo + hi) / 2.0, np.maximum(size, floor)


def add_lattice(context, obj, resolution=(3, 3, 3), margin: float = 0.05, interpolation: str = 'KEY_BSPLINE'):
    """Create a Lattice enclosing the object's points and a Lattice modifier that uses it; returns the lattice."""
    pts = rest_points_world(obj)
    centre, size = padded_box(pts, margin)
    data = bpy.data.lattices.new(f"{obj.name} lattice")
    data.points_u, data.points_v, data.points_w = (int(r) for r in resolution)
    for axis in "uvw":
        setattr(data, f"interpolation_type_{axis}", interpolation)
    # local point coordinates are not always [-0.5, 0.5] after a resolution change: measure them
    co = np.empty(len(data.points) * 3, dtype=np.float32)
    data.points.foreach_get("co", co)
    co = co.reshape(-1, 3)
    lo, hi = co.min(axis=0), co.max(axis=0)
    extent = np.where(hi - lo > 1e-9, hi - lo, 1.0)
    scale = size / extent
    lat = bpy.data.objects.new(f"{obj.name} lattice", data)
    lat.scale = scale.tolist()
    lat.location = (centre - scale * (lo + hi) / 2.0).tolist()
    for coll in obj.users_collection or (context.scene.collection,):
        coll.objects.link(lat)
    mod = obj.modifiers.new(LATTICE_MODIFIER, 'LATTICE')
    mod.object = lat
    return lat


def envelope_coverage(obj, arm) -> np.ndarray:
    """Approximate bone-envelope weight sum [N] for the object's rest points (Blender's envelope: full weight
    within the bone radius, fading to 0 over envelope_distance) - used to warn about points no bone moves."""
    pts = rest_points_world(obj).astype(np.float64)
    inv = np.linalg.inv(np.asarray(arm.matrix_world, dtype=np.float64))
    p = pts @ inv[:3, :3].T + inv[:3, 3]
    total = np.zeros(len(p))
    for bone in arm.data.bones:
        if not bone.use_deform:
            continue
        h, t = np.asarray(bone.head_local), np.asarray(bone.tail_local)
        seg = t - h
        length2 = max(float(seg @ seg), 1e-12)
        s = np.clip((p - h) @ seg / length2, 0.0, 1.0)
        dist = np.linalg.norm(p - (h + s[:, None] * seg), axis=1)
        radius = bone.head_radius + s * (bone.tail_radius - bone.head_radius)
        fall = max(bone.envelope_distance, 1e-9)
        total += bone.envelope_weight * np.clip(1.0 - (dist - radius) / fall, 0.0, 1.0)
    return total


def _armature_modifier(obj, arm):
    mod = obj.modifiers.get(ARMATURE_MODIFIER)
    if mod is None or mod.type != 'ARMATURE':
        mod = obj.modifiers.new(ARMATURE_MODIFIER, 'ARMATURE')
    mod.object = arm
    return mod


def bind_envelopes(obj, arm) -> int:
    """Deform the points with the armature's bone envelopes (no vertex groups); returns the number of points
    outside every envelope (they will not move)."""
    mod = _armature_modifier(obj, arm)
    mod.use_vertex_groups = False
    mod.use_bone_envelopes = True
    return int((envelope_coverage(obj, arm) <= 0.0).sum())


def bind_from_proxy(context, obj, arm, proxy) -> int:
    """Copy the proxy mesh's vertex-group weights onto the points (nearest proxy vertex, a Data Transfer
    modifier that is applied) and deform with those groups; returns the number of groups transferred."""
    if proxy.type != 'MESH' or not proxy.vertex_groups:
        raise InputError(f"proxy '{proxy.name}' must be a mesh with vertex groups (e.g. weights from "
                         f"Parent > With Automatic Weights on a simple mesh around the model)")
    bones = {b.name for b in arm.data.bones}
    names = [g.name for g in proxy.vertex_groups]
    if not bones.intersection(names):
        raise InputError(f"proxy '{proxy.name}': none of its vertex groups is named after a bone of "
                         f"'{arm.name}'; weight the proxy to this armature first")
    for name in names:
        if obj.vertex_groups.get(name) is None:
            obj.vertex_groups.new(name=name)
    mod = obj.modifiers.new(TRANSFER_MODIFIER, 'DATA_TRANSFER')
    try:
        mod.object = proxy
        mod.use_object_transform = True
        mod.use_vert_data = True
        mod.data_types_verts = {'VGROUP_WEIGHTS'}
        mod.vert_mapping = 'NEAREST'
        mod.layers_vgroup_select_src = 'ALL'
        mod.layers_vgroup_select_dst = 'NAME'
        with context.temp_override(object=obj, active_object=obj):
            bpy.ops.object.modifier_move_to_index(modifier=mod.name, index=0)  # rest positions, not deformed
            result = bpy.ops.object.modifier_apply(modifier=mod.name)
        if 'FINISHED' not in result:
            raise InputError(f"Blender could not apply the weight transfer onto '{obj.name}'")
    finally:
        leftover = obj.modifiers.get(TRANSFER_MODIFIER)
        if leftover is not None:
            obj.modifiers.remove(leftover)
    mod = _armature_modifier(obj, arm)
    mod.use_vertex_groups = True
    mod.use_bone_envelopes = False
    return len(names)


def unweighted_points(obj, arm) -> int:
    """How many of the object's points have no weight in any vertex group named after a deforming bone of `arm`
    (no bone moves them)."""
    bones = {g.index for g in obj.vertex_groups
             if g.name in arm.data.bones and arm.data.bones[g.name].use_deform}
    if not bones:
        return len(obj.data.vertices)
    return sum(1 for v in obj.data.vertices if not any(g.group in bones and g.weight > 0 for g in v.groups))


def _pick(context, name: str, kind: str, exclude):
    if name:
        obj = bpy.data.objects.get(name)
        if obj is None:
            raise InputError(f"no object named '{name}'")
        return obj
    for obj in context.selected_objects:
        if obj is not exclude and obj.type == kind:
            return obj
    return None


class POINTGT_OT_add_lattice(ModelOperator, bpy.types.Operator):
    """Add a Lattice around the points and deform them with it"""
    bl_idname = "pointgt.add_lattice"
    bl_label = "Add Lattice"

    resolution: bpy.props.IntVectorProperty(name="Resolution", size=3, default=(3, 3, 3), min=2, max=64)
    margin: bpy.props.FloatProperty(name="Margin", default=0.05, min=0.0, max=1.0,
                                    description="Extra room around the points, as a fraction of their size")

    @reports_errors("Adding a lattice to '{obj}'")
    def execute(self, context):
        obj = context.active_object
        lat = add_lattice(context, obj, tuple(self.resolution), self.margin)
        self.report({'INFO'}, f"Added lattice '{lat.name}' around '{obj.name}'")
        return {'FINISHED'}


class POINTGT_OT_bind_armature(ModelOperator, bpy.types.Operator):
    """Deform the points with a selected Armature (bone envelopes, or weights from a selected proxy mesh)"""
    bl_idname = "pointgt.bind_armature"
    bl_label = "Bind to Armature"

    mode: bpy.props.EnumProperty(
        name="Weights", default='ENVELOPE',
        items=[('ENVELOPE', "Bone envelopes", "Each bone moves the points inside its envelope"),
               ('PROXY', "From proxy mesh", "Copy vertex-group weights from the nearest vertex of a selected mesh")])
    armature: bpy.props.StringProperty(name="Armature", description="Armature object (default: the selected one)")
    proxy: bpy.props.StringProperty(name="Proxy", description="Weighted mesh (default: the selected one)")

    @reports_errors("Binding '{obj}'")
    def execute(self, context):
        obj = context.active_object
        arm = _pick(context, self.armature, 'ARMATURE', obj)
        if arm is None or arm.type != 'ARMATURE':
            raise InputError("select an Armature as well as the points (the points active)")
        if self.mode == 'ENVELOPE':
            outside = bind_envelopes(obj, arm)
            if outside:
                self.report({'WARNING'}, f"{outside} of {len(obj.data.vertices)} points are outside every bone "
                                         f"envelope and will not move; scale the envelopes or use a proxy mesh")
            else:
                self.report({'INFO'}, f"Bound '{obj.name}' to '{arm.name}' with bone envelopes")
        else:
            proxy = _pick(context, self.proxy, 'MESH', obj)
            if proxy is None:
                raise InputError("select a mesh with vertex groups as the proxy (the points active)")
            n = bind_from_proxy(context, obj, arm, proxy)
            still = unweighted_points(obj, arm)
            if still:
                self.report({'WARNING'}, f"{still} of {len(obj.data.vertices)} points got no bone weight from "
                                         f"'{proxy.name}' and will not move; weight the proxy where they are")
            else:
                self.report({'INFO'}, f"Bound '{obj.name}' to '{arm.name}' with {n} groups from '{proxy.name}'")
        return {'FINISHED'}


CLASSES = (POINTGT_OT_add_lattice, POINTGT_OT_bind_armature)
