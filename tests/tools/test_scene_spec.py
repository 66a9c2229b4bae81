"""scene.json: read and checked without bpy; a damaged file is a DataError naming the file and the entry."""
import json

import pytest

from core.util.errors import DataError
from tools.scenes.spec import load_scene_spec

GOOD = {"format": "pointgt-scene", "version": 1, "name": "cloth",
        "bbox": {"center": [0.0, 0.0, 0.1], "half_size": [1.0, 0.5, 0.2]},
        "texture": {"base": "checker", "params": {"decal": {"radius": 0.2}}},
        "poses": {"rest": {"type": "rest"}, "bend": {"type": "bend", "along": 0, "toward": 2, "angle_deg": 90.0}}}


def _write(tmp_path, doc):
    (tmp_path / "scene.json").write_text(doc if isinstance(doc, str) else json.dumps(doc))
    return tmp_path


def test_a_scene_file_make_scene_writes_is_read_as_it_is(tmp_path):
    assert load_scene_spec(_write(tmp_path, GOOD)) == GOOD
    assert load_scene_spec(GOOD) is GOOD  # an already-loaded description passes through


@pytest.mark.parametrize("edit,pattern", [
    (lambda d: [1, 2], "holds a list"),
    (lambda d: dict(d, format="pointgt-model"), "'format'"),
    (lambda d: {k: v for k, v in d.items() if k != "bbox"}, "'bbox'"),
    (lambda d: dict(d, bbox={"center": [0, 0], "half_size": [1, 1, 1]}), "'bbox'"),
    (lambda d: dict(d, bbox={"center": [0, 0, float("nan")], "half_size": [1, 1, 1]}), "'bbox'"),
    (lambda d: dict(d, bbox={"center": [0, 0, 0], "half_size": [1, 0, 1]}), "'bbox'"),
    (lambda d: dict(d, bbox={"center": [0, True, 0], "half_size": [1, 1, 1]}), "'bbox'"),
    (lambda d: dict(d, texture="checker"), "'texture'"),
    (lambda d: dict(d, texture={"params": []}), "'texture'"),
    (lambda d: dict(d, poses=["bend"]), "'poses'"),
    (lambda d: dict(d, poses={"bend": {"along": 0}}), "'poses'"),
])
def test_damaged_scene_files_name_the_file_and_the_entry(tmp_path, edit, pattern):
    _write(tmp_path, edit(json.loads(json.dumps(GOOD))))
    with pytest.raises(DataError, match=pattern) as err:
        load_scene_spec(tmp_path)
    assert "scene.json" in str(err.value) and "make-scene" in str(err.value)


def test_unreadable_and_missing_scene_files(tmp_path):
    with pytest.raises(DataError, match="no scene.json here"):
        load_scene_spec(tmp_path)
    (tmp_path / "scene.json").write_bytes(b"\xff\xfe{")
    with pytest.raises(DataError, match="not valid JSON"):
        load_scene_spec(tmp_path)
    _write(tmp_path, "[" * 100_000 + "]" * 100_000)
    with pytest.raises(DataError, match="not valid JSON"):
        load_scene_spec(tmp_path)
