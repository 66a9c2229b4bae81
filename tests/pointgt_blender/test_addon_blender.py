"""The packaged add-on inside a real Blender (bpy in a subprocess, its own BLENDER_USER_RESOURCES): install the
zip, register without torch, import a .pgt, rig it with a lattice and armatures, export, and the error cases.
One Blender process runs every step (tests/pointgt_blender/addon_script.py); the tests below check its record."""
from __future__ import annotations

import os
import zipfile
from pathlib import Path

import numpy as np
import pytest

from core.modelfile.pgt import save_pgt
from tests.helpers.blender import run_script, step_result
from tools.package_addon import build_addon

pytestmark = pytest.mark.blender
SCRIPT = Path(__file__).with_name("addon_script.py")
N = 60


def _model_arrays():
    rng = np.random.default_rng(3)
    xyz = rng.uniform(-0.5, 0.5, size=(N, 3)).astype(np.float32)
    atlas = rng.uniform(0.0, 1.0, size=(6, 8, 3)).astype(np.float32)  # H != W catches transposes and flips
    atlas[0, 0] = (1.0, 0.0, 0.0)  # top-left texel (row 0 = top in the file)
    return xyz, atlas


def _probe_wheel(folder: Path) -> None:
    """A tiny pure-Python wheel: lets the install button run real pip offline, without downloading torch."""
    files = {"pointgt_probe/__init__.py": "VALUE = 42\n",
             "pointgt_probe-1.0.dist-info/METADATA": "Metadata-Version: 2.1\nName: pointgt-probe\nVersion: 1.0\n",
             "pointgt_probe-1.0.dist-info/WHEEL": "Wheel-Version: 1.0\nGenerator: test\nRoot-Is-Purelib: true\n"
                                                  "Tag: py3-none-any\n"}
    files["pointgt_probe-1.0.dist-info/RECORD"] = "".join(f"{k},,\n" for k in files) + \
        "pointgt_probe-1.0.dist-info/RECORD,,\n"
    with zipfile.ZipFile(folder / "pointgt_probe-1.0-py3-none-any.whl", "w") as zf:
        for name, text in files.items():
            zf.writestr(name, text)


