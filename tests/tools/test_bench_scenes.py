"""The scene-library bench's fit commands: extra fit flags reach every fit and name its model files."""
import json

import pytest

import tools.bench.scenes as scenes


def _run(tmp_path, monkeypatch, argv):
    (tmp_path / "cloth").mkdir()
    (tmp_path / "cloth" / "scene.json").write_text(json.dumps({"name": "cloth"}))
    calls = []

    def fake_run(cmd, echo):
        calls.append(cmd)
        out = cmd[cmd.index("--out") + 1]
        open(out, "w").close()

    def fake_result(model):
        return {"model": str(model), "decoder": "unet"}

    monkeypatch.setattr(scenes, "run_command", fake_run)
    monkeypatch.setattr(scenes, "fit_result", fake_result)
    monkeypatch.setattr(scenes, "markdown", lambda rows, header: header + "\n| row |")
    assert scenes.main(["--work", str(tmp_path), "--scenes", "cloth", *argv]) == 0
    return calls


def test_fit_args_reach_every_fit_and_name_its_models(tmp_path, monkeypatch):
    calls = _run(tmp_path, monkeypatch, ["--minutes", "1", "--fit-args", "--decoder-weight-decay 0.5", "--tag", "wd",
                                         "--seed", "1"])
    assert len(calls) == 2  # the default fit and the other decoder setting
    for cmd in calls:
        i = cmd.index("--decoder-weight-decay")
        assert cmd[i + 1] == "0.5" and cmd[cmd.index("--seed") + 1] == "1"
    outs = sorted(cmd[cmd.index("--out") + 1] for cmd in calls)
    assert outs == [str(tmp_path / "cloth.wd.s1.default.pgt"), str(tmp_path / "cloth.wd.s1.none.pgt")]


def test_default_names_unchanged_and_fit_args_need_a_tag(tmp_path, monkeypatch):
    calls = _run(tmp_path, monkeypatch, ["--steps", "5", "--no-pair"])
    assert [c[c.index("--out") + 1] for c in calls] == [str(tmp_path / "cloth.default.pgt")]
    with pytest.raises(SystemExit):
        scenes.main(["--work", str(tmp_path), "--fit-args", "--decoder none"])
    with pytest.raises(SystemExit):
        scenes.main(["--work", str(tmp_path), "--fit-args", "--decoder none", "--tag", "../x"])


def test_the_table_shows_the_guards_actions_and_verdicts():
    def fit(decoder, **kw):
        return {"psnr": 30.0, "psnr_object": 22.0, "decoder": decoder, "steps": 900, "seconds": 300.0,
                "blank": {"psnr": 14.0, "psnr_object": 5.0}, "guard_events": [], "collapsed": None, "declined": None,
                "profile": {"decoder": decoder, "k": 20, "charts": "8"}, "measured": {"pixels_per_point": 0.4}, **kw}

    rows = [{"scene": "logo", "default": fit("unet", guard_events=["restarted the fit with the same settings"],
                                             declined="the object PSNR fell from 20.00 dB at step 900 to 16.00 dB"),
             "other": [fit("none", psnr_object=21.0)]},
            {"scene": "cloth", "default": fit("unet", collapsed="the render covers 10 % of the object's pixels",
                                              declined="ignored when collapsed")}]
    table = scenes.markdown(rows, "head")
    logo, cloth = table.splitlines()[-2:]
    assert "restarted the fit with the same settings; DECLINED (the object PSNR fell from 20.00" in logo
    assert "| 22.00 | 21.00 | +0.00 |" in logo
    assert "COLLAPSED (the render covers 10 %" in cloth and "DECLINED" not in cloth
