"""Run in a fresh bpy subprocess by test_addon_scene.py; prints one JSON line "RESULTS: {...}".

argv after "--": zip model.pgt blank.pgt workdir
The tiny card model seen from above (64 x 48 px). Steps: duplicates (Shift+D, Alt+D) and moves must leave the
atlas bit-identical and give each object its own preview. Each step records what it saw (or the error).
"""
import importlib
import json
import math
import os
import sys
import time

import numpy as np
import bpy
from script_common import (camera_only_scene, centroid, install_addon, make_active, paint_through_uvs,  # noqa: E402
                            read_png, recorder, two_bone_rig)

zip_path, model, blank_model, work = sys.argv[sys.argv.index("--") + 1:]
R = {}
PKG = "bl_ext.user_default.pointgt"
W, H = 64, 48


def mod(name):
    return importlib.import_module(f"{PKG}.{name}")


step = recorder(R)



def raw(image):
    buf = np.empty(image.size[0] * image.size[1] * image.channels, np.float32)
    image.pixels.foreach_get(buf)
    return buf


def settle():
    """What the UI would do between events: the depsgraph update (handlers), then idle time for the preview."""
    bpy.context.view_layer.update()
    prev = mod("operators.preview")
    if hasattr(prev, "run_pending"):
        prev.run_pending()


def obj():
    return bpy.data.objects["card"]


@step("install")
def _():
    return install_addon(zip_path)


@step("scene")
def _():
    scene, _ = camera_only_scene()
    r = scene.render
    r.resolution_x, r.resolution_y, r.resolution_percentage = W, H, 100
    res = bpy.ops.pointgt.import_model(filepath=model, preview_resolution=W)
    bpy.context.active_object.name = "card"
    mod("operators.preview").update_previews(scene, force=True)
    sync_progress = list(mod("operators.preview").S.progress)
    settle()
    return {"import": sorted(res), "preview": obj().pointgt.preview_image.name, "sync_progress": sync_progress}


@step("nonblocking")
def _():
    scene = bpy.context.scene
    prev = mod("operators.preview")
    S = prev.S
    o = obj()
    o.pointgt.preview_resolution = 128  # levels 128x96 <- 64x48
    prev.run_pending()
    S.handler_ms.clear()
    c0 = dict(S.counts)
    # a batch of operator calls, as a script or an artist building a rig: no render until Blender is idle
    bpy.ops.object.armature_add(location=(0.0, 0.0, 0.0))
    arm = bpy.context.active_object
    bpy.ops.object.mode_set(mode='EDIT')
    for i in range(4):
        bpy.ops.armature.bone_primitive_add(name=f"b{i}")
    bpy.ops.object.mode_set(mode='OBJECT')
    make_active(o)
    for f in range(2, 7):
        scene.frame_set(f)
        o.location.y += 0.01
        bpy.context.view_layer.update()
    batch = {k: S.counts[k] - c0[k] for k in ("rendered", "levels", "requests")}
    handler_ms = list(S.handler_ms)
    # idle: slices render coarse-to-fine; the first level is shown before the full one
    slices, statuses, slice_ms = 0, [], []
    while True:
        t0 = time.perf_counter()
        more = prev.run_slice(budget=0.0)
        slice_ms.append((time.perf_counter() - t0) * 1000)
        statuses.append(prev.status(o))
        slices += 1
        if not more:
            break
    idle = {k: S.counts[k] - c0[k] for k in ("rendered", "levels", "jobs")}
    # a change while a job runs cancels it; the preview then shows the new state
    scene.frame_set(1)
    bpy.context.view_layer.update()
    o.location.y = 0.0
    bpy.context.view_layer.update()
    prev.run_slice(budget=0.0)
    prev.run_slice(budget=0.0)
    prev.run_slice(budget=0.0)
    cancelled0 = S.counts["cancelled"]
    o.location.x = 0.05
    bpy.context.view_layer.update()
    prev.run_pending()
    rendered_rgb = S.records["card"].rendered.copy()
    final_state_pos = float(S.records["card"].state.points[:, 0].mean())
    o.location.x = 0.0
    bpy.context.view_layer.update()
    prev.run_pending()
    bpy.data.objects.remove(arm)
    o.pointgt.preview_resolution = W
    prev.run_pending()
    return {"batch": batch, "handler_max_ms": max(handler_ms), "handler_calls": len(handler_ms), "idle": idle,
            "slices": slices, "refining_seen": any("refining" in t for t in statuses),
            "slice_max_ms": max(slice_ms), "cancelled": S.counts["cancelled"] - cancelled0,
            "mean_x_after_move": final_state_pos, "levels": prev.preview_levels(128, 96),
            "final_status": statuses[-1], "level_seen": any("level 1 of 2" in t for t in statuses)}


