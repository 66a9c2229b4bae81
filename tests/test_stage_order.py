"""The stages import only earlier stages (images -> points -> atlas -> edits -> frames), and core never imports bpy.

Every import statement of every file under core/ is parsed (also the ones inside functions), so a late import
cannot hide a backwards dependency.
"""
from __future__ import annotations

import ast
from pathlib import Path

CORE = Path(__file__).resolve().parents[1] / "core"
STAGES = ("images", "points", "atlas", "edits", "frames")
# shared by every stage: configuration, errors/atomic writes/devices, the numpy-only model file
BASE = ("config", "util", "modelfile")


def imported_modules(source: str, module: str) -> list[tuple[int, str]]:
    """(line, dotted module name) of every import in `source`, relative imports resolved against `module`
    (the dotted name of the file, e.g. core.points.train)."""
    out = []
    for node in ast.walk(ast.parse(source)):
        if isinstance(node, ast.Import):
            out += [(node.lineno, a.name) for a in node.names]
        elif isinstance(node, ast.ImportFrom):
            base = node.module or ""
            if node.level:
                parent = module.split(".")[:-node.level]
                base = ".".join(parent + ([base] if base else []))
            # `from core import points` names a module too
            out += [(node.lineno, f"{base}.{a.name}" if base in ("core",) else base) for a in node.names]
    return sorted(set(out))


def violations(path: Path, source: str) -> list[str]:
    """Backwards stage imports and bpy imports of one file under core/."""
    rel = path.relative_to(CORE.parent).with_suffix("")
    module = ".".join(rel.parts)
    parts = rel.parts
    own = parts[1] if len(parts) > 2 else None  # core/<stage>/file.py; top-level core files are glue
    bad = []
    for line, name in imported_modules(source, module):
        top = name.split(".")
        if top[0] == "bpy":
            bad.append(f"{rel}.py:{line} imports bpy")
        if top[0] != "core" or len(top) < 2:
            continue
        target = top[1]
        if own in STAGES:
            if target in STAGES and STAGES.index(target) > STAGES.index(own):
                bad.append(f"{rel}.py:{line} (stage {own}) imports the later stage {target}: {name}")
            elif target not in STAGES and target not in BASE:
                bad.append(f"{rel}.py:{line} (stage {own}) imports the glue module {name}")
        elif own in BASE and target in STAGES:
            bad.append(f"{rel}.py:{line} (shared {own}) imports the stage {target}: {name}")
    return bad


def test_stages_import_only_earlier_stages_and_core_never_imports_bpy():
    files = sorted(CORE.rglob("*.py"))
    assert len(files) > 20
    bad = [v for f in files for v in violations(f, f.read_text(encoding="utf-8"))]
    assert not bad, "\n".join(bad)


def test_checker_flags_backwards_glue_and_bpy_imports():
    src = ("import torch\n"
           "from core.images.cameras import pixel_rays\n"
           "def f():\n"
           "    from core.frames.edited import render_edited\n"
           "    import bpy\n"
           "from ..pipeline import build_atlas\n"
           "from . import model\n")
    bad = violations(CORE / "points" / "fake.py", src)
    assert len(bad) == 3, bad
    assert "later stage frames" in bad[0] and "imports bpy" in bad[1] and "glue module core.pipeline" in bad[2]
    # the same imports are fine from the last stage except bpy and the glue
    assert len(violations(CORE / "frames" / "fake.py", src)) == 2
    assert violations(CORE / "images" / "fake.py", "from core.points import model\n")
    assert violations(CORE / "util" / "fake.py", "from core.atlas.atlas import Atlas\n")


def stage_imports() -> dict[str, set[str]]:
    """For each stage, the other stages its files import."""
    out = {s: set() for s in STAGES}
    for s in STAGES:
        for f in (CORE / s).rglob("*.py"):
            module = ".".join(f.relative_to(CORE.parent).with_suffix("").parts)
            for _, name in imported_modules(f.read_text(encoding="utf-8"), module):
                top = name.split(".")
                if top[0] == "core" and len(top) > 1 and top[1] in STAGES and top[1] != s:
                    out[s].add(top[1])
    return out


def test_architecture_page_lists_what_each_stage_imports():
    """docs/ARCHITECTURE.md's table names, per stage, the stages it imports: it must match the code."""
    page = (CORE.parent / "docs" / "ARCHITECTURE.md").read_text(encoding="utf-8")
    listed = {}
    for line in page.splitlines():
        cells = [c.strip() for c in line.strip().strip("|").split("|")]
        if len(cells) == 4 and cells[0] in STAGES:
            listed[cells[0]] = set() if cells[3] in ("–", "-") else {c.strip() for c in cells[3].split(",")}
    assert set(listed) == set(STAGES), listed
    assert listed == stage_imports()
