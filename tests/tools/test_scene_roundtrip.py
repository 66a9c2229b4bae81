"""A generated scene loads with the NeRF-synthetic loader and its cameras agree with its images."""
import subprocess
import sys

import numpy as np
import pytest
import torch

from core.images.cameras import project_points
from core.images.dataset import load_split


@pytest.mark.blender
def test_generated_scene_round_trips_through_the_loader(tmp_path):
    out = tmp_path / "crate"
    res = subprocess.run([sys.executable, "-m", "tools.cli", "make-scene", "crate", "--out", str(out), "--size", "32",
                          "--views-train", "4", "--views-val", "1", "--views-test", "1", "--samples", "2"],
                         capture_output=True, text=True, timeout=300)
    assert res.returncode == 0, res.stderr[-2000:]
    for split, n in (("train", 4), ("val", 1), ("test", 1)):
        data = load_split(out, split, background=(1.0, 1.0, 1.0))
        assert data.images.shape == (n, 32, 32, 3) and data.alphas.shape == (n, 32, 32)
        assert data.height == data.width == 32
        centre = torch.zeros(1, 3, dtype=data.c2w.dtype)
        for v in range(n):
            uv, depth = project_points(centre, data.c2w[v], data.height, data.width, data.focal)
            col, row = uv[0].tolist()
            assert depth.item() > 3.0 and 0 <= col < 32 and 0 <= row < 32
            r, c = int(row), int(col)
            patch = data.alphas[v, max(r - 2, 0): r + 3, max(c - 2, 0): c + 3]
            assert patch.mean() > 0.9  # the solid crate covers its centre from every side
            # the object does not touch the image border: transparent corners composite to the background
            assert np.allclose(data.images[v, 0, 0].numpy(), 1.0, atol=1e-6)
