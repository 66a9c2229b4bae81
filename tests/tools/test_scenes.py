"""`pointgt make-scene`: list, NeRF-synthetic layout, RGBA PNGs, pose variants, errors, shared pose rigs."""
import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from PIL import Image

from tools.scenes import cameras, pose_math

CLI = [sys.executable, "-m", "tools.cli", "make-scene"]


def _run(*args, check=True):
    res = subprocess.run(CLI + [str(a) for a in args], capture_output=True, text=True, timeout=300)
    if check:
        assert res.returncode == 0, res.stderr[-2000:] + res.stdout[-2000:]
    return res


def test_list_prints_scene_names_default_first():
    res = _run("--list")
    names = [line.split()[0] for line in res.stdout.splitlines()]
    assert names[0] == "cloth" and {"suzanne", "crate", "strip", "tube", "paper", "stick"} <= set(names)
    assert len(names) >= 10


def test_camera_sets_are_distinct_and_look_at_the_centre():
    a = cameras.split_cameras("train", 10, seed=0)
    b = cameras.split_cameras("test", 10, seed=0)
    assert a.shape == (10, 4, 4) and not np.allclose(a, b)
    assert np.allclose(np.linalg.norm(a[:, :3, 3], axis=1), 4.0)
    fwd = -a[:, :3, 2]  # the camera looks down -Z: forward points at the origin
    assert np.allclose(fwd, -a[:, :3, 3] / 4.0, atol=1e-9)
    dirs = cameras.sphere_directions(200, 3)
    assert dirs[:, 2].min() < -0.9 and dirs[:, 2].max() > 0.9  # the full sphere, both poles


def test_pose_maps_bend_twist_scale():
    pts = np.array([[-1.0, 0.0, 0.0], [0.0, 0.0, 0.0], [1.0, 0.0, 0.0]])
    c, h = np.zeros(3), np.array([1.0, 0.5, 0.1])
    b = pose_math.bend(pts, c, h, along=0, toward=2, angle_deg=180.0, m=1.0)
    # a half circle of length 2 (radius 2 / pi): the ends at x = -+R, z = R, their tangents opposite
    r = 2 / np.pi
    assert np.allclose(b[[0, 2]], [[-r, 0, r], [r, 0, r]], atol=1e-12)
    assert np.allclose(pose_math.bend(pts, c, h, 0, 2, 180.0, 0.0), pts)
    t = pose_math.twist(np.array([[1.0, 0.3, 0.0]]), c, h, along=0, angle_deg=360.0, m=1.0)
    assert np.allclose(t, [[1.0, -0.3, 0.0]], atol=1e-12)  # +180 degrees at the end
    s = pose_math.scale(np.array([[0.0, 0.0, 1.0]]), c, axis=2, factor=0.05, m=1.0)
    assert np.allclose(s, [[0, 0, 0.05]])


@pytest.fixture(scope="module")
def scene_dir(tmp_path_factory):
    out = tmp_path_factory.mktemp("scene") / "cloth"
    _run("cloth", "--out", out, "--size", 24, "--views-train", 3, "--views-val", 1, "--views-test", 2,
         "--samples", 2)
    return out


@pytest.mark.blender
def test_layout_json_and_rgba_pngs(scene_dir):
    for f in ("scene.json", "scene.blend", "transforms_train.json", "transforms_val.json", "transforms_test.json"):
        assert (scene_dir / f).exists(), f
    counts = {"train": 3, "val": 1, "test": 2}
    for split, n in counts.items():
        doc = json.loads((scene_dir / f"transforms_{split}.json").read_text())
        assert abs(doc["camera_angle_x"] - 0.6911) < 1e-3 and len(doc["frames"]) == n
        for i, fr in enumerate(doc["frames"]):
            assert fr["file_path"] == f"./{split}/r_{i}"
            m = np.asarray(fr["transform_matrix"])
            assert m.shape == (4, 4) and np.allclose(m[3], [0, 0, 0, 1])
            img = np.asarray(Image.open(scene_dir / (fr["file_path"] + ".png")))
            assert img.shape == (24, 24, 4)
            assert (img[..., 3] == 0).any() and (img[..., 3] == 255).any()  # transparent bg, opaque object
    spec = json.loads((scene_dir / "scene.json").read_text())
    assert spec["name"] == "cloth" and len(spec["bbox"]["half_size"]) == 3
    assert {"rest", "bend", "twist", "squash", "stretch", "arm"} <= set(spec["poses"])
    train = json.loads((scene_dir / "transforms_train.json").read_text())["frames"]
    test = json.loads((scene_dir / "transforms_test.json").read_text())["frames"]
    assert not np.allclose(train[0]["transform_matrix"], test[0]["transform_matrix"])