@step("duplicates")
def _():
    scene = bpy.context.scene
    prev = mod("operators.preview")
    atlas = obj().pointgt.atlas
    before = raw(atlas)
    rendered0 = prev.COUNTS["rendered"]
    bpy.ops.ed.undo_push(message="before duplicating")
    make_active(obj())
    bpy.ops.object.duplicate(linked=False)       # Shift+D
    dup = bpy.context.active_object
    settle()
    make_active(obj())
    bpy.ops.object.duplicate(linked=True)        # Alt+D
    linked = bpy.context.active_object
    settle()
    for i, (o, dx) in enumerate(((dup, 0.3), (linked, -0.3), (dup, 0.2), (obj(), 0.1))):
        o.location.x += dx
        settle()
        scene.frame_set(scene.frame_current + 1)
        settle()
        bpy.ops.ed.undo_push(message=f"move {i}")
    after = raw(atlas)
    objs = [obj(), dup, linked]
    previews = [o.pointgt.preview_image.name if o.pointgt.preview_image else None for o in objs]
    owners = [o.pointgt.preview_image.get("pointgt_owner") if o.pointgt.preview_image else None for o in objs]
    shared = [o.name for o in prev.atlas_users(obj())]
    # Make Atlas Single-User: the duplicate gets its own bit-identical copy, the original's atlas is untouched
    make_active(dup)
    res = bpy.ops.pointgt.single_user_atlas()
    own = dup.pointgt.atlas
    result = {"identical": bool(np.array_equal(before, after)), "max_diff": float(np.abs(before - after).max()),
            "previews": previews, "owners": owners, "names": [o.name for o in objs],
            "renders": prev.COUNTS["rendered"] - rendered0, "transfers": prev.COUNTS["transfers"], "shared": shared,
            "single_user": sorted(res), "own_atlas": own.name, "own_differs": own != atlas,
            "own_identical": bool(np.array_equal(raw(own), after)), "own_packed": own.packed_file is not None,
            "shared_after": [o.name for o in prev.atlas_users(obj())],
            "status": {o.name: prev.status(o) for o in objs}}
    # undo the moves and the duplicates, one step at a time, with the preview updating in between
    atlas_name = atlas.name
    undone = 0
    for _ in range(6):
        try:
            if 'FINISHED' in bpy.ops.ed.undo():
                undone += 1
        except RuntimeError:  # nothing left to undo
            break
        settle()
        bpy.context.scene.frame_set(bpy.context.scene.frame_current)  # undo replaced the scene's Python object
        settle()
    result["undo_steps"] = undone
    result["undo_identical"] = bool(np.array_equal(raw(bpy.data.images[atlas_name]), before))
    result["undo_transfers"] = prev.COUNTS["transfers"]
    result["undo_objects"] = sorted(o.name for o in bpy.data.objects if o.pointgt.is_model)
    return result


def render_still(path, engine='POINTGT'):
    scene = bpy.context.scene
    if engine:
        scene.render.engine = engine
    scene.render.filepath = path
    bpy.ops.render.render(write_still=True)
    return path


