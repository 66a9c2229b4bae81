"""Build the installable Blender extension zip: `pointgt_blender` + a vendored copy of `core`.

Layout inside the zip (the add-on's module becomes `bl_ext.<repo>.pointgt` once installed):

    blender_manifest.toml      <- addon_manifest.toml
    __init__.py, deps.py, ...  <- pointgt_blender/*.py (the add-on package itself)
    core/...                   <- core/**/*.py, vendored as a subpackage of the add-on

`import core` would not resolve inside Blender (the add-on is not on sys.path, and a top-level name as generic
as `core` could clash with another add-on's), so every absolute `from core... import` in the copied sources is
rewritten into the matching relative import (`from ..core.util.errors import X`). Plain `import core...`
statements cannot be rewritten that way and fail the build with the file and line named.
Blender's own validator (the bl_pkg CLI shipped inside the bpy wheel) checks the staged folder and the zip.
"""
from __future__ import annotations

import ast
import importlib.util
import re
import shutil
import subprocess
import sys
import tempfile
import tomllib
import zipfile
from pathlib import Path

from core.util.errors import InputError

REPO = Path(__file__).resolve().parents[1]
ADDON_SOURCE = REPO / "pointgt_blender"
CORE_SOURCE = REPO / "core"
MANIFEST = REPO / "addon_manifest.toml"
VENDORED = "core"  # the vendored package's name inside the add-on

_FROM_CORE = re.compile(r"from\s+core\b")


def _bpy_scripts_dir() -> Path:
    """`<site-packages>/bpy/<version>/scripts` of the installed bpy wheel (found without importing bpy)."""
    spec = importlib.util.find_spec("bpy")
    if spec is None or not spec.submodule_search_locations:
        raise InputError("package-addon needs the bpy wheel (Blender as a Python module) for Blender's extension "
                         "validator; install the project dependencies (bash tools/run.sh test sets them up)")
    root = Path(list(spec.submodule_search_locations)[0])
    found = sorted(root.glob("*/scripts/addons_core/bl_pkg/cli/blender_ext.py"))
    if not found:
        raise InputError(f"Blender's extension CLI (bl_pkg/cli/blender_ext.py) was not found under {root}")
    return found[-1].parents[3]


def blender_ext_cli() -> Path:
    return _bpy_scripts_dir() / "addons_core" / "bl_pkg" / "cli" / "blender_ext.py"


def blender_valid_tags() -> Path:
    """Blender's list of valid extension tags (the validator reads it with --valid-tags)."""
    return _bpy_scripts_dir() / "modules" / "_bpy_internal" / "extensions" / "tags.py"


def rewrite_core_imports(source: str, package_parts: int, filename: str = "<source>") -> str:
    """Turn `from core.x import y` into a relative import valid for a module `package_parts` packages below the
    add-on root (0 for the add-on's own modules, 2 for core/util/*.py). Raises InputError on `import core...`."""
    tree = ast.parse(source, filename=filename)
    lines = source.splitlines(keepends=True)
    dots = "." * (package_parts + 1)
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            for alias in node.names:
                if alias.name == "core" or alias.name.startswith("core."):
                    raise InputError(f"{filename}:{node.lineno}: 'import {alias.name}' cannot be vendored into the "
                                     f"add-on; write 'from core... import name' instead")
        elif isinstance(node, ast.ImportFrom) and node.level == 0 and node.module and (
                node.module == "core" or node.module.startswith("core.")):
            i, col = node.lineno - 1, node.col_offset
            head, tail = lines[i][:col], lines[i][col:]
            new_tail, n = _FROM_CORE.subn(f"from {dots}core", tail, count=1)
            if n != 1:
                raise InputError(f"{filename}:{node.lineno}: could not rewrite this import of core for the add-on")
            lines[i] = head + new_tail
    return "".join(lines)


def _copy_tree(src: Path, dst: Path, depth0: int) -> int:
    """Copy the .py files below `src` into `dst`, rewriting core imports; returns the number of files."""
    count = 0
    for path in sorted(src.rglob("*.py")):
        rel = path.relative_to(src)
        if "__pycache__" in rel.parts:
            continue
        out = dst / rel
        out.parent.mkdir(parents=True, exist_ok=True)
        text = path.read_text(encoding="utf-8")
        out.write_text(rewrite_core_imports(text, depth0 + len(rel.parts) - 1, str(path)), encoding="utf-8")
        count += 1
    return count


