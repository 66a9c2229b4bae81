"""`python -m tools.bench.gt_noise`: Cycles' noise in the ground truth falls with the sample count (tiny scene,
Blender in a subprocess)."""
from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[2]


@pytest.mark.blender
def test_noise_falls_with_the_sample_count(tmp_path):
    out = tmp_path / "noise.json"
    proc = subprocess.run([sys.executable, "-m", "tools.bench.gt_noise", "--work", str(tmp_path), "--scenes", "cloth",
                           "--size", "24", "--views", "2", "--samples", "1,16", "--reference", "128",
                           "--json", str(out), "--markdown", str(tmp_path / "noise.md")],
                          cwd=ROOT, capture_output=True, text=True, timeout=600)
    assert proc.returncode == 0, proc.stdout[-2000:] + proc.stderr[-3000:]
    (row,) = json.loads(out.read_text())
    one, sixteen = row["samples"]["1"]["psnr_object"], row["samples"]["16"]["psnr_object"]
    assert row["scene"] == "cloth" and not row["lit"]
    assert 5.0 < one < sixteen < 80.0, row                    # more samples, less noise against the reference
    assert all(v["s_per_view"] > 0 for v in row["samples"].values())
    assert (tmp_path / "cloth" / "noise" / "16" / "test" / "r_1.png").exists()
    assert "| cloth | no |" in (tmp_path / "noise.md").read_text()
