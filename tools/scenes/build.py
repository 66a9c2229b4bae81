"""Create a built-in scene (images, cameras, scene.blend, scene.json) and render its pose/texture variants."""
from __future__ import annotations

import json
import math
import time
from pathlib import Path

import bpy
import numpy as np

from core.edits.procedural import get_texture
from core.util.atomic import atomic_path, atomic_write_text
from core.util.errors import DataError, InputError
from tools.scenes import cameras, library, nodes, poses, render
from tools.scenes.spec import SCENE_FORMAT, load_scene_spec

FORMAT_VERSION = 1
CAMERA_RADIUS = 4.0
CAMERA_ANGLE_X = 0.6911112070083618  # the NeRF-synthetic value: the object fills most of the frame
OBJECT_NAME = "object"


def _write_json(path: Path, data: dict) -> None:
    atomic_write_text(path, json.dumps(data, indent=2) + "\n")


def _material(spec: dict, texture: str | None):
    """The scene's base texture, a global retexture, or the decal composited over the base texture."""
    lit = spec["render"]["lit"]
    base = spec["texture"]["base"]
    if texture is None:
        return nodes.make_material("base", base, lit=lit)
    tex = get_texture(texture)
    if tex.local:
        return nodes.make_material(texture, base, decal=texture, decal_params=spec["texture"]["params"].get(texture),
                                   lit=lit)
    return nodes.make_material(texture, texture, spec["texture"]["params"].get(texture), lit=lit)


def _set_material(obj, mat) -> None:
    obj.data.materials.clear()
    obj.data.materials.append(mat)


def _save_blend(path: Path) -> None:
    with atomic_path(path) as tmp:
        tmp.unlink()  # an existing file would make Blender write a "<tmp>1" backup of it
        with render.quiet_stdout():
            bpy.ops.wm.save_as_mainfile(filepath=str(tmp), check_existing=False, copy=True)


def make_scene(name: str, out, size: int = 128, views_train: int = 60, views_val: int = 8, views_test: int = 20,
               seed: int = 0, lit: bool = False, samples: int | None = None, force: bool = False, log=print) -> dict:
    """Build scene `name` in a fresh Blender file and render train/val/test views into `out`; returns scene.json."""
    if name not in library.SCENES:
        raise InputError(f"unknown scene '{name}'; choose one of {', '.join(library.scene_names())}")
    if size < 8 or size > 4096:
        raise InputError(f"--size {size}: choose 8..4096 pixels")
    if min(views_train, views_test) < 1 or views_val < 0:
        raise InputError("need at least 1 train and 1 test view (and >= 0 val views)")
    out = Path(out)
    if (out / "scene.json").exists() and not force:
        raise InputError(f"{out / 'scene.json'} already exists; pass --force to re-render it or choose another --out")
    sdef = library.SCENES[name]
    lit = bool(lit or sdef.lit)
    samples = int(samples or render.DEFAULT_SAMPLES)
    t0 = time.perf_counter()

    bpy.ops.wm.read_factory_settings(use_empty=True)
    scene = bpy.context.scene
    obj = library.build_object(sdef, OBJECT_NAME)
    me = obj.data
    center, half = list(me.texspace_location), list(me.texspace_size)  # what Generated coordinates use
    spec = {
        "format": SCENE_FORMAT, "version": FORMAT_VERSION, "name": name, "description": sdef.help,
        "object": OBJECT_NAME, "vertices": len(me.vertices), "faces": len(me.polygons),
        "bbox": {"center": center, "half_size": half},
        "camera": {"camera_angle_x": CAMERA_ANGLE_X, "radius": CAMERA_RADIUS, "width": size, "height": size,
                   "seed": seed, "views": {"train": views_train, "val": views_val, "test": views_test}},
        "render": {"engine": "CYCLES", "device": "CPU", "samples": samples, "lit": lit, "denoiser": None,
                   "view_transform": "Standard", "film_transparent": True},
        "texture": {"base": sdef.texture, "params": {"decal": sdef.decal}},
        "poses": sdef.poses,
    }
    _set_material(obj, _material(spec, None))
    if lit:
        render.add_lights(scene)
    render.setup_cycles(scene, size, samples, lit)
    cam = render.add_camera(scene, CAMERA_ANGLE_X)
    out.mkdir(parents=True, exist_ok=True)
    log(f"scene '{name}': {len(me.vertices)} vertices, {size}x{size}, {samples} samples, lit={lit}")
    for split, n in (("train", views_train), ("val", views_val), ("test", views_test)):
        c2ws = cameras.split_cameras(split, n, seed, CAMERA_RADIUS)
        frames = render.render_views(scene, cam, c2ws, out, split, log=log)
        _write_json(out / f"transforms_{split}.json", {"camera_angle_x": CAMERA_ANGLE_X, "frames": frames})

    # the rigs of every pose, modifiers present but switched off: enable one in Blender to see the pose
    for pose in sdef.poses:
        if poses.apply_pose(obj, spec, pose, 1.0) is not None:
            mod = obj.modifiers[f"pgt_{pose}"]
            mod.show_viewport = mod.show_render = False
    _save_blend(out / "scene.blend")
    spec["seconds"] = round(time.perf_counter() - t0, 2)
    _write_json(out / "scene.json", spec)
    log(f"scene '{name}' written to {out} in {spec['seconds']:.1f} s")
    return spec