@pytest.mark.blender
def test_pose_render_differs_from_rest_and_keeps_cameras(scene_dir):
    _run("cloth", "--out", scene_dir, "--pose", "bend", "--magnitude", 0.5)
    vdir = scene_dir / "poses" / "bend_m0.5"
    doc = json.loads((vdir / "transforms_test.json").read_text())
    rest = json.loads((scene_dir / "transforms_test.json").read_text())
    assert np.allclose([f["transform_matrix"] for f in doc["frames"]], [f["transform_matrix"] for f in rest["frames"]])
    a = np.asarray(Image.open(scene_dir / "test" / "r_0.png")).astype(int)
    b = np.asarray(Image.open(vdir / "test" / "r_0.png")).astype(int)
    assert np.abs(a[..., 3] - b[..., 3]).sum() > 255 * 5
    v = json.loads((vdir / "variant.json").read_text())
    assert v["pose"] == "bend" and v["magnitude"] == 0.5


@pytest.mark.blender
def test_rest_pose_with_texture_changes_colours_not_silhouette(scene_dir):
    _run("cloth", "--out", scene_dir, "--texture", "checker")
    a = np.asarray(Image.open(scene_dir / "test" / "r_1.png")).astype(int)
    b = np.asarray(Image.open(scene_dir / "poses" / "rest_checker" / "test" / "r_1.png")).astype(int)
    assert np.array_equal(a[..., 3], b[..., 3])
    assert np.abs(a[..., :3] - b[..., :3])[a[..., 3] == 255].mean() > 10


def test_pose_without_scene_is_a_clear_error(tmp_path):
    res = _run("cloth", "--out", tmp_path / "nothing", "--pose", "bend", check=False)
    assert res.returncode == 2 and "scene.json" in res.stderr and "make-scene" in res.stderr


@pytest.mark.blender
def test_unknown_pose_and_existing_scene_errors(scene_dir):
    res = _run("cloth", "--out", scene_dir, "--pose", "dance", check=False)
    assert res.returncode == 2 and "unknown pose 'dance'" in res.stderr
    res = _run("cloth", "--out", scene_dir, check=False)
    assert res.returncode == 2 and "--force" in res.stderr


SHARED_FIELD = r'''
import sys, json, numpy as np, bpy
from tools.scenes import poses
spec = json.loads(open(sys.argv[1]).read())
bpy.ops.wm.read_factory_settings(use_empty=True)
rng = np.random.default_rng(0)
c, h = np.array(spec["bbox"]["center"]), np.array(spec["bbox"]["half_size"])
pts = c + (rng.random((400, 3)) * 2 - 1) * h
out = {}
for pose in ("bend", "twist", "squash", "arm"):
    res = []
    for extra in (False, True):  # a second, vertex-only mesh holding an extra far-away stray point
        p = np.vstack([pts, c + 3 * h]) if extra else pts
        me = bpy.data.meshes.new("m"); me.from_pydata(p.tolist(), [], [])
        ob = bpy.data.objects.new(f"o{pose}{extra}", me); bpy.context.scene.collection.objects.link(ob)
        poses.apply_pose(ob, spec, pose, 0.7)
        dg = bpy.context.evaluated_depsgraph_get()
        ev = ob.evaluated_get(dg).data
        buf = np.empty(len(ev.vertices) * 3); ev.vertices.foreach_get("co", buf)
        res.append(buf.reshape(-1, 3)[: len(pts)])
    out[pose] = [float(np.abs(res[0] - res[1]).max()), float(np.abs(res[0] - pts).max())]
print(json.dumps(out))
'''


@pytest.mark.blender
def test_same_deformation_field_for_any_point_set(scene_dir, tmp_path):
    """A stray point must not change how the others move (SimpleDeform would fail this), and poses move points."""
    script = tmp_path / "field.py"
    script.write_text(SHARED_FIELD)
    res = subprocess.run([sys.executable, str(script), str(scene_dir / "scene.json")], capture_output=True,
                         text=True, timeout=120)
    assert res.returncode == 0, res.stderr[-2000:]
    out = json.loads(res.stdout.strip().splitlines()[-1])
    for pose, (diff, moved) in out.items():
        assert diff < 1e-5, (pose, diff)
        assert moved > 0.05, (pose, moved)


