"""tools.bench.atlas per-scene mode: which model file a scene uses, and the table with and without scores."""
from tools.bench.atlas import markdown_rows, scene_model


def test_scene_model_prefers_the_plain_name_then_the_library_bench_default(tmp_path):
    assert scene_model(tmp_path, "cloth") is None
    (tmp_path / "cloth.default.pgt").write_bytes(b"")
    assert scene_model(tmp_path, "cloth") == tmp_path / "cloth.default.pgt"
    (tmp_path / "cloth.pgt").write_bytes(b"")
    assert scene_model(tmp_path, "cloth") == tmp_path / "cloth.pgt"


def test_markdown_rows_with_and_without_scores():
    base = {"scene": "cloth", "layout": "islands", "size": "257x257", "utilisation": 0.6361, "round_trip": 1.0,
            "seconds": 41.2}
    scored = dict(base, atlas_colour=16.871, retexture=15.31, retexture_perfect=15.95, decal=19.07)
    grid = dict(scored, layout="grid", size="378x378", islands=0, retexture=16.2)
    lines = markdown_rows([dict(base, islands=18), scored, grid]).splitlines()
    assert len(lines) == 5 and all(line.count("|") == 11 for line in lines)
    assert "| islands | 257x257 | 18 | 63.6 % | 100.0 % | 41 | – | – | – |" in lines[2]
    assert "| islands | 257x257 | – |" in lines[3]  # a row without an island count
    assert lines[3].endswith("| 16.87 | 15.31 / 15.95 (0.64) | 19.07 |")
    assert "| grid | 378x378 | – |" in lines[4] and lines[4].endswith("| 16.20 / 15.95 (-0.25) | 19.07 |")
