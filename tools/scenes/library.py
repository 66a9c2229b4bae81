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
    lit: bool = False  # the library's variant is lit (view-dependent shading); `make-scene --lit` forces it


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


def _build_strip(bm):
    import bmesh

    bmesh.ops.create_grid(bm, x_segments=120, y_segments=24, size=1.0)


def _shape_strip(co):
    """A thin strip 4 : 1 with two full waves along its length and a slight twist."""
    import numpy as np

    x, y = co[:, 0], co[:, 1] * 0.25
    ang = 0.35 * x
    z = 0.18 * np.sin(2.0 * np.pi * x)
    return np.stack([x, y * np.cos(ang), z + y * np.sin(ang)], axis=1)


def _subdivide_along(bm, axis: int, cuts: int):
    """Cut every edge that runs along `axis` into cuts + 1 pieces (long side faces bend smoothly under a rig)."""
    import bmesh

    edges = [e for e in bm.edges if abs(e.verts[0].co[axis] - e.verts[1].co[axis]) > 1e-6]
    bmesh.ops.subdivide_edges(bm, edges=edges, cuts=cuts, use_grid_fill=True)


def _build_tube(bm):
    import bmesh

    bmesh.ops.create_cone(bm, cap_ends=True, cap_tris=False, segments=48, radius1=0.35, radius2=0.35, depth=2.0)
    _subdivide_along(bm, 2, 40)
    bmesh.ops.triangulate(bm, faces=[f for f in bm.faces if len(f.verts) > 4])


def _build_blob(bm):
    import bmesh

    bmesh.ops.create_icosphere(bm, subdivisions=5, radius=1.0)


def _shape_blob(co):
    """A lumpy, slightly elongated blob: a sphere pushed in and out by smooth bumps."""
    import numpy as np

    u = co / np.linalg.norm(co, axis=1, keepdims=True)
    bump = 0.18 * np.sin(3.0 * u[:, 0] + 1.0) * np.sin(2.0 * u[:, 1]) + 0.12 * np.sin(4.0 * u[:, 2] + 0.5)
    return u * (1.0 + bump)[:, None] * np.array([1.25, 1.0, 0.9])


def _star_outline(n=5, outer=1.0, inner=0.45):
    import math

    return [((outer if i % 2 == 0 else inner) * math.cos(math.pi * i / n + math.pi / 2),
             (outer if i % 2 == 0 else inner) * math.sin(math.pi * i / n + math.pi / 2)) for i in range(2 * n)]


def _inside(pt, poly) -> bool:
    x, y = pt
    inside = False
    for (x0, y0), (x1, y1) in zip(poly, poly[1:] + poly[:1]):
        if (y0 > y) != (y1 > y) and x < x0 + (y - y0) * (x1 - x0) / (y1 - y0):
            inside = not inside
    return inside


def _build_logo(bm):
    """An extruded five-pointed star (a logo shape): a dense grid cut to the outline, extruded to a slab."""
    import bmesh

    bmesh.ops.create_grid(bm, x_segments=64, y_segments=64, size=1.0)
    star = _star_outline()
    outside = [f for f in bm.faces if not _inside(tuple(f.calc_center_median())[:2], star)]
    bmesh.ops.delete(bm, geom=outside, context="FACES")
    ret = bmesh.ops.extrude_face_region(bm, geom=bm.faces[:])
    verts = [v for v in ret["geom"] if isinstance(v, bmesh.types.BMVert)]
    bmesh.ops.translate(bm, vec=(0.0, 0.0, 0.28), verts=verts)
    bmesh.ops.recalc_face_normals(bm, faces=bm.faces[:])


def _build_ring(bm):
    import bmesh
    import math

    # a torus from a swept circle: major radius 1, minor 0.3, 64 x 20 quads
    rows, cols, big, small = 64, 20, 1.0, 0.3
    grid = []
    for i in range(rows):
        a = 2 * math.pi * i / rows
        ring = []
        for j in range(cols):
            b = 2 * math.pi * j / cols
            r = big + small * math.cos(b)
            ring.append(bm.verts.new((r * math.cos(a), r * math.sin(a), small * math.sin(b))))
        grid.append(ring)
    for i in range(rows):
        for j in range(cols):
            bm.faces.new((grid[i][j], grid[(i + 1) % rows][j], grid[(i + 1) % rows][(j + 1) % cols],
                          grid[i][(j + 1) % cols]))


def _box(bm, centre, size, cuts):
    import bmesh

    ret = bmesh.ops.create_cube(bm, size=1.0)
    verts = ret["verts"]
    bmesh.ops.scale(bm, vec=size, verts=verts)
    bmesh.ops.translate(bm, vec=centre, verts=verts)
    edges = list({e for v in verts for e in v.link_edges})
    bmesh.ops.subdivide_edges(bm, edges=edges, cuts=cuts, use_grid_fill=True)


