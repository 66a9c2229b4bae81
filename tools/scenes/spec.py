"""A scene's description file (scene.json, written by `pointgt make-scene`): reading it and checking the parts the
tools read. No bpy: the checks run anywhere."""
from __future__ import annotations

import json
import math
from pathlib import Path

from core.util.errors import DataError

SCENE_FORMAT = "pointgt-scene"  # scene.json's "format" (tools/scenes/build.py writes it)


def load_scene_spec(scene) -> dict:
    """scene: a scene directory, its scene.json path, or the already-loaded dict."""
    if isinstance(scene, dict):
        return scene
    path = Path(scene)
    if path.is_dir():
        path = path / "scene.json"
    if not path.exists():
        raise DataError(f"{path}: no scene.json here; create the scene first with `pointgt make-scene NAME --out DIR`")
    try:
        spec = json.loads(path.read_text(encoding="utf-8"))
    except (json.JSONDecodeError, UnicodeDecodeError, RecursionError) as exc:
        raise DataError(f"{path}: not valid JSON ({type(exc).__name__}: {exc})") from exc
    check_scene_spec(spec, path)
    return spec


def _numbers(value, n: int) -> bool:
    return (isinstance(value, list) and len(value) == n and all(
        isinstance(v, (int, float)) and not isinstance(v, bool) and math.isfinite(v) for v in value))


def check_scene_spec(spec, path) -> None:
    """The parts of a scene.json that the tools read (`pointgt make-scene` writes them): an object with a 'bbox'
    (centre [3] and half_size [3] > 0, finite), a 'texture' object (its 'params' an object) and 'poses' (an object of
    pose objects, each with a 'type'). Raises DataError naming the file and the entry; make the scene again to fix."""
    def bad(what):
        return DataError(f"{path}: {what}; the scene file is damaged, make the scene again with `pointgt make-scene`")

    if not isinstance(spec, dict):
        raise bad(f"holds a {type(spec).__name__}, not a scene description object")
    if "format" in spec and spec["format"] != SCENE_FORMAT:
        raise bad(f"'format' is {spec['format']!r}, not {SCENE_FORMAT!r}")
    box = spec.get("bbox")
    if not (isinstance(box, dict) and _numbers(box.get("center"), 3) and _numbers(box.get("half_size"), 3)
            and min(box["half_size"]) > 0):
        raise bad("'bbox' must hold 'center' and 'half_size' as three finite numbers each (half_size > 0)")
    tex = spec.get("texture")
    if not (isinstance(tex, dict) and isinstance(tex.get("params", {}), dict)):
        raise bad("'texture' must be an object whose 'params' is an object")
    poses = spec.get("poses")
    if not (isinstance(poses, dict) and all(isinstance(p, dict) and isinstance(p.get("type"), str)
                                            for p in poses.values())):
        raise bad("'poses' must be an object of pose objects, each with a 'type'")