@pytest.fixture(scope="module")
def record(tmp_path_factory):
    tmp = tmp_path_factory.mktemp("addon")
    zip_path = build_addon(tmp / "dist")
    xyz, atlas = _model_arrays()
    model = tmp / "bunny.pgt"
    save_pgt(model, {"points/xyz": xyz, "atlas/image": atlas}, {"scene": "test"})
    data = model.read_bytes()
    corrupt = tmp / "broken.pgt"
    corrupt.write_bytes(data[: len(data) // 2])  # cut in half, as an interrupted copy would
    work = tmp / "work"
    work.mkdir()
    wheels = tmp / "wheels"
    wheels.mkdir()
    _probe_wheel(wheels)
    env = dict(os.environ, BLENDER_USER_RESOURCES=str(tmp / "blender_user"), PIP_NO_INDEX="1")
    results = run_script(SCRIPT, [str(zip_path), str(model), str(corrupt), str(work), str(wheels)], env, tmp,
                          timeout=300)
    return {"r": results, "xyz": xyz, "atlas": atlas, "model": model, "corrupt": corrupt, "work": work}


def _get(record, step):
    return step_result(record["r"], step)


def test_installs_and_registers_without_torch(record):
    r = _get(record, "install")
    assert r["result"] == ["FINISHED"] and r["enabled"] and r["import_op"]
    assert r["torch_loaded"] is False
    # operators on the model are undoable through their shared base; those that change no scene data are not
    assert r["undo"] == {"reset_canonical": True, "bind_armature": True, "add_lattice": True, "pack_model": True,
                         "transfer_paint": False, "export_deformed": False}
    t = _get(record, "torch_missing")
    assert t["available"] is False and "PyTorch is missing" in t["message"]
    # the torch-only operator refuses to run on an imported model and says why
    assert "PyTorch is missing" in _get(record, "import")["torch_poll_error"]


def test_import_builds_points_mesh_with_ids_and_packed_atlas(record):
    r = _get(record, "import")
    assert r["result"] == ["FINISHED"] and r["new_objects"] == 1 and r["name"] == "bunny"
    assert (r["verts"], r["edges"], r["faces"]) == (N, 0, 0)
    assert r["ids"] == list(range(N)) and r["attr"] == ["POINT", "INT"]
    np.testing.assert_allclose(np.asarray(r["co"]).reshape(N, 3), record["xyz"], atol=1e-7)
    assert r["image_size"] == [8, 6] and r["packed"] and r["image_float"]
    atlas = np.asarray(r["atlas"], np.float32)
    np.testing.assert_allclose(atlas, record["atlas"], atol=2e-5)  # same orientation: row 0 = top
    assert r["k"] == 12 and r["point_count"] == N
    assert os.path.samefile(r["model_path"], record["model"])  # absolute while the .blend is unsaved


def test_atlas_and_settings_survive_save_and_reload(record):
    r = _get(record, "reload_blend")
    np.testing.assert_allclose(np.asarray(r["atlas"], np.float32), record["atlas"], atol=2e-5)
    assert r["k"] == 12 and r["resolved"]
    assert r["model_path"] == "//../bunny.pgt"  # made relative when the .blend got a location (work/scene.blend)


def test_corrupt_or_missing_model_reports_and_creates_nothing(record):
    r = _get(record, "import_corrupt")
    assert "broken.pgt" in r["error"] and r["unchanged"]
    assert "nope.pgt" in r["missing"] and "not found" in r["missing"]
    assert "BAD" in r["late"] and r["unchanged_late"]


def test_lattice_wraps_points_and_deforms_them(record):
    r = _get(record, "lattice")
    assert r["lattice_type"] == "LATTICE"
    assert r["identity_err"] < 1e-4  # an untouched lattice leaves the points where they were
    assert r["max_move"] > 0.05 and r["finite"] and r["ids_ok"]


def test_reset_restores_canonical_positions(record):
    r = _get(record, "reset")
    assert r["err"] < 1e-6 and r["disabled"] == [False] and r["left"] == 0


def test_armature_envelopes_move_points(record):
    r = _get(record, "armature_envelope")
    assert r["modifier"] == ["ARMATURE"] and r["max_move"] > 0.05 and r["finite"]
    # our envelope estimate (used for the "points outside every envelope" warning) agrees with Blender
    assert r["uncovered"] > 0 and r["uncovered_move"] < 1e-6 and r["covered_still"] == 0


def test_armature_weights_from_proxy_mesh(record):
    r = _get(record, "armature_proxy")
    assert r["groups"] == ["Bone"] and r["min_weight"] == pytest.approx(1.0)
    assert r["modifiers"] == ["ARMATURE"] and r["max_move"] > 0.05
    assert "vertex groups" in r["err_no_groups"]


def test_export_writes_npy_pair_with_backups(record):
    r = _get(record, "export")
    assert r["shape"] == [N, 3] and r["dtype"] == "float32" and r["ids_dtype"] == "int64"
    assert r["equal"] and r["bak"]


def test_nan_positions_are_reported_not_exported(record):
    r = _get(record, "nan_positions")
    assert "NaN" in r["error"] and "ids 1" in r["error"] and not r["written"]


def test_point_count_change_without_ids_is_reported(record):
    r = _get(record, "count_changed")
    assert "changed the point count" in r["direct"] and f"from {N} to {N + 3}" in r["direct"]
    assert r["n_eval"] < N
    assert "changed the point count" in r["op_error"]


def test_install_button_runs_pip_into_the_addon_folder(record):
    r = _get(record, "install_offline_wheel")
    assert r["result"] == ["FINISHED"] and r["value"] == 42 and r["in_site"]


def test_torch_features_work_once_torch_imports(record):
    r = _get(record, "torch_unblocked")
    assert r["result"] == ["FINISHED"]
    assert r["cuda_err"] == "" or "CUDA is not available" in r["cuda_err"]


def test_the_objects_occlusion_setting_reaches_the_frame_inputs(record):
    """The Folds (occlusion) checkbox of an imported model is on by default (EditConfig.f_occlusion) and, when off,
    reaches the frame's inputs (tests/pointgt_blender/test_addon_frame_renderer.py)."""
    r = _get(record, "occlusion_setting")
    assert r == {"default": True, "off": False}


def test_existing_site_packages_folder_is_used_and_released(record):
    r = _get(record, "site_packages_pref")
    assert r["value"] == 7 and r["on_path"] and r["removed"]


def test_lattice_on_flat_and_single_point_models_stays_finite(record):
    r = _get(record, "degenerate_lattice")
    for name in ("flat", "single"):
        assert r[name]["finite"] and r[name]["scale_ok"] and r[name]["err"] < 1e-4, (name, r[name])
        assert r[name]["atlas"]  # models without an atlas import as points only


def test_points_outside_every_envelope_are_counted(record):
    r = _get(record, "envelope_outside")
    assert r["outside_far"] == N and r["outside_near"] < N


def test_panel_and_preferences_draw_and_show_what_is_missing(record):
    r = _get(record, "draw_ui")
    assert "PyTorch is missing" in r["no_model"] and "Select an imported model" in r["no_model"]
    for name in ("model_path", "neighbors", "correspondence", "device", "pointgt.add_lattice",
                 "pointgt.bind_armature", "pointgt.reset_canonical", "pointgt.export_deformed"):
        assert name in r["with_model"]
    assert "PyTorch is missing" in r["prefs_labels"] and "folder not found" in r["prefs_labels"]
    assert "pointgt.install_torch" in r["prefs_ops"] and r["addon_prefs"] == "PointGTPreferences"
