"""Pose rigs: add a named pose's deformer to ANY object (a mesh or a vertex-only point mesh), needs bpy.

Each pose gets one rig object in the current Blender scene, named `pgt_rig_<pose>` (a Lattice, or an Armature
whose bones deform by envelope only), shared by every object the pose is applied to, so a scene mesh and a
model's points in the same scene get the same deformation field. The rig stores its spec and magnitude as custom
properties, so `set_magnitude` and `animate_pose` work on a loaded scene.blend too.
"""
from __future__ import annotations

import json
import math

import bpy
import numpy as np
from mathutils import Matrix

from core.util.errors import InputError
from tools.scenes import pose_math
from tools.scenes.spec import load_scene_spec

LATTICE_MARGIN = 1.3  # the lattice box is the rest bbox scaled by this: points slightly outside still deform
LATTICE_SLICES = 24  # along the bend/twist axis
MIN_EXTENT = 0.2  # lattice size of a (nearly) flat axis


def pose_spec(spec: dict, pose: str) -> dict:
    poses = spec.get("poses", {})
    if pose not in poses:
        raise InputError(f"unknown pose '{pose}' for scene '{spec.get('name')}'; choose one of {', '.join(poses)}")
    return poses[pose]


def rig_name(pose: str) -> str:
    return f"pgt_rig_{pose}"


def _bbox(spec):
    return np.asarray(spec["bbox"]["center"], dtype=np.float64), np.asarray(spec["bbox"]["half_size"], dtype=np.float64)


def _make_lattice(name: str, pose: dict, center, half):
    lat = bpy.data.lattices.new(name)
    along = pose.get("along", 0)
    res = [2, 2, 2]
    if pose["type"] in ("bend", "twist"):
        res[along] = LATTICE_SLICES
    lat.points_u, lat.points_v, lat.points_w = res
    for attr in ("interpolation_type_u", "interpolation_type_v", "interpolation_type_w"):
        setattr(lat, attr, "KEY_LINEAR")  # linear: scaling is exact, bends/twists piecewise linear
    obj = bpy.data.objects.new(name, lat)
    bpy.context.scene.collection.objects.link(obj)
    size = np.maximum(2.0 * half * LATTICE_MARGIN, MIN_EXTENT)
    obj.matrix_world = Matrix.LocRotScale(tuple(center), None, tuple(size))
    obj.hide_render = True
    return obj


def _make_armature(name: str, pose: dict, center, half):
    """Two connected bones along `along` through the bbox, deforming by envelopes that cover the whole box."""
    arm = bpy.data.armatures.new(name)
    obj = bpy.data.objects.new(name, arm)
    bpy.context.scene.collection.objects.link(obj)
    along = pose["along"]
    others = [i for i in range(3) if i != along]
    cross = float(np.linalg.norm(half[others]))
    radius, falloff = 1.05 * cross, 0.25 * max(cross, 1e-3)
    start, joint, end = center.copy(), center.copy(), center.copy()
    start[along] -= half[along]
    end[along] += half[along]
    view_layer = bpy.context.view_layer
    view_layer.objects.active = obj
    bpy.ops.object.mode_set(mode="EDIT")
    bones = []
    for bname, head, tail in (("root", start, joint), ("tip", joint, end)):
        b = arm.edit_bones.new(bname)
        b.head, b.tail = tuple(head), tuple(tail)
        b.head_radius = b.tail_radius = radius
        b.envelope_distance = falloff
        b.envelope_weight = 1.0
        b.use_deform = True
        bones.append(b)
    bones[1].parent = bones[0]
    bones[1].use_connect = True
    bpy.ops.object.mode_set(mode="OBJECT")
    obj.hide_render = True
    return obj


def get_rig(spec: dict, pose: str):
    """The rig object of `pose` in the current scene, created on first use (None for the rest pose)."""
    p = pose_spec(spec, pose)
    if p["type"] == "rest":
        return None
    name = rig_name(pose)
    obj = bpy.data.objects.get(name)
    if obj is not None:
        return obj
    center, half = _bbox(spec)
    obj = _make_armature(name, p, center, half) if p["type"] == "armature" else _make_lattice(name, p, center, half)
    obj["pointgt_pose"] = json.dumps({"name": pose, **p, "bbox": spec["bbox"]})
    obj["pointgt_rest"] = [list(pt.co) for pt in obj.data.points] if obj.type == "LATTICE" else []
    obj["pointgt_magnitude"] = 0.0
    return obj


