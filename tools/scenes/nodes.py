"""Shader node trees for the procedural textures of `core.edits.procedural` (needs bpy).

`NodeOps` is the Blender backend of the texture expressions: each operation becomes a Math node, so the material
computes exactly the formula that `core.edits.procedural.evaluate` computes in torch.
"""
from __future__ import annotations

import bpy

from core.edits.procedural import ExprOps, build_expression


class NodeOps(ExprOps):
    """Builds Math nodes into `tree`; Scalars are output sockets (or float constants, folded in Python)."""

    def __init__(self, tree: bpy.types.NodeTree):
        self.tree = tree
        self.count = 0

    def _node(self, op: str, inputs):
        node = self.tree.nodes.new("ShaderNodeMath")
        node.operation = op
        node.use_clamp = False
        node.location = (200 + 160 * (self.count // 40), -60 * (self.count % 40))
        self.count += 1
        for sock, val in zip(node.inputs, inputs):
            if self._is_const(val):
                sock.default_value = float(val)
            else:
                self.tree.links.new(val, sock)
        return node.outputs[0]

    def _bin(self, op, a, b):
        return self._node(op, (a, b))

    def _un(self, op, a):
        return self._node(op, (a,))

    def constant(self, value: float):
        node = self.tree.nodes.new("ShaderNodeValue")
        node.outputs[0].default_value = float(value)
        return node.outputs[0]


def _generated_sockets(tree):
    coord = tree.nodes.new("ShaderNodeTexCoord")
    sep = tree.nodes.new("ShaderNodeSeparateXYZ")
    sep.location = (200, 0)
    tree.links.new(coord.outputs["Generated"], sep.inputs[0])
    return sep.outputs[0], sep.outputs[1], sep.outputs[2]


def texture_color_socket(tree, base: str, base_params: dict | None = None, decal: str | None = None,
                         decal_params: dict | None = None):
    """Add nodes computing the LINEAR colour of `base` (optionally with `decal` composited over it in display
    space) from Generated coordinates; returns the output socket of a Combine Color node."""
    ops = NodeOps(tree)
    g = _generated_sockets(tree)
    rgb, _ = build_expression(base, g, ops, base_params)
    if decal is not None:
        drgb, mask = build_expression(decal, g, ops, decal_params)
        rgb = ops.mix_rgb(mask if mask is not None else 1.0, rgb, drgb)
    linear = [ops.srgb_to_linear(c) for c in rgb]
    combine = tree.nodes.new("ShaderNodeCombineColor")
    combine.location = (1400, 0)
    for sock, val in zip(combine.inputs, linear):
        if ops._is_const(val):
            sock.default_value = float(val)
        else:
            tree.links.new(val, sock)
    return combine.outputs[0]


def make_material(name: str, base: str, base_params: dict | None = None, decal: str | None = None,
                  decal_params: dict | None = None, lit: bool = False) -> bpy.types.Material:
    """Emission material (colour = texture, no lighting: an exact ground truth under any deformation), or with
    `lit` a Principled BSDF with the same base colour. Double-sided (no backface culling)."""
    mat = bpy.data.materials.new(name)
    mat.use_nodes = True
    tree = mat.node_tree
    tree.nodes.clear()
    out = tree.nodes.new("ShaderNodeOutputMaterial")
    out.location = (1900, 0)
    color = texture_color_socket(tree, base, base_params, decal, decal_params)
    if lit:
        shader = tree.nodes.new("ShaderNodeBsdfPrincipled")
        tree.links.new(color, shader.inputs["Base Color"])
        shader.inputs["Roughness"].default_value = 0.6
    else:
        shader = tree.nodes.new("ShaderNodeEmission")
        tree.links.new(color, shader.inputs["Color"])
        shader.inputs["Strength"].default_value = 1.0
    shader.location = (1650, 0)
    tree.links.new(shader.outputs[0], out.inputs["Surface"])
    mat.use_backface_culling = False
    return mat
