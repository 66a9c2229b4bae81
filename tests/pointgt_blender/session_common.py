"""What the headless Blender session scripts share (each runs as its own process with this folder on sys.path):
steps whose result or traceback is recorded for the test to assert on, selecting objects, painting through a
proxy's UV map and reading rendered frames."""
import traceback

import bpy
import numpy as np


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


def make_active(obj, *others):
    """Select obj and others, obj active."""
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
