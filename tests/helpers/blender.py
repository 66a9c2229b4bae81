"""What the add-on tests share around their Blender subprocesses: the packaged add-on with the tiny trained model
in a fresh folder, running one Blender script and reading the record it prints, checking one recorded step, and
the enlarged image strips some tests write for the docs (POINTGT_DOC_IMAGES)."""
from __future__ import annotations

import json
import os
import subprocess
import sys
from dataclasses import dataclass
from pathlib import Path

from PIL import Image

from tests.helpers.tiny import save_tiny
from tools.package_addon import build_addon


@dataclass
class AddonSetup:
    """zip_path: the packaged add-on; model: the tiny "addon" model file; work: an empty folder for the script's
    outputs; env: the environment for Blender (its own BLENDER_USER_RESOURCES, one OpenMP thread)."""

    tmp: Path
    zip_path: Path
    model: Path
    work: Path
    env: dict


def addon_setup(tmp: Path) -> AddonSetup:
    """Package the add-on and save the tiny trained card model under `tmp` (a fresh folder)."""
    zip_path = build_addon(tmp / "dist")
    model = save_tiny(tmp / "card.pgt", "addon")
    work = tmp / "work"
    work.mkdir()
    env = dict(os.environ, BLENDER_USER_RESOURCES=str(tmp / "blender_user"), OMP_NUM_THREADS="1")
    return AddonSetup(tmp, zip_path, model, work, env)


def run_script(script: Path, args: list[str], env: dict | None = None, cwd: Path | None = None,
                timeout: float = 600):
    """Run a Blender script (bpy as a module) with `args` after `--`; returns its last `RESULTS: ` line, parsed.
    A script that printed none (a crash) fails the test with the end of its output."""
    proc = subprocess.run([sys.executable, str(script), "--", *args], capture_output=True, text=True, env=env,
                          timeout=timeout, cwd=cwd)
    lines = [ln for ln in proc.stdout.splitlines() if ln.startswith("RESULTS: ")]
    assert lines, f"Blender script crashed (exit {proc.returncode}):\n{proc.stdout[-4000:]}\n{proc.stderr[-4000:]}"
    return json.loads(lines[-1][len("RESULTS: "):])


def step_result(results: dict, step: str):
    """The recorded result of one step; fails with its traceback when the step raised (script_common.recorder
    records {"error", "trace"} then; a step may return an "error" of its own, which is not a failure)."""
    res = results[step]
    failed = isinstance(res, dict) and "error" in res and isinstance(res.get("trace"), str)
    assert not failed, f"{step} failed: {res['trace']}"
    return res


def image_strip(paths, target: Path) -> None:
    """Frames side by side, 3x enlarged (nearest), 4 px apart, saved as a PNG for the docs."""
    target.parent.mkdir(parents=True, exist_ok=True)
    ims = [Image.open(p).convert("RGB") for p in paths]
    w, h = ims[0].size
    canvas = Image.new("RGB", (len(ims) * (3 * w + 4) - 4, 3 * h), "white")
    for i, im in enumerate(ims):
        canvas.paste(im.resize((3 * w, 3 * h), Image.NEAREST), (i * (3 * w + 4), 0))
    canvas.save(target, optimize=True)
