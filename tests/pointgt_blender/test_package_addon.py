"""`pointgt package-addon`: the zip layout, the vendored core with rewritten imports, Blender's validator."""
from __future__ import annotations

import ast
import os
import subprocess
import sys
import zipfile
from pathlib import Path

import pytest

from core.util.errors import InputError
from tools.package_addon import REPO, rewrite_core_imports, validate


def test_rewrite_makes_core_imports_relative_at_each_depth():
    src = ("import os\nfrom core.util.errors import InputError\nfrom core import config\n"
           "if True:\n    from core.modelfile.pgt import (\n        load_pgt,\n    )\nfrom corelib import x\n")
    assert rewrite_core_imports(src, 0) == src.replace("from core.", "from .core.").replace(
        "from core import", "from .core import")
    out2 = rewrite_core_imports(src, 2)
    assert "from ...core.util.errors import InputError" in out2 and "from ...core import config" in out2
    assert "    from ...core.modelfile.pgt import (\n        load_pgt," in out2
    assert "from corelib import x" in out2  # another package whose name starts with "core" is left alone


def test_rewrite_rejects_plain_import_of_core():
    with pytest.raises(InputError, match=r"x\.py:2: 'import core\.config'"):
        rewrite_core_imports("import os\nimport core.config\n", 0, "x.py")


def test_rewrite_leaves_strings_and_comments_alone():
    src = '"""Use `from core.x import y` in code."""\n# from core.a import b\nVALUE = "from core.z import w"\n'
    assert rewrite_core_imports(src, 1) == src


@pytest.fixture(scope="module")
def built(tmp_path_factory):
    out = tmp_path_factory.mktemp("dist")
    proc = subprocess.run([sys.executable, "-m", "tools.cli", "package-addon", "--out", str(out)],
                          capture_output=True, text=True, cwd=REPO)
    assert proc.returncode == 0, proc.stderr
    return Path(proc.stdout.strip().splitlines()[-1]), out


def test_cli_prints_zip_path_last_and_zip_validates(built):
    path, out = built
    assert path == (out / "pointgt-0.1.0.zip").resolve() and path.is_file()
    assert "pointgt" in validate(path)


def test_zip_holds_manifest_addon_and_vendored_core_without_absolute_core_imports(built):
    path, _ = built
    with zipfile.ZipFile(path) as zf:
        names = zf.namelist()
        assert "blender_manifest.toml" in names and "__init__.py" in names
        assert "core/modelfile/pgt.py" in names and "core/util/errors.py" in names
        assert not any("__pycache__" in n or n.endswith(".pyc") for n in names)
        for name in (n for n in names if n.endswith(".py")):
            tree = ast.parse(zf.read(name).decode("utf-8"), name)
            for node in ast.walk(tree):
                if isinstance(node, ast.ImportFrom) and node.level == 0:
                    assert not (node.module or "").startswith("core"), f"{name}: absolute import of core"
                if isinstance(node, ast.Import):
                    assert not any(a.name.split(".")[0] == "core" for a in node.names), name


def test_validator_rejects_a_bad_manifest(tmp_path):
    (tmp_path / "__init__.py").write_text("def register(): pass\ndef unregister(): pass\n")
    text = (REPO / "addon_manifest.toml").read_text().replace('tags = ["Render"', 'tags = ["Rendering"')
    (tmp_path / "blender_manifest.toml").write_text(text)
    with pytest.raises(InputError, match="Rendering"):
        validate(tmp_path)


LEGACY_SCRIPT = """
import sys, bpy
import addon_utils
zip_path, model = sys.argv[-2:]
bpy.ops.preferences.addon_install(filepath=zip_path)
addon_utils.enable("pointgt", default_set=True)
print("RESULT", "pointgt" in bpy.context.preferences.addons, sorted(bpy.ops.pointgt.import_model(filepath=model)),
      len(bpy.context.active_object.data.vertices))
"""


@pytest.mark.blender
def test_legacy_zip_installs_as_a_legacy_addon(tmp_path):
    import numpy as np

    from core.modelfile.pgt import save_pgt
    from tools.package_addon import build_addon

    path = build_addon(tmp_path / "dist", legacy=True)
    with zipfile.ZipFile(path) as zf:
        names = zf.namelist()
    assert "pointgt/__init__.py" in names and "pointgt/core/modelfile/pgt.py" in names
    assert not any(n.endswith("blender_manifest.toml") for n in names)
    model = tmp_path / "m.pgt"
    save_pgt(model, {"points/xyz": np.zeros((5, 3), np.float32)}, {})
    env = dict(os.environ, BLENDER_USER_RESOURCES=str(tmp_path / "user"))
    proc = subprocess.run([sys.executable, "-c", LEGACY_SCRIPT, str(path), str(model)], capture_output=True,
                          text=True, env=env, timeout=120)
    assert "RESULT True ['FINISHED'] 5" in proc.stdout, proc.stdout[-2000:] + proc.stderr[-2000:]


def test_versions_must_agree(monkeypatch):
    import tools.package_addon as pa

    monkeypatch.setattr(pa, "_bl_info_version", lambda: "9.9.9")
    with pytest.raises(InputError, match="versions differ"):
        pa.check_versions()
