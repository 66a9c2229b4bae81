"""Run in a fresh bpy subprocess by test_addon_pose90.py; prints one JSON line "RESULTS: {...}".

argv after "--": zip model.pgt workdir
The issue's scripted run at 90 degrees: import the tiny card (surface proxy, points bound to it by Surface
Deform), Automatic Weights on the proxy for a two-bone armature along the card, a red disc painted through the
proxy's UV map, then the right bone turned 0 / 45 / 90 degrees and rendered (F12, PointGT engine). For each angle:
where the disc lands in the frame against where the deformed proxy says it should be, and the pieces of the chain
on the add-on's side measured on their own (points against the deformed proxy surface; the correspondences).
"""
import importlib
import json
import math
import os
import sys

import numpy as np
import bpy
from script_common import (install_addon, paint_through_uvs, read_png, recorder,  # noqa: E402
                            two_bone_rig)

zip_path, model, work = sys.argv[sys.argv.index("--") + 1:]
R = {}
PKG = "bl_ext.user_default.pointgt"
W, H = 128, 96
# painted discs: (centre, radius, linear colour): one on the turning half, one next to the joint where the heat
# weights blend the two bones
SPOTS = {"far": (np.array([0.45, 0.15, 0.0]), 0.12, (1.0, 0.0, 0.0)),
         "joint": (np.array([0.15, -0.22, 0.0]), 0.1, (0.0, 1.0, 0.0))}
step = recorder(R)
REST = {}  # (correspondence, spot) -> drift at rest (px)


def mod(name):
    return importlib.import_module(f"{PKG}.{name}")


def obj():
    return bpy.data.objects["card"]


def project(points):
    c2w, focal = mod("scene.camera").scene_camera(bpy.context.scene, W, H)
    cam = (np.asarray(points) - c2w[:3, 3]) @ c2w[:3, :3]
    return np.stack([focal * cam[:, 0] / -cam[:, 2] + W / 2, -focal * cam[:, 1] / -cam[:, 2] + H / 2], axis=1)


def units_per_px():
    """World units per pixel on the card's plane (z = 0) for the camera straight above it."""
    c2w, focal = mod("scene.camera").scene_camera(bpy.context.scene, W, H)
    return float(c2w[2, 3] / focal)


def mesh_arrays(mesh):
    co = np.empty(len(mesh.vertices) * 3, np.float32)
    mesh.vertices.foreach_get("co", co)
    vi = np.empty(len(mesh.loops), np.int32)
    mesh.loops.foreach_get("vertex_index", vi)
    return co.reshape(-1, 3).astype(np.float64), vi.reshape(-1, 3)


def closest_on_triangles(p, tri):
    """Closest point of each point p [N, 3] on triangles tri [F, 3, 3]: (face [N], barycentric [N, 3], offset
    along the face normal [N]). Brute force over all faces, by projecting onto each plane and clamping via a
    dense barycentric search (the card is nearly flat; exactness to ~1e-3 is enough here)."""
    a, b, c = tri[:, 0], tri[:, 1], tri[:, 2]
    n = np.cross(b - a, c - a)
    n /= np.maximum(np.linalg.norm(n, axis=1, keepdims=True), 1e-12)
    best = (np.full(len(p), np.inf), np.zeros(len(p), int), np.zeros((len(p), 3)), np.zeros(len(p)))
    v0, v1 = b - a, c - a
    d00, d01, d11 = (v0 * v0).sum(1), (v0 * v1).sum(1), (v1 * v1).sum(1)
    den = np.maximum(d00 * d11 - d01 * d01, 1e-20)
    for i, q in enumerate(p):
        v2 = q - a
        d20, d21 = (v2 * v0).sum(1), (v2 * v1).sum(1)
        v = np.clip((d11 * d20 - d01 * d21) / den, 0, 1)
        w = np.clip((d00 * d21 - d01 * d20) / den, 0, 1)
        s = np.maximum(v + w, 1.0)
        v, w = v / s, w / s
        foot = a + v[:, None] * v0 + w[:, None] * v1
        dist = np.linalg.norm(q - foot, axis=1)
        f = int(dist.argmin())
        best[0][i], best[1][i] = dist[f], f
        best[2][i] = (1 - v[f] - w[f], v[f], w[f])
        best[3][i] = float((q - foot[f]) @ n[f])
    return best[1], best[2], best[3]


@step("install")
def _():
    return install_addon(zip_path)


@step("setup")
def _():
    out = {}
    scene = bpy.context.scene
    for o in list(bpy.data.objects):
        if o.type != 'CAMERA':
            bpy.data.objects.remove(o)
    cam = scene.camera
    cam.location, cam.rotation_euler = (0.0, 0.0, 3.0), (0.0, 0.0, 0.0)
    r = scene.render
    r.resolution_x, r.resolution_y, r.resolution_percentage = W, H, 100
    scene.view_settings.view_transform = 'Standard'
    scene.pointgt.live_preview = False  # this script measures F12 only
    out["import"] = sorted(bpy.ops.pointgt.import_model(filepath=model, preview_resolution=W))
    bpy.context.active_object.name = "card"
    proxy = obj().pointgt.proxy
    for name, (centre, radius, colour) in SPOTS.items():
        out[name] = paint_through_uvs(proxy, obj().pointgt.atlas, centre, radius, colour)
    arm, out["parent"] = two_bone_rig(proxy)
    out["units_per_px"] = units_per_px()
    return out


