"""The issue's done-when pose: Automatic Weights on the surface proxy, the right bone turned up to 90 degrees,
paint written through the proxy's UV map; where the paint lands in F12 against where the deformed proxy has it
(pose90_script.py, one Blender subprocess with the tiny card model)."""
from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import pytest

from tests.helpers.tiny import save_tiny
from tools.package_addon import build_addon

pytestmark = pytest.mark.blender
HERE = Path(__file__).parent


@pytest.fixture(scope="module")
def record(tmp_path_factory):
    tmp = tmp_path_factory.mktemp("pose90")
    zip_path = build_addon(tmp / "dist")
    model = save_tiny(tmp / "card.pgt", "addon")
    work = tmp / "work"
    work.mkdir()
    env = dict(os.environ, BLENDER_USER_RESOURCES=str(tmp / "blender_user"), OMP_NUM_THREADS="1")
    proc = subprocess.run([sys.executable, str(HERE / "pose90_script.py"), "--", str(zip_path), str(model),
                           str(work)], capture_output=True, text=True, env=env, timeout=600, cwd=tmp)
    lines = [ln for ln in proc.stdout.splitlines() if ln.startswith("RESULTS: ")]
    assert lines, f"Blender script crashed (exit {proc.returncode}):\n{proc.stdout[-4000:]}\n{proc.stderr[-4000:]}"
    if os.environ.get("POINTGT_DOC_IMAGES"):  # docs/addon.md shows these frames
        from tests.helpers.blender import image_strip

        image_strip([work / f"pose{a}_deform_aware.png" for a in (0, 45, 90)],
                    Path(os.environ["POINTGT_DOC_IMAGES"]) / "addon_pose_0_45_90.png")
    return json.loads(lines[-1][len("RESULTS: "):])


def _get(r, name):
    res = r[name]
    assert "trace" not in res, f"{name} failed: {res.get('trace')}"
    return res


def test_setup_paints_through_the_proxy_and_weights_it(record):
    r = _get(record, "setup")
    assert r["import"] == ["FINISHED"] and r["parent"] == ["FINISHED"]
    for spot in ("far", "joint"):
        texels, faces = r[spot]
        assert faces >= 4 and texels >= 10, r


@pytest.mark.parametrize("angle", [0, 45, 90])
def test_points_follow_the_deformed_proxy(record, angle):
    r = _get(record, f"pose{angle}")
    assert r["points_near"] >= 20 and r["points_vs_proxy"] < 0.01, r  # Surface Deform carries them exactly


def test_f12_reports_progress_per_stage(record):
    p = _get(record, "pose0")["DEFORM_AWARE"]["progress"]
    assert len(p) == 4 and p == sorted(p) and p[0] == 0.0 and p[-1] == 1.0, p  # loading, tracing, shading, done


def test_paint_at_rest_lands_where_the_proxy_has_it(record):
    d = _get(record, "pose0")["DEFORM_AWARE"]
    assert d["error"] == "", d
    for spot in ("far", "joint"):  # 128 x 96 px, 0.017 units per pixel
        assert d[spot]["pixels"] >= 20 and d[spot]["drift_px"] < 3.5, d


@pytest.mark.parametrize("angle", [45, 90])
def test_paint_follows_the_pose(record, angle):
    """The disc sits where the deformed proxy has it at 45 and at 90 degrees, with deform-aware (the paper's)
    and with the default deform-gradient: within 3.5 px (0.06 units), and the pose adds at most 1.5 px (0.025 units) to
    what the render is off at rest (measured: 1.0 px for the disc on the turned half at 90 degrees)."""
    r = _get(record, f"pose{angle}")
    for corr in ("DEFORM_AWARE", "DEFORM_GRADIENT"):
        d = r[corr]
        assert d["error"] == "", r
        for spot in ("far", "joint"):
            assert d[spot]["pixels"] >= 20 and d[spot]["drift_px"] < 3.5 and d[spot]["added_px"] < 1.5, \
                (corr, spot, r)
