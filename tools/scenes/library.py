"""The built-in scenes: geometry (needs bpy when built), base texture, decal placement and pose list.

Every object is centred at the origin, fits a sphere of radius 0.95 and has an identity object matrix (the
transform is applied to the mesh), so rest-pose world coordinates = mesh coordinates.
"""
from __future__ import annotations

import dataclasses
from typing import Callable

FIT_RADIUS = 0.95


def _poses(along: int, toward: int, squash: int, stretch: int, about: int) -> dict:
    """The pose list every scene shares, with its own axes (0 = x, 1 = y, 2 = z)."""
    return {
        "rest": {"type": "rest"},
        "bend": {"type": "bend", "along": along, "toward": toward, "angle_deg": 180.0},
        "twist": {"type": "twist", "along": along, "angle_deg": 360.0},
        "squash": {"type": "scale", "axis": squash, "factor": 0.05},
        "stretch": {"type": "scale", "axis": stretch, "factor": 5.0},
        "arm": {"type": "armature", "along": along, "about": about, "angle_deg": 90.0},
    }


@dataclasses.dataclass(frozen=True)
class SceneDef:
    name: str
    help: str
    build: Callable  # (bmesh.BMesh) -> None: fills the bmesh with the base geometry (any scale/position)
    texture: str  # base texture in core.edits.procedural
    decal: dict  # default parameters of the `decal` texture: centre/radius/weights in Generated units
    poses: dict
    shape: Callable | None = None  # vertices [V, 3] -> [V, 3] (numpy), applied after `build`


def _build_cloth(bm):
    import bmesh

    bmesh.ops.create_grid(bm, x_segments=96, y_segments=36, size=1.0)


def _shape_cloth(co):
    """A strip 2.5 : 1 with a gentle wave along its length (and a slight one across)."""
    import numpy as np

    x, y = co[:, 0], co[:, 1] * 0.4
    return np.stack([x, y, 0.08 * np.sin(1.5 * np.pi * x) + 0.03 * np.sin(np.pi * y / 0.4)], axis=1)


def _build_suzanne(bm):
    import bmesh

    bmesh.ops.create_monkey(bm)
    for _ in range(2):  # two smooth subdivisions: an organic, dense surface that bends smoothly
        bmesh.ops.subdivide_edges(bm, edges=bm.edges[:], cuts=1, use_grid_fill=True, smooth=1.0)
    bmesh.ops.triangulate(bm, faces=bm.faces[:])


def _build_crate(bm):
    import bmesh

    bmesh.ops.create_cube(bm, size=1.0)
    bmesh.ops.subdivide_edges(bm, edges=bm.edges[:], cuts=23, use_grid_fill=True)


def _shape_crate(co):
    return co * (1.5, 1.0, 1.0)  # a crate 1.5 : 1 : 1, long along x


SCENES: dict[str, SceneDef] = {s.name: s for s in [
    SceneDef("cloth", "thin double-sided cloth strip with a gentle wave (the paper's cloth case)", _build_cloth,
             "flag", {"center": (0.7, 0.5, 0.5), "radius": 0.18, "weights": (1.0, 1.0, 0.0)},
             _poses(along=0, toward=2, squash=2, stretch=0, about=1), _shape_cloth),
    SceneDef("suzanne", "subdivided Suzanne: an organic, character-like shape", _build_suzanne,
             "tiger", {"center": (0.5, 0.0, 0.6), "radius": 0.25, "weights": (1.0, 1.0, 1.0)},
             _poses(along=2, toward=1, squash=2, stretch=2, about=0)),
    SceneDef("crate", "rigid box with a fine procedural wood pattern (texture detail case)", _build_crate,
             "planks", {"center": (0.5, 0.0, 0.5), "radius": 0.3, "weights": (1.0, 1.0, 1.0)},
             _poses(along=0, toward=2, squash=2, stretch=0, about=1), _shape_crate),
]}
DEFAULT_SCENE = "cloth"


def scene_names() -> list[str]:
    """Scene names, the default first."""
    return [DEFAULT_SCENE] + [n for n in SCENES if n != DEFAULT_SCENE]


def build_object(sdef: SceneDef, name: str = "object"):
    """Create the scene's mesh object in the current Blender scene: centred, fit to FIT_RADIUS, identity matrix."""
    import bmesh
    import bpy
    import numpy as np

    bm = bmesh.new()
    sdef.build(bm)
    me = bpy.data.meshes.new(name)
    bm.to_mesh(me)
    bm.free()
    co = np.empty(len(me.vertices) * 3, dtype=np.float64)
    me.vertices.foreach_get("co", co)
    co = co.reshape(-1, 3)
    if sdef.shape is not None:
        co = np.asarray(sdef.shape(co), dtype=np.float64)
    co -= 0.5 * (co.min(0) + co.max(0))
    co *= FIT_RADIUS / np.linalg.norm(co, axis=1).max()
    me.vertices.foreach_set("co", co.ravel())
    me.update()
    obj = bpy.data.objects.new(name, me)
    bpy.context.scene.collection.objects.link(obj)
    if hasattr(me, "shade_smooth"):
        me.shade_smooth()
    return obj