def centroid(rgb, colour, margin=0.2):
    """Centroid (x, y) in pixels and count of the pixels where the paint's channel stands out (exceeds the
    others by `margin`): the painted disc, also where the render blends it with the card's colour."""
    k = int(np.argmax(colour))
    others = [i for i in range(3) if i != k]
    rows, cols = np.nonzero(rgb[..., k] - rgb[..., others].max(-1) > margin)
    if not len(rows):
        return [float("nan"), float("nan")], 0
    return [float(cols.mean() + 0.5), float(rows.mean() + 0.5)], int(len(rows))


def painted_faces(proxy, centre, radius):
    co, tri = mesh_arrays(proxy.data)
    return np.linalg.norm(co[tri].mean(1) - centre, axis=1) < radius


def measure(angle):
    """Render at `angle` degrees and measure the disc; the add-on's part of the chain on its own."""
    out = {}
    scene = bpy.context.scene
    o, proxy = obj(), obj().pointgt.proxy
    arm = next(x for x in bpy.data.objects if x.type == 'ARMATURE')
    pb = arm.pose.bones["right"]
    pb.rotation_mode = 'XYZ'
    pb.rotation_euler = (0.0, 0.0, math.radians(angle))
    bpy.context.view_layer.update()
    dg = bpy.context.evaluated_depsgraph_get()
    # where the proxy says the paint is: the centroid of its painted faces, deformed (area-weighted)
    rest_co, tri = mesh_arrays(proxy.data)
    ev = proxy.evaluated_get(dg)
    mw = np.array(proxy.matrix_world)
    pose_co = np.empty(len(ev.data.vertices) * 3, np.float32)
    ev.data.vertices.foreach_get("co", pose_co)
    pose_co = pose_co.reshape(-1, 3).astype(np.float64) @ mw[:3, :3].T + mw[:3, 3]
    for name, (centre, radius, colour) in SPOTS.items():
        t = pose_co[tri[painted_faces(proxy, centre, radius)]]
        area = 0.5 * np.linalg.norm(np.cross(t[:, 1] - t[:, 0], t[:, 2] - t[:, 0]), axis=1)
        expect3 = (t.mean(1) * area[:, None]).sum(0) / area.sum()
        out[name] = {"expect_xy": expect3[:2].tolist(), "expect_px": project(expect3[None])[0].tolist()}
    # the points against the deformed proxy: each point's place on the rest proxy (face, barycentric, offset
    # along the normal) carried to the posed proxy, against where Surface Deform put it (points near the paint)
    pos, ids = mod("scene.evaluated").evaluated_points(o, dg)
    rest = np.empty(len(o.data.vertices) * 3, np.float32)
    o.data.vertices.foreach_get("co", rest)
    rest = rest.reshape(-1, 3).astype(np.float64)[ids]
    near = np.zeros(len(rest), bool)
    for centre, radius, _ in SPOTS.values():
        near |= np.linalg.norm(rest - centre, axis=1) < 2 * radius
    f, bary, off = closest_on_triangles(rest[near], rest_co[tri])
    pt = pose_co[tri[f]]
    n = np.cross(pt[:, 1] - pt[:, 0], pt[:, 2] - pt[:, 0])
    n /= np.maximum(np.linalg.norm(n, axis=1, keepdims=True), 1e-12)
    carried = (pt * bary[..., None]).sum(1) + off[:, None] * n
    out["points_vs_proxy"] = float(np.linalg.norm(np.asarray(pos, np.float64)[near] - carried, axis=1).mean())
    out["points_near"] = int(near.sum())
    # F12 with each correspondence
    for corr in ('DEFORM_AWARE', 'DEFORM_GRADIENT', 'NAIVE'):
        o.pointgt.correspondence = corr
        scene.render.engine = 'POINTGT'
        path = os.path.join(work, f"pose{angle:g}_{corr.lower()}.png")
        scene.render.filepath = path
        bpy.ops.render.render(write_still=True)
        rgb = read_png(path)
        last = mod("render.render_engine").LAST
        out[corr] = {"error": last.get("error", ""), "progress": list(last.get("progress", []))}
        for name, (centre, radius, colour) in SPOTS.items():
            c, npx = centroid(rgb, colour)
            e = out[name]["expect_px"]
            drift_px = float(np.hypot(c[0] - e[0], c[1] - e[1]))
            res = {"centroid": c, "pixels": npx, "drift_px": drift_px, "drift_units": drift_px * units_per_px()}
            # the rest pose is measured first: how much the pose adds to the drift the render has at rest
            res["added_px"] = drift_px - REST.setdefault((corr, name), drift_px)
            out[corr][name] = res
    o.pointgt.correspondence = 'DEFORM_AWARE'
    return out


for ang in (0, 45, 90):
    step(f"pose{ang}")(lambda ang=ang: measure(ang))

with open(os.path.join(work, "results.json"), "w") as fh:
    json.dump(R, fh, indent=1)
print("RESULTS: " + json.dumps(R))
