"""The surface proxy in Blender: the mesh of `proxy_mesh.proxy_arrays` with the UV map 'PointGT atlas' and a
material showing the model's atlas (Solid mode's Texture colour, Material Preview, EEVEE/Cycles, Texture Paint),
and a Surface Deform modifier on the points bound to it at rest, so whatever moves the proxy moves the points."""
from __future__ import annotations

import bpy
import numpy as np

from core.util.errors import InputError

from ..ui.properties import ModelOperator, not_object_mode
from ..scene.proxy_mesh import proxy_arrays, read_texel_map
from .reporting import reports_errors

PROXY_SUFFIX = " proxy"
SURFACE_DEFORM = "PointGT Surface Deform"
UV_NAME = "PointGT atlas"


def atlas_material(name: str, image):
    """A material showing `image` through the UV map: Principled base colour from an Image Texture node that is
    the active node (Solid mode's Texture colour and Texture Paint's canvas use it)."""
    mat = bpy.data.materials.new(name)
    mat.use_nodes = True
    nt = mat.node_tree
    bsdf = next((n for n in nt.nodes if n.bl_idname == 'ShaderNodeBsdfPrincipled'), None)
    if bsdf is None:
        bsdf = nt.nodes.new('ShaderNodeBsdfPrincipled')
        out = next(n for n in nt.nodes if n.bl_idname == 'ShaderNodeOutputMaterial')
        nt.links.new(bsdf.outputs[0], out.inputs[0])
    uvmap = nt.nodes.new('ShaderNodeUVMap')
    uvmap.uv_map = UV_NAME
    tex = nt.nodes.new('ShaderNodeTexImage')
    tex.image = image
    tex.interpolation = 'Linear'
    tex.location = (bsdf.location.x - 320, bsdf.location.y)
    uvmap.location = (tex.location.x - 220, tex.location.y)
    nt.links.new(uvmap.outputs["UV"], tex.inputs["Vector"])
    nt.links.new(tex.outputs["Color"], bsdf.inputs["Base Color"])
    if "Roughness" in bsdf.inputs:
        bsdf.inputs["Roughness"].default_value = 1.0
    nt.nodes.active = tex
    return mat


def build_proxy(context, obj, path: str, target_faces: int = 4000):
    """Create '<object> proxy': the mesh of `proxy_arrays` in the object's space and transform, with the UV map
    'PointGT atlas' and a material showing the object's atlas. Returns the proxy object."""
    tex, R, pad = read_texel_map(path)
    verts, tris, uv = proxy_arrays(tex, R, pad, target_faces)
    mesh = bpy.data.meshes.new(obj.name + PROXY_SUFFIX)
    mesh.vertices.add(len(verts))
    mesh.vertices.foreach_set("co", verts.reshape(-1))
    mesh.loops.add(tris.size)
    mesh.loops.foreach_set("vertex_index", tris.reshape(-1))
    mesh.polygons.add(len(tris))
    mesh.polygons.foreach_set("loop_start", np.arange(0, tris.size, 3, dtype=np.int32))
    mesh.update(calc_edges=True)
    layer = mesh.uv_layers.new(name=UV_NAME)
    layer.data.foreach_set("uv", np.ascontiguousarray(uv, dtype=np.float32).reshape(-1))
    mesh.validate()
    if obj.pointgt.atlas is not None:
        mesh.materials.append(atlas_material(obj.name + " atlas", obj.pointgt.atlas))
    proxy = bpy.data.objects.new(obj.name + PROXY_SUFFIX, mesh)
    proxy.matrix_world = obj.matrix_world.copy()
    for coll in obj.users_collection or (context.scene.collection,):
        coll.objects.link(proxy)
    obj.pointgt.proxy = proxy
    return proxy


def follow_proxy(context, obj, proxy) -> None:
    """Make the points follow the proxy: a Surface Deform modifier (first in the stack) bound now, at rest."""
    mod = obj.modifiers.get(SURFACE_DEFORM)
    if mod is None or mod.type != 'SURFACE_DEFORM':
        mod = obj.modifiers.new(SURFACE_DEFORM, 'SURFACE_DEFORM')
    mod.target = proxy
    with context.temp_override(object=obj, active_object=obj):
        bpy.ops.object.modifier_move_to_index(modifier=mod.name, index=0)
        if mod.is_bound:
            bpy.ops.object.surfacedeform_bind(modifier=mod.name)  # unbind first
        bpy.ops.object.surfacedeform_bind(modifier=mod.name)
    if not mod.is_bound:
        raise InputError(f"Blender could not bind '{obj.name}' to '{proxy.name}' (Surface Deform); the proxy may be "
                         f"too sparse: raise its face count")


def add_proxy(context, obj, path: str, target_faces: int = 4000, follow: bool = True):
    """build_proxy (+ follow_proxy); on any error nothing is left behind. Returns the proxy object."""
    proxy = build_proxy(context, obj, path, target_faces)
    try:
        if follow:
            follow_proxy(context, obj, proxy)
    except Exception:
        mesh, mats = proxy.data, list(proxy.data.materials)
        bpy.data.objects.remove(proxy)
        bpy.data.meshes.remove(mesh)
        for m in mats:
            if m is not None and m.users == 0:
                bpy.data.materials.remove(m)
        mod = obj.modifiers.get(SURFACE_DEFORM)
        if mod is not None:
            obj.modifiers.remove(mod)
        raise
    return proxy


class POINTGT_OT_add_proxy(ModelOperator, bpy.types.Operator):
    """Make a surface mesh of the model, UV-mapped into its atlas (paint it in 3-D), that the points follow
    (rig or simulate the proxy like any mesh)"""
    bl_idname = "pointgt.add_proxy"
    bl_label = "Add Surface Proxy"

    target_faces: bpy.props.IntProperty(name="Faces", default=4000, min=50, max=200000,
                                        description="At most this many triangles")
    follow: bpy.props.BoolProperty(name="Points follow the proxy", default=True,
                                   description="Bind the points to the proxy with a Surface Deform modifier, "
                                               "so rigging the proxy poses the neural render")

    poll_reason = staticmethod(not_object_mode)

    @reports_errors("Making a proxy for '{obj}'")
    def execute(self, context):
        from ..scene.scene_inputs import model_file

        obj = context.active_object
        proxy = add_proxy(context, obj, model_file(obj), self.target_faces, self.follow)
        self.report({'INFO'}, f"Added '{proxy.name}' ({len(proxy.data.polygons)} faces)"
                              + ("; the points follow it" if self.follow else ""))
        return {'FINISHED'}


CLASSES = (POINTGT_OT_add_proxy,)
