"""tools.bench.orientation: rolled cameras, their scene folder and the score (the Cycles side runs in the benchmark)."""
import json

import numpy as np

from tools.bench.orientation import markdown, rolled_c2w, rolled_scene_dir


def _camera():
    from core.images.cameras import look_at

    return look_at((1.0, -3.0, 2.0)).numpy()


def test_a_rolled_camera_keeps_its_place_and_direction_and_turns_its_image():
    c = _camera()
    r = rolled_c2w(c, 90)
    assert np.allclose(r[:3, 3], c[:3, 3]) and np.allclose(r[:3, 2], c[:3, 2])  # position, viewing axis
    assert np.allclose(r[:3, 0], c[:3, 1]) and np.allclose(r[:3, 1], -c[:3, 0])  # image x -> old y
    assert np.allclose(rolled_c2w(c, 360), c) and np.allclose(rolled_c2w(rolled_c2w(c, 30), -30), c)
    assert np.allclose(r[:3, :3] @ r[:3, :3].T, np.eye(3))


def test_the_rolled_folder_holds_the_eval_cameras_rolled(tmp_path):
    frames = [{"file_path": f"./test/r_{i}", "transform_matrix": rolled_c2w(_camera(), 20 * i).tolist()}
              for i in range(5)]
    (tmp_path / "transforms_test.json").write_text(json.dumps({"camera_angle_x": 0.69, "frames": frames}))
    for name in ("scene.blend", "scene.json"):
        (tmp_path / name).write_text("x")
    d = rolled_scene_dir(tmp_path, 2, 45)
    doc = json.loads((d / "transforms_test.json").read_text())
    assert d.name == "roll_2_45" and len(doc["frames"]) == 2 and doc["camera_angle_x"] == 0.69
    want = [rolled_c2w(np.array(frames[i]["transform_matrix"]), 45) for i in (0, 4)]
    assert all(np.allclose(f["transform_matrix"], w) for f, w in zip(doc["frames"], want))
    assert (d / "scene.blend").is_symlink()
    # a cached ground truth of other cameras is dropped when the cameras change
    (d / "poses" / "rest").mkdir(parents=True)
    (d / "poses" / "rest" / "variant.json").write_text("{}")
    rolled_scene_dir(tmp_path, 2, 45)
    assert (d / "poses" / "rest" / "variant.json").exists()  # same cameras: kept
    (d / "transforms_test.json").write_text(json.dumps({**doc, "frames": doc["frames"][:1]}))
    rolled_scene_dir(tmp_path, 2, 45)
    assert not (d / "poses" / "rest" / "variant.json").exists()


def test_markdown_has_a_row_per_model():
    res = {"scene": "S", "views": 4, "models": {"a/A.pgt": {"rest": 30.0, "roll 45": 28.0, "arm": 24.0},
                                               "B.pgt": {"rest": 29.0, "roll 45": 29.0, "arm": 25.0}}}
    text = markdown(res)
    assert "| A.pgt | 30.00 | 28.00 | 24.00 | 26.00 |" in text and "| B.pgt | 29.00 | 29.00 | 25.00 | 27.00 |" in text
    same = markdown({**res, "models": {"x/M.pgt": res["models"]["a/A.pgt"], "y/M.pgt": res["models"]["B.pgt"]}})
    assert "| x/M.pgt |" in same and "| y/M.pgt |" in same