LIBRARY_GEOMETRY = r'''
import json, sys
import bpy
import numpy as np
import torch
sys.path.insert(0, sys.argv[1])
from core.edits.procedural import evaluate
from tools.scenes import library

out = {}
for name, sdef in library.SCENES.items():
    bpy.ops.wm.read_factory_settings(use_empty=True)
    obj = library.build_object(sdef, name)
    me = obj.data
    co = np.empty(len(me.vertices) * 3)
    me.vertices.foreach_get("co", co)
    co = co.reshape(-1, 3)
    lo, hi = co.min(0), co.max(0)
    centre, half = 0.5 * (lo + hi), 0.5 * (hi - lo)
    rgb, mask = evaluate(sdef.texture, torch.from_numpy(co), centre, half)
    out[name] = {"verts": len(me.vertices), "faces": len(me.polygons), "radius": float(np.linalg.norm(co, axis=1).max()),
                 "centre": float(np.abs(centre).max()), "finite": bool(torch.isfinite(rgb).all()),
                 "colour_std": float(rgb.std(0).mean()), "poses": sorted(sdef.poses)}
print(json.dumps(out))
'''


@pytest.mark.blender
def test_library_scenes_build_centred_textured_and_posable(tmp_path):
    """Every library object builds with faces, centred and fit to the radius, its base texture finite over it
    (and not one flat colour unless it is the flat-colour texture), and the shared pose list."""
    from pathlib import Path

    script = tmp_path / "library.py"
    script.write_text(LIBRARY_GEOMETRY)
    root = str(Path(__file__).resolve().parents[2])
    res = subprocess.run([sys.executable, str(script), root], capture_output=True, text=True, timeout=300)
    assert res.returncode == 0, res.stderr[-2000:]
    out = json.loads(res.stdout.strip().splitlines()[-1])
    assert len(out) >= 10
    for name, r in out.items():
        assert r["verts"] > 500 and r["faces"] > 100, (name, r)
        assert abs(r["radius"] - 0.95) < 1e-4 and r["centre"] < 1e-6, (name, r)
        assert r["finite"] and r["colour_std"] > 0.01, (name, r)
        assert r["poses"] == sorted(["rest", "bend", "twist", "squash", "stretch", "arm"]), name


OPEN_SCENE = r'''
import json, sys
import bpy  # noqa: F401 (mathutils comes with it)
import numpy as np
from mathutils import Vector
from tools.scenes.render import open_scene, world_vertices
from tools.bench.colour_field_bound import rest_mesh_tree

scene = sys.argv[1]
spec, obj = open_scene(scene)
rest = world_vertices(obj)
c, h = np.array(spec["bbox"]["center"]), np.array(spec["bbox"]["half_size"])
out = {"object": obj.name, "verts": len(obj.data.vertices), "shape": list(rest.shape),
       "lo": (rest.min(0) - (c - h)).tolist(), "hi": ((c + h) - rest.max(0)).tolist(),
       "finite": bool(np.isfinite(rest).all())}
tree = rest_mesh_tree(scene)  # opens the file again
far = c + np.array([0.0, 0.0, 10.0 * h.max() + 1.0])
hit = tree.ray_cast(Vector(far), Vector((0.0, 0.0, -1.0)))[0]
print(json.dumps({**out, "hit": None if hit is None else list(hit)}))
'''


@pytest.mark.blender
def test_open_scene_gives_the_object_and_its_world_vertices(scene_dir, tmp_path):
    """tools.scenes.render.open_scene opens scene.blend and names the scene's object; world_vertices lie in the
    scene's bounding box; the benches' rest-mesh BVH (built from them) is hit by a ray down through the centre."""
    script = tmp_path / "open.py"
    script.write_text(OPEN_SCENE)
    res = subprocess.run([sys.executable, str(script), str(scene_dir)], capture_output=True, text=True, timeout=120,
                         cwd=str(Path(__file__).resolve().parents[2]))
    assert res.returncode == 0, res.stderr[-2000:]
    out = json.loads(res.stdout.strip().splitlines()[-1])
    spec = json.loads((scene_dir / "scene.json").read_text())
    assert out["object"] == spec["object"]
    assert out["shape"] == [out["verts"], 3] and out["verts"] > 3 and out["finite"]
    assert min(out["lo"]) > -1e-4 and min(out["hi"]) > -1e-4, out  # inside the box it states
    assert out["hit"] is not None


@pytest.mark.blender
def test_the_rest_mesh_tree_is_callable_first_in_a_process(scene_dir):
    """The benches' rest-mesh BVH (`pose_bound --base`, `colour_field_bound`) in a fresh process that has not
    imported bpy: mathutils ships inside bpy, so importing it first failed (No module named 'mathutils')."""
    code = ("import sys\nfrom tools.bench.colour_field_bound import rest_mesh_tree\n"
            "print(type(rest_mesh_tree(sys.argv[1])).__name__)")
    res = subprocess.run([sys.executable, "-c", code, str(scene_dir)], capture_output=True, text=True, timeout=120,
                         cwd=str(Path(__file__).resolve().parents[2]))
    assert res.returncode == 0, res.stderr[-2000:]
    assert res.stdout.strip().splitlines()[-1] == "BVHTree"
