"""The add-on's layers (pointgt_blender/__init__.py): bridge/ never imports bpy; ui/ and operators/ never import
torch at module level (the add-on must register without PyTorch). Checked on the source, no Blender needed."""
import ast
from pathlib import Path

import pytest

ADDON = Path(__file__).resolve().parents[2] / "pointgt_blender"


def _imports(path: Path, module_level_only: bool) -> set[str]:
    """Top-level names of the packages `path` imports (absolute imports only)."""
    tree = ast.parse(path.read_text(encoding="utf-8"), filename=str(path))
    nodes = tree.body if module_level_only else list(ast.walk(tree))
    if module_level_only:  # also look inside module-level if/try blocks, still module level
        nodes = [n for top in tree.body for n in ast.walk(top)
                 if not isinstance(top, (ast.FunctionDef, ast.AsyncFunctionDef, ast.ClassDef))]
        nodes += [n for top in tree.body if isinstance(top, ast.ClassDef) for n in top.body]
    names = set()
    for node in nodes:
        if isinstance(node, ast.Import):
            names |= {a.name.split(".")[0] for a in node.names}
        elif isinstance(node, ast.ImportFrom) and node.level == 0 and node.module:
            names.add(node.module.split(".")[0])
    return names


def _modules(sub: str) -> list[Path]:
    found = sorted((ADDON / sub).glob("*.py"))
    assert found, f"pointgt_blender/{sub}/ holds no modules"
    return found


@pytest.mark.parametrize("path", _modules("bridge"), ids=lambda p: p.name)
def test_bridge_never_imports_bpy(path):
    bad = _imports(path, module_level_only=False) & {"bpy", "bpy_extras", "mathutils", "bmesh"}
    assert not bad, f"{path.relative_to(ADDON.parent)} imports {sorted(bad)}; the bridge must run without Blender"


@pytest.mark.parametrize("path", _modules("ui") + _modules("operators"), ids=lambda p: f"{p.parent.name}/{p.name}")
def test_ui_and_operators_import_torch_lazily(path):
    bad = _imports(path, module_level_only=True) & {"torch"}
    assert not bad, f"{path.relative_to(ADDON.parent)} imports torch at module level; import it inside the function"


def test_the_checker_sees_both_kinds_of_import(tmp_path):
    src = tmp_path / "m.py"
    src.write_text("import torch.nn\nfrom bpy.types import Operator\ndef f():\n    import numpy\n")
    assert _imports(src, module_level_only=True) == {"torch", "bpy"}
    assert _imports(src, module_level_only=False) == {"torch", "bpy", "numpy"}
