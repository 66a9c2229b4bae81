"""What the headless Blender scripts share (each runs as its own process with this folder on sys.path):
blocking torch as a Blender without PyTorch would, steps whose result or traceback is recorded for the test to
assert on, an empty scene with its camera above the card, selecting objects, painting through a proxy's UV map and
reading rendered frames. bpy is imported only inside the functions, so a script can block torch before anything
imports bpy."""
import sys
import traceback

import numpy as np


class TorchBlocker:
    """Makes `import torch` fail as it would in a Blender without PyTorch."""

    def find_spec(self, name, path=None, target=None):
        if name == "torch" or name.startswith("torch."):
            raise ImportError(f"No module named '{name}' (blocked by the test)")
        return None


def block_torch() -> TorchBlocker:
    """Block torch from now on; `sys.meta_path.remove(blocker)` lifts it."""
    blocker = TorchBlocker()
    sys.meta_path.insert(0, blocker)
    return blocker


def recorder(results: dict, trace_chars: int = 2000):
    """A `@step(name)` decorator that runs the function at once and stores its result, or the error and the end
    of its traceback, in results[name]."""
    def step(name):
        def deco(fn):
            try:
                results[name] = fn()
            except Exception as exc:  # recorded, the test asserts on it
                results[name] = {"error": f"{type(exc).__name__}: {exc}",
                                 "trace": traceback.format_exc()[-trace_chars:]}
            return fn
        return deco
    return step


def camera_only_scene():
    """Every object but the cameras removed, the scene camera 3 units above the origin looking down −Z (at the
    card in the plane z = 0). Returns (scene, camera)."""
    import bpy

    scene = bpy.context.scene
    for o in list(bpy.data.objects):
        if o.type != 'CAMERA':
            bpy.data.objects.remove(o)
    cam = scene.camera
    cam.location = (0.0, 0.0, 3.0)
    cam.rotation_euler = (0.0, 0.0, 0.0)
    return scene, cam


def drop_ids_modifier(obj, distance: float):
    """Add a Geometry Nodes modifier that removes the pointgt_id attribute and merges points closer than
    `distance`: the point count changes and the ids are gone, as a careless node setup would leave them."""
    import bpy

    ng = bpy.data.node_groups.new("drop ids", 'GeometryNodeTree')
    ng.interface.new_socket("Geometry", in_out='INPUT', socket_type='NodeSocketGeometry')
    ng.interface.new_socket("Geometry", in_out='OUTPUT', socket_type='NodeSocketGeometry')
    gin, gout = ng.nodes.new('NodeGroupInput'), ng.nodes.new('NodeGroupOutput')
    remove = ng.nodes.new('GeometryNodeRemoveAttribute')
    remove.inputs["Name"].default_value = "pointgt_id"
    merge = ng.nodes.new('GeometryNodeMergeByDistance')
    merge.inputs["Distance"].default_value = distance
    ng.links.new(gin.outputs[0], remove.inputs[0])
    ng.links.new(remove.outputs[0], merge.inputs[0])
    ng.links.new(merge.outputs[0], gout.inputs[0])
    mod = obj.modifiers.new("drop", 'NODES')
    mod.node_group = ng
    return mod


def make_active(obj, *others):
    """Select obj and others, obj active."""
    import bpy

    for o in bpy.context.view_layer.objects:
        o.select_set(False)
    for o in (obj, *others):
        o.select_set(True)
    bpy.context.view_layer.objects.active = obj


def paint_through_uvs(proxy, image, centre, radius, colour):
    """What Texture Paint on the proxy does: the texels inside the UV triangles of the proxy faces whose centre
    lies within `radius` of `centre` (object space) get `colour` (linear RGB). Returns (texels painted, faces)."""
    m = proxy.data
    co = np.empty(len(m.vertices) * 3, np.float32)
    m.vertices.foreach_get("co", co)
    co = co.reshape(-1, 3)
    vi = np.empty(len(m.loops), np.int32)
    m.loops.foreach_get("vertex_index", vi)
    uv = np.empty(len(m.loops) * 2, np.float32)
    m.uv_layers["PointGT atlas"].data.foreach_get("uv", uv)
    tri_v, tri_uv = vi.reshape(-1, 3), uv.reshape(-1, 3, 2)
    pick = np.linalg.norm(co[tri_v].mean(1) - np.asarray(centre), axis=1) < radius
    w, h = image.size
    px = np.empty(w * h * 4, np.float32)
    image.pixels.foreach_get(px)
    px = px.reshape(h, w, 4)
    yy, xx = np.mgrid[0:h, 0:w]
    centres = np.stack([(xx + 0.5) / w, (yy + 0.5) / h], -1).reshape(-1, 2)  # Blender rows: 0 = bottom
    hit = np.zeros(h * w, bool)
    for t in tri_uv[pick]:
        a, b, c = t
        m2 = np.array([b - a, c - a]).T
        if abs(np.linalg.det(m2)) < 1e-12:
            continue
        lam = np.linalg.solve(m2, (centres - a).T).T
        hit |= (lam >= -1e-6).all(1) & (lam.sum(1) <= 1 + 1e-6)
    px.reshape(-1, 4)[hit, :3] = colour
    image.pixels.foreach_set(px.reshape(-1))
    image.update()
    return int(hit.sum()), int(pick.sum())


def read_png(path):
    """The RGB of an image file as float [H, W, 3], row 0 = top."""
    import bpy

    img = bpy.data.images.load(path)
    w, h = img.size
    buf = np.empty(w * h * img.channels, np.float32)
    img.pixels.foreach_get(buf)
    bpy.data.images.remove(img)
    return buf.reshape(h, w, -1)[::-1, :, :3]  # row 0 = top


def centroid(rgb, colour):
    near = np.linalg.norm(rgb - np.asarray(colour, np.float32), axis=-1) < 0.45
    rows, cols = np.nonzero(near)
    if not len(rows):
        return [float("nan"), float("nan")], 0
    return [float(cols.mean() + 0.5), float(rows.mean() + 0.5)], int(near.sum())


def two_bone_rig(proxy):
    """An armature along the card's x axis — bone "left" from x = −0.9 to the origin, "right" from the origin to
    x = 0.9, connected — parented to `proxy` with Automatic Weights. Returns (armature, parent_set's result)."""
    import bpy

    bpy.ops.object.armature_add(location=(0.0, 0.0, 0.0))
    arm = bpy.context.active_object
    bpy.ops.object.mode_set(mode='EDIT')
    left = arm.data.edit_bones[0]
    left.head, left.tail, left.name = (-0.9, 0.0, 0.0), (0.0, 0.0, 0.0), "left"
    right = arm.data.edit_bones.new("right")
    right.head, right.tail, right.parent, right.use_connect = (0.0, 0.0, 0.0), (0.9, 0.0, 0.0), left, True
    bpy.ops.object.mode_set(mode='OBJECT')
    make_active(arm, proxy)
    return arm, sorted(bpy.ops.object.parent_set(type='ARMATURE_AUTO'))


def install_addon(zip_path: str) -> dict:
    """Install and enable the packaged add-on from its zip (the user_default repository)."""
    import bpy

    res = bpy.ops.extensions.package_install_files(filepath=zip_path, repo="user_default", enable_on_install=True)
    return {"result": sorted(res)}