@step("warnings")
def _():
    scene = bpy.context.scene
    prev = mod("operators.preview")
    out = {}
    # a model that renders blank warns on import
    bpy.ops.pointgt.import_model(filepath=blank_model, preview_resolution=W)
    blank = bpy.context.active_object
    out["blank_status"] = prev.status(blank)
    if blank.pointgt.proxy is not None:
        bpy.data.objects.remove(blank.pointgt.proxy)
    bpy.data.objects.remove(blank)
    out["good_status"] = prev.status(obj())
    # poses the render cannot show: collapsed, blown up, off-camera (preview status and F12 both say so)
    ng = bpy.data.node_groups.new("scale", 'GeometryNodeTree')
    ng.interface.new_socket("Geometry", in_out='INPUT', socket_type='NodeSocketGeometry')
    ng.interface.new_socket("Geometry", in_out='OUTPUT', socket_type='NodeSocketGeometry')
    gin, gout = ng.nodes.new('NodeGroupInput'), ng.nodes.new('NodeGroupOutput')
    tf = ng.nodes.new('GeometryNodeTransform')
    ng.links.new(gin.outputs[0], tf.inputs[0])
    ng.links.new(tf.outputs[0], gout.inputs[0])
    gn = obj().modifiers.new("scale", 'NODES')
    gn.node_group = ng
    for label, scale in (("collapsed", 1e-6), ("exploded", 1e6)):  # as a bone or lattice scaled by 1e-6 / 1e6
        tf.inputs["Scale"].default_value = (scale, scale, scale)
        settle()
        out[label] = prev.status(obj())
    obj().modifiers.remove(gn)
    obj().location.x = 100.0
    settle()
    out["off_camera"] = prev.status(obj())
    render_still(os.path.join(work, "off.png"))
    out["off_camera_render"] = mod("render.render_engine").LAST.get("warning", "")
    obj().location.x = 0.0
    settle()
    out["back"] = prev.status(obj())
    return out


@step("packed")
def _():
    out = {}
    o = obj()
    text = o.pointgt.packed_model
    out["packed"] = text is not None and isinstance(text.get("pointgt_model"), bytes)
    out["packed_size"] = len(text["pointgt_model"]) if out["packed"] else 0
    for other in [x for x in bpy.data.objects if x.name != "card" and x.pointgt.is_model]:
        bpy.data.objects.remove(other)  # the duplicates of the earlier step
    render_still(os.path.join(work, "before.png"))
    blend = os.path.join(work, "scene.blend")
    bpy.ops.wm.save_as_mainfile(filepath=blend)
    moved = model + ".away"
    os.rename(model, moved)  # the .blend must render without its .pgt (a render farm)
    try:
        bpy.ops.wm.open_mainfile(filepath=blend)
        render_still(os.path.join(work, "after.png"))
        out["error_after"] = mod("render.render_engine").LAST.get("error", "")
    finally:
        os.rename(moved, model)
    # Unpack Model writes the packed bytes out and points the object at the file
    make_active(obj())
    res = bpy.ops.pointgt.unpack_model(filepath=os.path.join(work, "unpacked.pgt"))
    out["unpack"] = sorted(res)
    out["unpacked_same"] = open(os.path.join(work, "unpacked.pgt"), "rb").read() == open(model, "rb").read()
    out["after_unpack"] = {"packed": obj().pointgt.packed_model is not None, "path": obj().pointgt.model_path,
                           "texts": [t.name for t in bpy.data.texts]}
    res = bpy.ops.pointgt.pack_model()
    out["repack"] = sorted(res)
    return out


