"""A capture's own camera in Blender: a nerfstudio capture with a non-square image, an off-centre principal point
and fx != fy is loaded, a tiny model fitted to it, and the add-on's engine renders one of its views from a scene
camera set up with camera_settings + pixel_aspect; the frame must equal `pointgt render` for that view."""
from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import torch

from core.bundle import save_bundle
from core.images.cameras import Intrinsics
from core.images.colour import linear_to_srgb
from core.images.dataset import load_cameras, load_dataset
from core.images.png import read_png
from tests.helpers.synthetic import fibonacci_cameras, render_split, write_capture
from tests.helpers.tiny import fit_tiny
from tools.package_addon import build_addon

pytestmark = pytest.mark.blender
HERE = Path(__file__).parent
REPO = HERE.parents[1]
W, H = 48, 40
K = Intrinsics(40.0, 35.0, 21.0, 22.5)  # fx != fy (pixel aspect 8:7), principal point off the centre (24, 20)
VIEW = "test_1"


@pytest.fixture(scope="module")
def record(tmp_path_factory):
    tmp = tmp_path_factory.mktemp("capture")
    train = render_split("card", fibonacci_cameras(8, seed=0), W, height=H, intrinsics=K)
    test = render_split("card", fibonacci_cameras(2, seed=5), W, height=H, intrinsics=K, split="test")
    capture = write_capture(tmp / "capture", [train, test])
    data = load_dataset(capture, required=("train", "test"))
    assert data["train"].layout == "nerfstudio" and data["train"].focal == K
    model = save_bundle(tmp / "capture.pgt", fit_tiny("addon", data["train"], data["test"], atlas_steps=100),
                        backup=False)
    env = dict(os.environ, OMP_NUM_THREADS="1", PYTHONPATH=str(REPO))
    proc = subprocess.run([sys.executable, "-m", "tools.cli", "render", str(model), "--cameras",
                           str(capture / "transforms.json"), "--out", str(tmp / "ref"), "--device", "cpu"],
                          capture_output=True, text=True, env=env, cwd=REPO, timeout=600)
    assert proc.returncode == 0, proc.stderr[-3000:]
    cams = load_cameras(capture / "transforms.json")
    i = cams.names.index(VIEW)
    camera = {"c2w": cams.c2w[i].tolist(), "intrinsics": cams.focal.as_list(), "width": cams.width,
              "height": cams.height}
    (tmp / "camera.json").write_text(json.dumps(camera))
    work = tmp / "work"
    work.mkdir()
    env = dict(env, BLENDER_USER_RESOURCES=str(tmp / "blender_user"))
    proc = subprocess.run([sys.executable, str(HERE / "capture_render_script.py"), "--", str(build_addon(tmp / "dist")),
                           str(model), str(tmp / "camera.json"), str(work)],
                          capture_output=True, text=True, env=env, cwd=HERE, timeout=600)
    lines = [ln for ln in proc.stdout.splitlines() if ln.startswith("RESULTS: ")]
    assert lines, f"Blender script crashed (exit {proc.returncode}):\n{proc.stdout[-4000:]}\n{proc.stderr[-4000:]}"
    return {"r": json.loads(lines[-1][len("RESULTS: "):]), "ref": read_png(tmp / "ref" / f"{VIEW}.png"),
            "engine": work / "engine.npy", "camera": camera}


def test_scene_camera_reproduces_the_capture_camera(record):
    r = record["r"]
    for name in ("install", "scene", "camera"):
        assert "error" not in r[name], r[name]
    assert r["camera"]["aspect"] == pytest.approx([1.0, 40.0 / 35.0])  # fy < fx: taller pixels
    np.testing.assert_allclose(r["camera"]["intrinsics"], K.as_list(), rtol=1e-5)
    assert r["camera"]["c2w_err"] < 1e-6


def test_engine_frame_equals_pointgt_render(record):
    r = record["r"]
    assert r["render"].get("error") is None and r["render"]["size"] == [W, H], r["render"]
    got = np.load(record["engine"])  # scene-linear, premultiplied, float32
    ref = record["ref"]  # 8-bit PNG: straight sRGB colour, alpha
    assert got.shape == ref.shape == (H, W, 4)
    alpha = got[..., 3]
    assert (ref[..., 3] > 0.5).sum() > 50  # the card is in view
    # The PNG quantises colour and alpha to 8 bits (error <= 0.5/255 each); the engine's frame is float. 1/255
    # leaves 0.5/255 for float32 rounding in the engine's sRGB <-> linear round trip.
    assert np.abs(alpha - ref[..., 3]).max() <= 1.0 / 255
    # The PNG holds straight colour, quantised directly (<= 0.5/255); the engine's is premultiplied, so it is
    # divided by its own (float) alpha where that is large enough for float32 rounding not to matter.
    straight = linear_to_srgb(torch.from_numpy(got[..., :3] / np.maximum(alpha, 1e-12)[..., None]).clamp(0, 1))
    seen = alpha > 0.01
    err = float(np.abs(straight.numpy() - ref[..., :3])[seen].max())
    assert err <= 1.0 / 255, err
