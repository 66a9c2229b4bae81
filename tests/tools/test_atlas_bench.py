"""tools.bench.atlas per-scene mode: which model file a scene uses, and the table with and without scores."""
from tools.bench.atlas import markdown_rows, scene_mirror, scene_model


def test_scene_model_prefers_the_plain_name_then_the_library_bench_default(tmp_path):
    assert scene_model(tmp_path, "cloth") is None
    (tmp_path / "cloth.default.pgt").write_bytes(b"")
    assert scene_model(tmp_path, "cloth") == tmp_path / "cloth.default.pgt"
    (tmp_path / "cloth.pgt").write_bytes(b"")
    assert scene_model(tmp_path, "cloth") == tmp_path / "cloth.pgt"


def test_scene_model_with_a_tag_reads_only_that_settings_library_fit(tmp_path):
    (tmp_path / "cloth.pgt").write_bytes(b"")
    (tmp_path / "cloth.default.pgt").write_bytes(b"")
    assert scene_model(tmp_path, "cloth", "vd") is None  # never falls back to another setting's fit
    (tmp_path / "cloth.vd.default.pgt").write_bytes(b"")
    assert scene_model(str(tmp_path), "cloth", "vd") == tmp_path / "cloth.vd.default.pgt"


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


def test_scene_mirror_keeps_ground_truth_out_of_a_read_only_scene(tmp_path):
    import json
    import os
    import stat

    from tools.eval_edits import view_subset_dir
    scene = tmp_path / "lib" / "cloth"
    scene.mkdir(parents=True)
    (scene / "scene.blend").write_bytes(b"blend")
    (scene / "scene.json").write_text("{}")
    (scene / "transforms_test.json").write_text(json.dumps({"frames": [{"i": i} for i in range(6)]}))
    os.chmod(scene, stat.S_IRUSR | stat.S_IXUSR)  # the library is read-only
    try:
        mirror = scene_mirror(scene, tmp_path / "work")
        sub = view_subset_dir(mirror, 2)
        assert sub.parent == mirror and (sub / "scene.blend").read_bytes() == b"blend"
        assert len(json.loads((sub / "transforms_test.json").read_text())["frames"]) == 2
        assert sorted(p.name for p in scene.iterdir()) == ["scene.blend", "scene.json", "transforms_test.json"]
        assert scene_mirror(scene, tmp_path / "work") == mirror  # reused
    finally:
        os.chmod(scene, stat.S_IRWXU)


def test_lookups_and_footprint_variants_parse_and_refuse_bad_entries():
    """--lookups "lookup:bake[:k]" and --footprint-variants "[lookup:]lambdas" (tools/bench/atlas.py)."""
    import pytest

    from core.atlas.config import AtlasConfig
    from core.frames.edited import EditConfig
    from core.util.errors import InputError
    from tools.bench.atlas import parse_lookups, split_variant

    assert parse_lookups("") == [("samples", "auto", EditConfig().lookup_k)]
    assert parse_lookups("charts:samples, samples:fit:8") == [("charts", "samples", EditConfig().lookup_k),
                                                               ("samples", "fit", 8)]
    for bad in ("samples", "pixels:fit", "samples:splat", "samples:fit:0", "samples:fit:x", "samples:fit:2:1"):
        with pytest.raises(InputError, match="--lookups"):
            parse_lookups(bad)
    cfg = AtlasConfig()
    assert split_variant("1,4", cfg) == (cfg.footprint_lookup, "1,4")
    assert split_variant("charts:16", cfg) == ("charts", "16")
    with pytest.raises(InputError, match="samples or charts"):
        split_variant("texels:1", cfg)
    with pytest.raises(InputError):
        split_variant("charts:-1", cfg)
