"""The frame benchmark runs end to end at tiny sizes and reports finite, consistent figures."""
import json
import math

from tools.bench import frames


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
