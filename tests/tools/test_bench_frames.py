"""The frame benchmark runs end to end at tiny sizes and reports finite, consistent figures (Blender's first frame
after opening a .blend too)."""
import json
import math

import pytest

from tests.helpers.tiny import save_tiny
from tools.bench import blend_cold, frames


def test_frames_bench_tiny(tmp_path, capsys):
    out = tmp_path / "frames.json"
    rc = frames.main(["--points", "300", "--atlas-steps", "2", "--sizes", "16,24", "--frames", "1",
                      "--threads-list", "1", "--json", str(out)])
    assert rc == 0
    res = json.loads(out.read_text())
    text = capsys.readouterr().out
    assert "| size | threads |" in text and "cold first frame" in text and "machine:" in text
    cold = res["cold"]
    parts = ("imports_s", "load_s", "edit_inputs_s", "first_frame_s", "second_frame_s")
    assert all(cold[k] > 0 for k in parts)
    assert cold["process_s"] >= sum(cold[k] for k in parts)  # the whole process includes its parts
    assert [r["size"] for r in res["rows"]] == [16, 24]
    labels = {"no decoder: plain", "no decoder: deformed + painted", "UNet: plain", "UNet: deformed + painted"}
    for r in res["rows"]:
        assert set(r["cells"]) == labels
        for c in r["cells"].values():
            assert 0 < c["min_s"] <= c["median_s"] <= c["max_s"] < 60
    assert len(res["profile"]) == 4  # two sizes × two decoders, deformed + painted
    for p in res["profile"]:
        st = p["stages"]
        staged = sum(st.get(s, 0.0) for s in frames.STAGES)
        assert math.isfinite(st["total"]) and 0 < staged <= st["total"] * 1.05
        assert st["attention"] > 0 and st["neighbour search"] > 0 and st["texture lookup"] > 0
        assert (st.get("decoder", 0.0) > 0) == p["case"].startswith("UNet")


def test_fast_paths_bench_tiny(tmp_path):
    """Every fast path it times agrees with its torch form on a real frame (the table's last column)."""
    from tools.bench import fast_paths

    out = tmp_path / "fast.json"
    assert fast_paths.main(["--points", "400", "--atlas-steps", "2", "--size", "40", "--reps", "1",
                            "--distance", "5", "--json", str(out)]) == 0
    rows = {r["path"]: r for r in json.loads(out.read_text())["rows"]}
    assert {"point colours", "decoder", "texture lookup (anti-aliased)", "pixel filter"} <= set(rows)
    for r in rows.values():
        assert r["torch_s"] > 0 and r["fast_s"] > 0 and r["max_abs_diff"] <= 1e-5, r


@pytest.mark.blender
def test_blend_cold_bench_tiny(tmp_path, capsys):
    """--blend-cold builds the scene headless, opens it in fresh Blenders and times every part; the add-on's
    load_post warm-up starts for a packed and for an unpacked model; the first image equals the setup's."""
    model = save_tiny(tmp_path / "card.pgt", "fast")
    out = tmp_path / "blend.json"
    assert frames.main(["--blend-cold", "--model", str(model), "--blend-size", "32", "--blend-runs", "1",
                        "--threads", "1", "--blend-work", str(tmp_path / "work"), "--json", str(out)]) == 0
    res = json.loads(out.read_text())
    assert "| packed |" in capsys.readouterr().out
    assert math.isfinite(res["setup"]["first_render_ever_s"]) and res["setup"]["points"] > 0
    assert set(res["runs"]) == {"packed", "path"}
    for variant, runs in res["runs"].items():
        (r,) = runs
        assert all(math.isfinite(r[k]) and r[k] > 0 for k in blend_cold.STEPS + ("process_s",)), (variant, r)
        inside = r["import_bpy_s"] + r["prefs_s"] + r["open_s"] + r["first_frame_s"] + r["second_frame_s"]
        assert r["process_s"] >= inside and r["open_to_image_s"] >= r["first_frame_s"]
        assert r["warmup_started_on_load"] and r["warmup_error"] == "", (variant, r)
        assert r["image_diff"] == 0, variant
    assert {"import torch", "model load", "trace (neighbours, attention; numba's cache loaded)"} <= set(res["parts"])
    assert all(math.isfinite(v) for v in res["parts"].values()) and res["parts"]["import torch"] > 0
