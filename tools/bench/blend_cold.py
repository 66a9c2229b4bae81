"""Blender's first frame after opening a .blend (`python -m tools.bench.frames --blend-cold`): the scene is made once
by `blend_script.py setup`, then every run is a fresh bpy process (`blend_script.py open`) timed from inside
(per step, wall and CPU seconds) and from outside (the whole process). See tools/bench/frames.py for the flags."""
from __future__ import annotations

import json
import os
import statistics
import subprocess
import sys
import time
from pathlib import Path

SCRIPT = Path(__file__).with_name("blend_script.py")
VARIANTS = ("packed", "path")  # the model packed into the .blend (the import's default) | read from the .pgt
STEPS = ("import_bpy_s", "prefs_s", "open_s", "first_frame_s", "first_frame_cpu_s", "open_to_image_s",
         "open_to_image_cpu_s", "second_frame_s")


def _run_script(args: list[str], env: dict, timeout: float) -> tuple[dict, float]:
    """Run blend_script.py with `args`; (its RESULTS record, the process's wall seconds)."""
    t = time.perf_counter()
    proc = subprocess.run([sys.executable, str(SCRIPT), "--", *args], capture_output=True, text=True, env=env,
                          timeout=timeout, check=False)
    wall = time.perf_counter() - t
    lines = [ln for ln in proc.stdout.splitlines() if ln.startswith("RESULTS: ")]
    if proc.returncode or not lines:
        raise RuntimeError(f"blend_script.py {args[0]} failed (exit {proc.returncode}):\n"
                           f"{proc.stdout[-2000:]}\n{proc.stderr[-2000:]}")
    return json.loads(lines[-1][len("RESULTS: "):]), wall


def blender_env(work: Path, threads: int) -> dict:
    """Blender's environment for the runs: its own user folder under `work` (preferences with the add-on
    enabled, the installed add-on and its numba cache), `threads` OpenMP threads (0: the default), and no
    PYTHONPATH: the add-on runs from its installed copy, as in an artist's Blender."""
    env = {k: v for k, v in os.environ.items() if k != "PYTHONPATH"}
    env["BLENDER_USER_RESOURCES"] = str(work / "blender_user")
    if threads > 0:
        env["OMP_NUM_THREADS"] = env["MKL_NUM_THREADS"] = str(threads)
    return env


def setup_scene(model: str | os.PathLike, work: Path, size: int, timeout: float = 900) -> dict:
    """Package the add-on from this checkout and build the scene in `work` (path.blend, packed.blend; see
    blend_script.py). Returns the setup run's record (incl. first_render_ever_s: the first F12 after
    installing, which compiles the numba kernels) and setup_s, its process's wall seconds."""
    from tools.package_addon import build_addon

    work.mkdir(parents=True, exist_ok=True)
    zip_path = build_addon(work / "dist")
    res, wall = _run_script(["setup", str(zip_path), str(Path(model).resolve()), str(work), str(size)],
                         blender_env(work, 1), timeout)
    res["setup_s"] = wall
    return res


def open_run(work: Path, variant: str, threads: int, wait: float = 0.0, timeout: float = 600) -> dict:
    """One fresh Blender opening work/<variant>.blend and pressing F12 twice (`wait` seconds after opening);
    the record of blend_script.py open plus process_s, the whole process's wall seconds seen from here, and
    image_diff: the largest difference (8-bit levels) of its first image from the setup's F12 of the same pose."""
    import numpy as np
    from PIL import Image

    png = work / f"open_{variant}.png"
    res, wall = _run_script(["open", str(work / f"{variant}.blend"), str(png), str(wait)], blender_env(work, threads),
                         timeout)
    res["process_s"] = wall
    a, b = (np.asarray(Image.open(p), dtype=np.int16) for p in (png, work / "setup.png"))
    res["image_diff"] = int(np.abs(a - b).max()) if a.shape == b.shape else 255
    return res


def blend_cold(model: str | os.PathLike, work: Path, size: int, runs: int, threads: int, wait: float = 0.0,
               variants=VARIANTS, log=print) -> dict:
    """Set up once, then `runs` rounds of one fresh Blender per variant (interleaved), then one more Blender that
    times the parts of the first variant's first image on their own (blend_script.py parts). Returns {"setup":
    record, "runs": {variant: [record per run]}, "median": {variant: {step: median seconds}}, "parts": {part: CPU
    seconds}, "load": [1-minute load average before, after]}."""
    load = [os.getloadavg()[0]]
    setup = setup_scene(model, work, size)
    log(f"setup: {setup['points']} points, {size}² PointGT engine; first F12 after installing the add-on "
        f"{setup['first_render_ever_s']:.2f} s (compiles the numba kernels into its cache)")
    out = {v: [] for v in variants}
    for _ in range(runs):
        for v in variants:
            out[v].append(open_run(work, v, threads, wait))
    parts, _ = _run_script(["parts", str(work / f"{variants[0]}.blend"), str(work / "parts.png")],
                        blender_env(work, threads), 600)
    load.append(os.getloadavg()[0])
    med = {v: {k: statistics.median(r[k] for r in rs) for k in STEPS + ("process_s",)} for v, rs in out.items()}
    return {"setup": setup, "runs": out, "median": med, "parts": parts["parts_cpu_s"], "load": load}


def table(res: dict) -> list[str]:
    """Markdown rows: median (min–max) wall seconds per variant and step, CPU seconds beside the first image's,
    in how many runs the warm-up started on load / had finished before F12 / by the first image, and the largest
    difference of a first image from the setup's (8-bit levels)."""
    rows = ["| model in the .blend | process wall s | import bpy s | prefs s | open s | F12 → image s | CPU s | "
            "open → image s | CPU s | second F12 s | warm-up started / done before F12 / by the image | image diff |",
            "|" + "---|" * 12]

    def cell(rs, k):
        xs = [r[k] for r in rs]
        return f"{statistics.median(xs):.2f}" + (f" ({min(xs):.2f}–{max(xs):.2f})" if len(xs) > 1 else "")

    for v, rs in res["runs"].items():
        started = sum(bool(r["warmup_started_on_load"]) for r in rs)
        before = sum(bool(r["warmup_done_before_f12"]) for r in rs)
        done = sum(bool(r["warmup_done_by_first_image"]) for r in rs)
        rows.append(f"| {v} | " + " | ".join(cell(rs, k) for k in ("process_s",) + STEPS) +
                    f" | {started} / {before} / {done} of {len(rs)} | {max(r['image_diff'] for r in rs)} |")
    return rows