def _build_table(bm):
    """A table: a top slab and four separate legs (a many-part, concave object)."""
    _box(bm, (0.0, 0.0, 0.8), (2.0, 1.2, 0.12), 12)
    for x in (-0.85, 0.85):
        for y in (-0.5, 0.5):
            _box(bm, (x, y, 0.0), (0.12, 0.12, 1.5), 8)


def _build_stick(bm):
    """A thin stick with a knob at one end (thin-stick case): 1.9 long, 0.05 thick."""
    import bmesh

    bmesh.ops.create_cone(bm, cap_ends=True, cap_tris=False, segments=16, radius1=0.05, radius2=0.05, depth=1.9)
    _subdivide_along(bm, 2, 60)
    bmesh.ops.triangulate(bm, faces=[f for f in bm.faces if len(f.verts) > 4])
    ret = bmesh.ops.create_uvsphere(bm, u_segments=24, v_segments=12, radius=0.16)
    bmesh.ops.translate(bm, vec=(0.0, 0.0, 0.95), verts=ret["verts"])


def _build_paper(bm):
    import bmesh

    bmesh.ops.create_grid(bm, x_segments=64, y_segments=80, size=1.0)


def _shape_paper(co):
    """A sheet of paper 0.8 : 1, curled along its length."""
    import numpy as np

    x, y = co[:, 0] * 0.8, co[:, 1]
    return np.stack([x, y, 0.25 * (y ** 2) + 0.05 * np.sin(2.0 * x)], axis=1)


def _build_puck(bm):
    import bmesh

    bmesh.ops.create_cone(bm, cap_ends=True, cap_tris=False, segments=64, radius1=1.0, radius2=1.0, depth=0.7)
    _subdivide_along(bm, 2, 10)
    bmesh.ops.triangulate(bm, faces=[f for f in bm.faces if len(f.verts) > 4])
    bmesh.ops.subdivide_edges(bm, edges=bm.edges[:], cuts=1, use_grid_fill=True)


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
    SceneDef("strip", "thin wavy, slightly twisted strip with a rich multi-colour texture (cells, bricks, noise)",
             _build_strip, "multi", {"center": (0.3, 0.5, 0.5), "radius": 0.15, "weights": (1.0, 1.0, 0.0)},
             _poses(along=0, toward=2, squash=2, stretch=0, about=1), _shape_strip),
    SceneDef("tube", "closed tube (capped cylinder) with a smooth colour gradient", _build_tube, "gradient",
             {"center": (0.5, 0.0, 0.6), "radius": 0.2, "weights": (1.0, 0.0, 1.0)},
             _poses(along=2, toward=0, squash=0, stretch=2, about=1)),
    SceneDef("blob", "lumpy closed blob with high-frequency noise, lit (view-dependent shading)", _build_blob,
             "noise", {"center": (0.5, 0.0, 0.5), "radius": 0.25, "weights": (1.0, 0.0, 1.0)},
             _poses(along=0, toward=2, squash=2, stretch=0, about=1), _shape_blob, lit=True),
    SceneDef("logo", "extruded five-pointed star (a logo slab) with Voronoi cells", _build_logo, "cells",
             {"center": (0.5, 0.6, 1.0), "radius": 0.2, "weights": (1.0, 1.0, 0.0)},
             _poses(along=1, toward=2, squash=2, stretch=1, about=0)),
    SceneDef("ring", "torus (a concave ring) with running-bond bricks, lit", _build_ring, "bricks",
             {"center": (1.0, 0.5, 0.5), "radius": 0.25, "weights": (1.0, 1.0, 0.0)},
             _poses(along=0, toward=2, squash=2, stretch=0, about=1), lit=True),
    SceneDef("table", "table top on four separate legs (many parts, concave) in flat colours", _build_table, "flat",
             {"center": (0.5, 0.5, 1.0), "radius": 0.2, "weights": (1.0, 1.0, 0.0)},
             _poses(along=0, toward=2, squash=2, stretch=0, about=1)),
    SceneDef("stick", "thin stick with a knob, fine dark lines across it", _build_stick, "fine_lines",
             {"center": (0.5, 0.5, 0.3), "radius": 0.15, "weights": (0.0, 0.0, 1.0)},
             _poses(along=2, toward=0, squash=0, stretch=2, about=1)),
    SceneDef("paper", "curled sheet of near-white paper with small text (near-white on white)", _build_paper,
             "small_text", {"center": (0.5, 0.3, 0.5), "radius": 0.15, "weights": (1.0, 1.0, 0.0)},
             _poses(along=1, toward=2, squash=2, stretch=1, about=0), _shape_paper),
    SceneDef("puck", "short closed cylinder in near-black rubber with dark ribs", _build_puck, "near_black",
             {"center": (0.5, 0.5, 1.0), "radius": 0.25, "weights": (1.0, 1.0, 0.0)},
             _poses(along=0, toward=2, squash=2, stretch=0, about=1)),
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