def variant_dirname(pose: str = "rest", magnitude: float = 1.0, texture: str | None = None) -> str:
    """poses/<pose>[_m<magnitude>][_<texture>]: the magnitude is left out when it is 1 (and for rest)."""
    name = pose
    if pose != "rest" and magnitude != 1.0:
        name += f"_m{magnitude:g}"
    if texture:
        name += f"_{texture}"
    return name


def render_variant(out, pose: str = "rest", magnitude: float = 1.0, texture: str | None = None,
                   samples: int | None = None, log=print) -> Path:
    """Render the TEST cameras of an existing scene posed/retextured into out/poses/<variant>/; returns that dir."""
    out = Path(out)
    spec = load_scene_spec(out)
    blend = out / "scene.blend"
    test_json = out / "transforms_test.json"
    for f in (blend, test_json):
        if not f.exists():
            raise DataError(f"{f}: missing; re-create the scene with `pointgt make-scene {spec.get('name', 'NAME')} "
                            f"--out {out} --force`")
    if not math.isfinite(magnitude):
        raise InputError(f"--magnitude must be finite, got {magnitude}")
    poses.pose_spec(spec, pose)  # unknown pose: clear error before any work
    if texture is not None:
        get_texture(texture)
    frames = json.loads(test_json.read_text())["frames"]
    c2ws = np.asarray([f["transform_matrix"] for f in frames], dtype=np.float64)

    bpy.ops.wm.open_mainfile(filepath=str(blend))
    scene = bpy.context.scene
    obj = bpy.data.objects[spec["object"]]
    if texture is not None:
        _set_material(obj, _material(spec, texture))
    rig = poses.apply_pose(obj, spec, pose, magnitude)
    if rig is not None:
        mod = obj.modifiers[f"pgt_{pose}"]
        mod.show_viewport = mod.show_render = True
    if samples:
        scene.cycles.samples = int(samples)
    dirname = variant_dirname(pose, magnitude, texture)
    vdir = out / "poses" / dirname
    log(f"variant '{dirname}' of scene '{spec['name']}': {len(c2ws)} test views")
    rendered = render.render_views(scene, scene.camera, c2ws, vdir, "test", log=log)
    _write_json(vdir / "transforms_test.json", {"camera_angle_x": spec["camera"]["camera_angle_x"], "frames": rendered})
    _write_json(vdir / "variant.json", {
        "scene": spec["name"], "pose": pose, "pose_spec": spec["poses"][pose], "magnitude": magnitude,
        "texture": texture, "texture_params": spec["texture"]["params"].get(texture) if texture else None,
        "base_texture": spec["texture"]["base"], "bbox": spec["bbox"]})
    return vdir