def set_magnitude(rig, magnitude: float) -> None:
    """Pose the rig at `magnitude` (0 = rest, 1 = the named pose)."""
    if not math.isfinite(magnitude):
        raise InputError(f"magnitude must be finite, got {magnitude}")
    p = json.loads(rig["pointgt_pose"])
    center = np.asarray(p["bbox"]["center"], dtype=np.float64)
    half = np.asarray(p["bbox"]["half_size"], dtype=np.float64)
    if p["type"] == "armature":
        tip = rig.pose.bones["tip"]
        rest = np.array(rig.data.bones["tip"].matrix_local.to_3x3())  # bone frame in armature space
        r_arm = pose_math.rotation_matrix(p["about"], math.radians(p["angle_deg"]) * magnitude)
        tip.rotation_mode = "QUATERNION"
        tip.rotation_quaternion = Matrix((rest.T @ r_arm @ rest).tolist()).to_quaternion()
    else:
        local = np.asarray(rig["pointgt_rest"], dtype=np.float64).reshape(-1, 3)
        mw = np.array(rig.matrix_world)
        world = local @ mw[:3, :3].T + mw[:3, 3]
        moved = pose_math.deform(world, p, center, half, magnitude)
        back = (moved - mw[:3, 3]) @ np.linalg.inv(mw[:3, :3]).T
        for pt, co in zip(rig.data.points, back):
            pt.co_deform = tuple(co)
        rig.data.update_tag()
    rig["pointgt_magnitude"] = float(magnitude)


def _keyframe(rig, frame: int) -> None:
    if rig.type == "ARMATURE":
        rig.pose.bones["tip"].keyframe_insert("rotation_quaternion", frame=frame)
    else:
        for i in range(len(rig.data.points)):
            rig.data.keyframe_insert(f"points[{i}].co_deform", frame=frame)


def apply_pose(obj, scene, pose: str, magnitude: float = 1.0):
    """Add the deformer of `pose` to `obj` (mesh or vertex-only mesh) and set the pose's magnitude.

    scene: scene dir / scene.json / loaded dict. Returns the (shared) rig object, or None for `rest`.
    The modifier is named `pgt_<pose>`; applying twice reuses it.
    """
    spec = load_scene_spec(scene)
    rig = get_rig(spec, pose)
    if rig is None:
        return None
    set_magnitude(rig, magnitude)
    name = f"pgt_{pose}"
    if obj.modifiers.get(name) is None:
        kind = "ARMATURE" if rig.type == "ARMATURE" else "LATTICE"
        mod = obj.modifiers.new(name, kind)
        if mod is None:  # e.g. a PointCloud object: it accepts Geometry Nodes only
            raise InputError(f"object '{obj.name}' ({obj.type}) cannot take a {kind} modifier; use a (vertex-only) mesh")
        mod.object = rig
        if kind == "ARMATURE":
            mod.use_vertex_groups = False  # envelopes only: defined for points without weights
            mod.use_bone_envelopes = True
            mod.use_deform_preserve_volume = False
    return rig


def animate_pose(obj, scene, pose: str, frame_start: int, frame_end: int, magnitude: float = 1.0):
    """Apply `pose` to `obj` and keyframe its magnitude from 0 at frame_start to `magnitude` at frame_end
    (one key per frame, so every frame holds the exactly scaled pose, e.g. a bend of m * 180 degrees)."""
    if frame_end <= frame_start:
        raise InputError(f"frame_end ({frame_end}) must be after frame_start ({frame_start})")
    rig = apply_pose(obj, scene, pose, 0.0)
    if rig is None:
        return None
    for f in range(frame_start, frame_end + 1):
        set_magnitude(rig, magnitude * (f - frame_start) / (frame_end - frame_start))
        _keyframe(rig, f)
    return rig