@step("outlines")
def _():
    """The chart outlines the Image Editor draws over the atlas: which editors get them, and their geometry
    against the model's texel map."""
    out = {}
    o, scene = obj(), bpy.context.scene
    panel, outl = mod("ui.image_panel"), mod("scene.chart_outlines")
    out["draw_handlers"] = len(mod("scene.handlers")._DRAW)
    win = bpy.context.window_manager.windows[0]
    area = win.screen.areas[0]
    old_type = area.type
    area.type = 'IMAGE_EDITOR'
    space = area.spaces.active
    region = next(r for r in area.regions if r.type == 'WINDOW')
    other = bpy.data.images.new("not an atlas", 8, 8)
    try:
        with bpy.context.temp_override(window=win, area=area, region=region):
            space.image = o.pointgt.atlas
            seg = panel.shown_outlines(bpy.context)
            panel.draw_chart_outlines()  # headless the view was never drawn: it returns without drawing
            scene.pointgt.chart_outlines = False
            out["off"] = panel.shown_outlines(bpy.context) is None
            scene.pointgt.chart_outlines = True
            space.image = other
            out["other_image"] = panel.shown_outlines(bpy.context) is None
            space.image = o.pointgt.atlas
            out["cached"] = panel.shown_outlines(bpy.context) is seg
    finally:
        area.type = old_type
        bpy.data.images.remove(other)
    # geometry: every unit edge of every segment separates two different charts (or a chart and no surface); the
    # charts of an island atlas are its islands (the cells its island arrays place), of a grid its chart squares
    path = mod("scene.scene_inputs").model_file(o)
    tex, R, pad = mod("scene.proxy_mesh").read_texel_map(path)
    H, W = tex.shape[:2]
    co = mod("scene.chart_outlines")
    with co.PgtFile(path) as f:
        arrays = {k: f.read(k) for k in co.KEYS if k in f.names}
        out["islands"] = f.meta["atlas"].get("layout") == "islands"
    if out["islands"]:
        lab = co.chart_labels(arrays, (H, W))
    else:
        cell = R + 2 * pad
        rows, cols = np.mgrid[0:H, 0:W]
        lab = np.where(np.isfinite(tex).all(-1), (rows // cell) * (W // cell) + cols // cell, -1)
    at = np.pad(lab, 1, constant_values=-1)  # at[r + 1, c + 1] = lab[r, c]; -1 outside the image
    px = np.stack([seg[..., 0] * W, (1.0 - seg[..., 1]) * H], -1)  # back to pixel corners, y down
    out["on_grid"] = bool(np.abs(px - np.round(px)).max() < 1e-3)
    px = np.round(px).astype(int)
    bad = edges = 0
    seen = set()
    for (x0, y0), (x1, y1) in px.tolist():
        if x0 == x1:  # vertical: pixels (y, x - 1) and (y, x) on either side
            pairs = [((y, x0 - 1), (y, x0)) for y in range(min(y0, y1), max(y0, y1))]
        else:
            pairs = [((y0 - 1, x), (y0, x)) for x in range(min(x0, x1), max(x0, x1))]
        for a, b in pairs:
            la, lb = at[a[0] + 1, a[1] + 1], at[b[0] + 1, b[1] + 1]
            bad += int(la == lb or max(la, lb) < 0)
            edges += 1
            seen |= {int(la), int(lb)}
    # every such unit edge of the texel map is drawn: count them directly
    dv = (at[1:-1, :-1] != at[1:-1, 1:]) & (np.maximum(at[1:-1, :-1], at[1:-1, 1:]) >= 0)
    dh = (at[:-1, 1:-1] != at[1:, 1:-1]) & (np.maximum(at[:-1, 1:-1], at[1:, 1:-1]) >= 0)
    out.update(segments=int(len(seg)), unit_edges=edges, bad=bad, expected_edges=int(dv.sum() + dh.sum()),
               charts=int(len(np.unique(lab[lab >= 0]))), outlined_charts=len(seen - {-1}))
    return out


def project(points):
    c2w, focal = mod("scene.camera").scene_camera(bpy.context.scene, W, H)
    cam = (np.asarray(points) - c2w[:3, 3]) @ c2w[:3, :3]
    return np.stack([focal * cam[:, 0] / -cam[:, 2] + W / 2, -focal * cam[:, 1] / -cam[:, 2] + H / 2], axis=1)


@step("proxy")
def _():
    out = {}
    o = obj()
    proxy = o.pointgt.proxy
    mat = proxy.data.materials[0]
    active = mat.node_tree.nodes.active
    out["faces"] = len(proxy.data.polygons)
    out["triangles"] = all(len(p.vertices) == 3 for p in proxy.data.polygons)
    out["uv"] = proxy.data.uv_layers.active.name if proxy.data.uv_layers.active else ""
    out["material_image"] = active.image.name if getattr(active, "image", None) else ""
    out["atlas"] = o.pointgt.atlas.name
    sd = o.modifiers.get("PointGT Surface Deform")
    out["bound"] = bool(sd and sd.is_bound and sd.target == proxy and o.modifiers[0] == sd)
    # cracks: open edges and pieces of the proxy against the same texel map meshed chart by chart (not closed)
    pm = mod("scene.proxy_mesh")
    tri = np.empty(len(proxy.data.loops), np.int32)
    proxy.data.loops.foreach_get("vertex_index", tri)
    tri = tri.reshape(-1, 3)
    tex, R_, pad_ = pm.read_texel_map(mod("scene.scene_inputs").model_file(o))
    _, raw_tris, _ = pm.proxy_arrays(tex, R_, pad_, stitch=0.0, close=0, fill=0)

    def cracks(t):
        _, counts = pm._edge_counts(t)
        label = pm.mesh_components(int(t.max()) + 1, t)
        return {"open_edges": int((counts == 1).sum()), "pieces": len(np.unique(label[np.unique(t)])),
                "most": int(counts.max())}

    out["cracks"], out["cracks_per_chart"] = cracks(tri), cracks(raw_tris)
    # 3-D paint on the proxy: a red disc on the card's right half, written through the proxy's UV map
    centre = np.array([0.45, 0.15, 0.0])
    out["painted_texels"], out["painted_faces"] = paint_through_uvs(proxy, o.pointgt.atlas, centre, 0.12,
                                                                    (1.0, 0.0, 0.0))
    scene = bpy.context.scene
    r = scene.render
    r.resolution_x, r.resolution_y, r.resolution_percentage = W, H, 100
    scene.view_settings.view_transform = 'Standard'
    scene.frame_set(1)
    rgb = read_png(render_still(os.path.join(work, "proxy_rest.png")))
    out["rest"] = centroid(rgb, (1.0, 0.0, 0.0))
    out["rest_expect"] = project(centre[None])[0].tolist()
    # rig the proxy with Automatic Weights; a 90 degree turn of the right bone poses the neural render
    arm, out["parent"] = two_bone_rig(proxy)
    pb = arm.pose.bones["right"]
    pb.rotation_mode = 'XYZ'

    def turn(p, degrees):  # (x, y) turned about the bone's head (the origin)
        a = math.radians(degrees)
        return np.stack([p[:, 0] * math.cos(a) - p[:, 1] * math.sin(a), p[:, 0] * math.sin(a) + p[:, 1] * math.cos(a),
                         p[:, 2]], 1)

    # 90 degrees: the points follow the proxy's heat weights (right half turned rigidly, left half still)
    pb.rotation_euler = (0.0, 0.0, math.radians(90.0))
    bpy.context.view_layer.update()
    pos, ids = mod("scene.evaluated").evaluated_points(o, bpy.context.evaluated_depsgraph_get())
    rest = np.empty(len(o.data.vertices) * 3, np.float32)
    o.data.vertices.foreach_get("co", rest)
    rest = rest.reshape(-1, 3)[ids]
    right, left = rest[:, 0] > 0.6, rest[:, 0] < -0.6  # away from the joint at x = 0
    out["right_error"] = float(np.linalg.norm(pos[right] - turn(rest[right], 90.0), axis=1).mean())
    out["left_moved"] = float(np.linalg.norm(pos[left] - rest[left], axis=1).mean())
    out["right_moved"] = float(np.linalg.norm(pos[right] - rest[right], axis=1).mean())
    # near the joint the heat weights blend the two bones: points between rest and the full turn
    full = np.linalg.norm(turn(rest, 90.0) - rest, axis=1)
    moved = np.linalg.norm(pos - rest, axis=1)
    share = np.where(full > 1e-3, moved / np.maximum(full, 1e-3), 0.0)
    out["blended"] = int(((share > 0.1) & (share < 0.9)).sum())
    out["points"] = int(len(rest))
    # 90 degrees: the paint follows in the neural render (F12)
    rgb = read_png(render_still(os.path.join(work, "proxy_posed90.png")))
    out["posed90"] = centroid(rgb, (1.0, 0.0, 0.0))
    out["posed90_expect"] = project(turn(centre[None], 90.0))[0].tolist()
    # 45 degrees: the paint follows in the neural render
    pb.rotation_euler = (0.0, 0.0, math.radians(45.0))
    bpy.context.view_layer.update()
    rgb = read_png(render_still(os.path.join(work, "proxy_posed.png")))
    out["posed"] = centroid(rgb, (1.0, 0.0, 0.0))
    out["posed_expect"] = project(turn(centre[None], 45.0))[0].tolist()
    out["error"] = mod("render.render_engine").LAST.get("error", "")
    return out


def diffuse(name, colour):
    mat = bpy.data.materials.new(name)
    mat.use_nodes = True
    bsdf = next(n for n in mat.node_tree.nodes if n.bl_idname == 'ShaderNodeBsdfPrincipled')
    bsdf.inputs["Base Color"].default_value = (*colour, 1.0)
    bsdf.inputs["Roughness"].default_value = 1.0
    return mat


def judge_composite(rgb, alone, neural):
    """Occlusion, the paint's place and the shadow, by pixels, in a composited frame rgb (sRGB, row 0 = top),
    given the scene rendered alone and the PointGT engine's own frame."""
    out = {}
    scene = bpy.context.scene
    layer = mod("render.composite").bpy.data.images["PointGT layer"]
    lay = np.empty(W * H * 4, np.float32)
    layer.pixels.foreach_get(lay)
    lay = lay.reshape(H, W, 4)[::-1]  # straight scene-linear RGBA, row 0 = top
    c2w, focal = mod("scene.camera").scene_camera(scene, W, H)
    rows, cols = np.mgrid[0:H, 0:W] + 0.5
    d = np.stack([(cols - W / 2) / focal, -(rows - H / 2) / focal, -np.ones_like(cols)], -1) @ c2w[:3, :3].T
    eye = c2w[:3, 3]
    card_hit = eye + d * ((0.0 - eye[2]) / d[..., 2])[..., None]
    floor_hit = eye + d * ((-0.6 - eye[2]) / d[..., 2])[..., None]
    on_card = (np.abs(card_hit[..., 0]) < 0.95) & (np.abs(card_hit[..., 1]) < 0.55)
    to_sun = np.array([0.0, math.sin(math.radians(45.0)), math.cos(math.radians(45.0))])
    up = floor_hit + to_sun * (0.6 / to_sun[2])
    # the card's unposed left half shadows these floor pixels; far from any part of the card, the floor is lit
    shadow = (up[..., 0] > -0.8) & (up[..., 0] < -0.05) & (np.abs(up[..., 1]) < 0.4) & ~on_card
    lit = ~on_card & ~((np.abs(up[..., 0]) < 1.0) & (up[..., 1] > -0.6) & (up[..., 1] < 1.3)) \
        & (np.abs(floor_hit[..., 0]) > 0.2)
    lum = rgb.mean(-1)
    out["shadow_px"], out["lit_px"] = int(shadow.sum()), int(lit.sum())
    out["shadow_lum"], out["lit_lum"] = float(lum[shadow].mean()), float(lum[lit].mean())
    # the box hides the card; elsewhere on the card the neural colours show, over the floor
    bc, br = project(np.array([[0.5, 0.1, 0.475]]))[0]
    out["box_px"] = rgb[int(br), int(bc)].tolist()
    out["layer_alpha_at_box"] = float(lay[int(br), int(bc), 3])  # the model is there, behind the box
    out["neural_at_box"] = neural[int(br), int(bc)].tolist()
    # the paint follows the pose in the composited frame (lighter there: the layer's alpha shows some floor)
    reddish = (rgb[..., 0] - rgb[..., 1:].max(-1)) > 0.25
    rr, rc = np.nonzero(reddish)
    out["red"] = [[float(rc.mean() + 0.5), float(rr.mean() + 0.5)] if len(rr) else [float("nan")] * 2, int(len(rr))]
    out["red_expect"] = project(np.array([[0.45 * math.cos(math.pi / 4) - 0.15 * math.sin(math.pi / 4),
                                           0.45 * math.sin(math.pi / 4) + 0.15 * math.cos(math.pi / 4), 0.0]]))[0].tolist()
    bx0, by0 = project(np.array([[0.34, 0.26, 0.475]]))[0]
    bx1, by1 = project(np.array([[0.66, -0.06, 0.475]]))[0]
    away = on_card & ~((cols > bx0 - 2) & (cols < bx1 + 2) & (rows > by0 - 2) & (rows < by1 + 2))
    away &= (card_hit[..., 0] > -0.75) & (card_hit[..., 0] < -0.1) & (np.abs(card_hit[..., 1]) < 0.35)  # left half
    out["card_px"] = int(away.sum())
    ai = mod("scene.atlas_image")
    a = lay[..., 3:4]
    expect = ai.linear_to_srgb(lay[..., :3] * a + ai.srgb_to_linear(alone) * (1.0 - a))  # the layer over the scene
    out["card_diff"] = float(np.abs(rgb[away] - expect[away]).mean())
    out["card_vs_scene_alone"] = float(np.abs(rgb[away] - alone[away]).mean())
    out["card_alpha"] = float(a[away].mean())
    return out


@step("composite")
def _():
    out = {}
    scene = bpy.context.scene
    o = obj()
    arm = next(x for x in bpy.data.objects if x.type == 'ARMATURE')
    # the card's right half stays turned by 45 degrees (proxy step), with the red disc painted through the proxy
    neural = read_png(render_still(os.path.join(work, "neural_only.png")))  # the PointGT engine alone
    bpy.ops.mesh.primitive_plane_add(size=6.0, location=(0.0, 0.0, -0.6))
    floor = bpy.context.active_object
    floor.data.materials.append(diffuse("floor", (0.8, 0.8, 0.8)))
    bpy.ops.mesh.primitive_cube_add(size=0.25, location=(0.5, 0.1, 0.35))
    box = bpy.context.active_object
    box.data.materials.append(diffuse("box", (0.05, 0.8, 0.05)))
    # the sun shines from +y at 45 degrees: the card's shadow falls 0.6 towards -y, partly beside the card
    bpy.ops.object.light_add(type='SUN', location=(0.0, 0.0, 5.0), rotation=(math.radians(-45.0), 0.0, 0.0))
    sun = bpy.context.active_object
    sun.data.energy = 3.0
    sun.data.angle = 0.0
    make_active(o)
    out["setup"] = sorted(bpy.ops.pointgt.setup_composite())
    out["engine"] = scene.render.engine
    scene.cycles.samples = 16
    scene.cycles.use_denoising = False
    scene.view_settings.view_transform = 'Standard'
    rgb = read_png(render_still(os.path.join(work, "composite.png"), engine=None))
    out["layer_progress"] = dict(mod("render.composite").LAST_LAYER)
    scene.render.use_compositing = False  # the scene alone (Cycles), to check the merge against
    alone = read_png(render_still(os.path.join(work, "scene_only.png"), engine=None))
    scene.render.use_compositing = True
    # which pixels see what: rays through pixel centres against the card (z = 0), the floor and the sun
    out.update(judge_composite(rgb, alone, neural))
    return out


@step("composite_eevee")
def _():
    """The same frame with EEVEE rendering the rest of the scene."""
    scene = bpy.context.scene
    out = {}
    neural = read_png(os.path.join(work, "neural_only.png"))
    scene.render.engine = 'BLENDER_EEVEE'
    out["engine"] = scene.render.engine
    t = time.perf_counter()
    rgb = read_png(render_still(os.path.join(work, "composite_eevee.png"), engine=None))
    out["seconds"] = time.perf_counter() - t
    scene.render.use_compositing = False
    alone = read_png(render_still(os.path.join(work, "scene_only_eevee.png"), engine=None))
    scene.render.use_compositing = True
    out.update(judge_composite(rgb, alone, neural))
    return out


with open(os.path.join(work, "results.json"), "w") as fh:  # kept with pytest's temporary folders, to read
    json.dump(R, fh, indent=1)
print("RESULTS: " + json.dumps(R))