def _bl_info_version() -> str:
    """`bl_info["version"]` of the add-on's __init__.py as "x.y.z" (read with ast, never executed)."""
    init = ADDON_SOURCE / "__init__.py"
    for node in ast.parse(init.read_text(encoding="utf-8")).body:
        if isinstance(node, ast.Assign) and any(getattr(t, "id", "") == "bl_info" for t in node.targets):
            return ".".join(str(v) for v in ast.literal_eval(node.value)["version"])
    raise InputError(f"{init}: no bl_info dict (needed for the legacy add-on zip)")


def check_versions() -> str:
    """The manifest's version must equal the Python package's (pyproject.toml) and bl_info's; returns it."""
    manifest = tomllib.loads(MANIFEST.read_text(encoding="utf-8"))
    project = tomllib.loads((REPO / "pyproject.toml").read_text(encoding="utf-8"))["project"]
    versions = {"addon_manifest.toml": manifest.get("version"), "pyproject.toml": project.get("version"),
                "pointgt_blender bl_info": _bl_info_version()}
    if len(set(versions.values())) != 1:
        raise InputError(f"the add-on versions differ ({versions}); make them equal")
    return manifest["version"]


def _run_cli(args: list[str], what: str) -> str:
    proc = subprocess.run([sys.executable, str(blender_ext_cli()), *args], capture_output=True, text=True)
    out = (proc.stdout + proc.stderr).strip()
    if proc.returncode != 0 or "Error" in out or "error:" in out:
        raise InputError(f"Blender's extension validator rejected {what}:\n{out}")
    return out


def validate(path: str | Path) -> str:
    """Run Blender's validator on a staged folder or a built zip; returns its output, raises InputError."""
    return _run_cli(["validate", str(path), "--valid-tags", str(blender_valid_tags())], str(path))


def stage(dest: Path) -> Path:
    """Write the add-on's files (manifest, add-on modules, vendored core) into the empty folder `dest`."""
    if not (ADDON_SOURCE / "__init__.py").is_file():
        raise InputError(f"{ADDON_SOURCE}: the add-on package is missing")
    check_versions()
    dest.mkdir(parents=True, exist_ok=True)
    shutil.copyfile(MANIFEST, dest / "blender_manifest.toml")
    _copy_tree(ADDON_SOURCE, dest, 0)
    _copy_tree(CORE_SOURCE, dest / VENDORED, 1)
    return dest


def _legacy_zip(src: Path, dest: Path) -> None:
    """The same files under one top folder `pointgt/`, the layout legacy add-on installs expect (without the
    manifest, which would make Blender treat it as an extension)."""
    with zipfile.ZipFile(dest, "w", zipfile.ZIP_DEFLATED) as zf:
        for path in sorted(p for p in src.rglob("*") if p.is_file() and p.name != "blender_manifest.toml"):
            zf.write(path, f"pointgt/{path.relative_to(src).as_posix()}")


def build_addon(out_dir: str | Path, legacy: bool = False) -> Path:
    """Stage, validate and build `pointgt-<version>.zip` in `out_dir` (created); returns the zip's path.
    `legacy=True` builds `pointgt-<version>-legacy.zip` (top folder `pointgt/`, for Install from Disk as a
    legacy add-on). An existing zip of the same name is kept as `<name>.bak`."""
    from core.util.atomic import check_output_dir

    out_dir = check_output_dir(out_dir, "--out")
    out_dir.mkdir(parents=True, exist_ok=True)
    version = check_versions()
    target = out_dir / f"pointgt-{version}{'-legacy' if legacy else ''}.zip"
    with tempfile.TemporaryDirectory(prefix="pointgt-addon-") as tmp:
        src = stage(Path(tmp) / "pointgt")
        validate(src)
        built = Path(tmp) / "built.zip"
        if legacy:
            _legacy_zip(src, built)
        else:
            _run_cli(["build", "--source-dir", str(src), "--output-filepath", str(built),
                      "--valid-tags", str(blender_valid_tags())], str(src))
            validate(built)
        from core.util.atomic import atomic_path

        with atomic_path(target) as part:  # the temp folder may be on another disk: copy, then rename in place
            shutil.copyfile(built, part)
    return target
