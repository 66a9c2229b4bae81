"""The library edit benchmark's summary: rest, worst pose and gap per renderer and edit, from eval-edits rows."""
import json
from pathlib import Path

import pytest

from tools.bench.edits_library import fit_command, gaps, main, markdown
from tools.bench.scenes import model_path


def _row(pose, mag, edit, renderer, psnr_object, corr="deform-aware", blend="soft"):
    return {"pose": pose, "magnitude": mag, "edit": edit, "correspondence": "-" if edit == "geometry" else corr,
            "temperature": 1.0, "blend": blend, "renderer": renderer, "psnr_object": psnr_object,
            "seconds_per_frame": 0.1}


def test_worst_pose_gap_and_count_within_3_db():
    rows = [_row("rest", 0.0, "geometry", "paper", 20.0), _row("bend", 1.0, "geometry", "paper", 19.0),
            _row("stretch", 1.0, "geometry", "paper", 12.0), _row("rest", 0.0, "retexture", "paper", 18.0),
            _row("bend", 1.0, "retexture", "paper", 17.5), _row("stretch", 1.0, "retexture", "paper", 16.0),
            # ignored: other correspondence, threshold blend, another magnitude
            _row("stretch", 1.0, "retexture", "paper", 1.0, corr="naive"),
            _row("stretch", 1.0, "retexture", "paper", 1.0, blend="threshold"),
            _row("stretch", 0.5, "geometry", "paper", 1.0)]
    out = gaps({"renderers": ["paper"], "rows": rows})
    assert len(out) == 1
    g, t = out[0]["geometry"], out[0]["retexture"]
    assert g["worst_pose"] == "stretch" and abs(g["gap"] - 8.0) < 1e-9 and (g["within"], g["poses"]) == (1, 2)
    assert t["worst_pose"] == "stretch" and abs(t["gap"] - 2.0) < 1e-9 and (t["within"], t["poses"]) == (2, 2)
    text = markdown({"cloth": out}, "head")
    assert "| cloth | paper | 20.00 / stretch 8.00 | 18.00 / stretch 2.00 | 1/2, 2/2 |" in text


def test_the_table_reads_the_first_listed_correspondence():
    rows = [_row("rest", 0.0, "retexture", "D", 20.0), _row("stretch", 1.0, "retexture", "D", 14.0),
            _row("rest", 0.0, "retexture", "D", 20.0, corr="deform-gradient"),
            _row("stretch", 1.0, "retexture", "D", 19.0, corr="deform-gradient")]
    listed = {"renderers": ["D"], "rows": rows, "correspondences": ["deform-gradient", "deform-aware"]}
    assert abs(gaps(listed)[0]["retexture"]["gap"] - 1.0) < 1e-9  # the first listed: deform-gradient
    assert abs(gaps(listed, "deform-aware")[0]["retexture"]["gap"] - 6.0) < 1e-9
    assert abs(gaps({"renderers": ["D"], "rows": rows})[0]["retexture"]["gap"] - 6.0) < 1e-9  # none listed


def test_fit_args_reach_the_scene_bench_under_their_tag():
    base = fit_command(Path("W"), "suzanne", 1, [], ["--steps", "1000"])
    assert base == ["tools.bench.scenes", "--work", "W", "--scenes", "suzanne", "--no-pair", "--threads", "1",
                    "--steps", "1000"]
    tagged = fit_command(Path("W"), "suzanne", 1, [], ["--steps", "1000"], "--view-dependent", "vd")
    assert tagged == base + ["--fit-args", "--view-dependent", "--tag", "vd"]
    # the file the scene bench writes for that setting, which the edits bench then reads
    assert model_path(Path("W"), "suzanne", None, "vd").name == "suzanne.vd.default.pgt"


@pytest.mark.parametrize("argv", [["--fit-args=--view-dependent"], ["--tag", "vd"]])
def test_fit_args_and_tag_go_together(argv, tmp_path, capsys):
    with pytest.raises(SystemExit):
        main(["--work", str(tmp_path)] + argv)
    assert "--fit-args and --tag go together" in capsys.readouterr().err


def test_downscale_makes_finer_scenes_and_fits_from_them():
    """--downscale 4: the scene at 4 x 128², the fit reads it at 128² (`pointgt fit --downscale 4`)."""
    cmd = fit_command(Path("W"), "strip", 1, [], ["--minutes", "5"], "--view-dependent", "vd", downscale=4)
    assert cmd[cmd.index("--size") + 1] == "512"
    assert cmd[cmd.index("--fit-args") + 1] == "--view-dependent --downscale 4" and cmd[-1] == "vd"


def test_a_scene_made_at_another_size_is_refused(tmp_path):
    """A --work folder whose scene was made at 128² is not fitted from as if it were 512² (and the reverse)."""
    (tmp_path / "cloth").mkdir()
    (tmp_path / "cloth" / "scene.json").write_text(json.dumps({"camera": {"width": 128}}))
    with pytest.raises(SystemExit, match="made at 128², this run fits from 512²"):
        main(["--work", str(tmp_path), "--scenes", "cloth", "--downscale", "4"])


@pytest.mark.parametrize("value", ["0", "9"])
def test_downscale_out_of_range_is_refused(tmp_path, capsys, value):
    with pytest.raises(SystemExit):
        main(["--work", str(tmp_path), "--downscale", value])
    assert "--downscale" in capsys.readouterr().err
