"""The main job's 4x still: render_scaled gives the split's own frame at factor 1 and a finite frame of the same
view at 4x the size."""
import torch

from core.frames.edited import EditState, render_edited
from tests.helpers.tiny import tiny_bundle
from tools.demo import render_scaled


def test_render_scaled_matches_the_split_frame_and_scales():
    bundle, _, test = tiny_bundle("card")
    state = EditState(bundle, points=bundle.model.xyz.detach() * torch.tensor([1.5, 1.0, 1.0]))
    cam = test.c2w[0]
    one = render_scaled(state, cam, test, 1)
    ref = render_edited(state, cam, test.height, test.width, test.focal)["rgb"]
    assert torch.equal(one["rgb"], ref)
    big = render_scaled(state, cam, test, 4)
    assert big["rgb"].shape == (4 * test.height, 4 * test.width, 3) and bool(torch.isfinite(big["rgb"]).all())
    # the same view: the 4x frame averaged down over 4 x 4 blocks stays close to the 1x frame
    down = big["rgb"].reshape(test.height, 4, test.width, 4, 3).mean((1, 3))
    assert float((down - ref).abs().mean()) < 0.05
    assert big["seconds"] > 0


def test_reuse_message_names_the_scenes_samples_and_how_to_render_more(tmp_path):
    import json

    from tools.demo import reuse_message

    scene = tmp_path / "out" / "scene"
    scene.mkdir(parents=True)
    assert reuse_message(scene, "cloth", 64) == "reusing the existing scene"          # no scene.json: plain
    (scene / "scene.json").write_text("{not json")
    assert reuse_message(scene, "cloth", 64) == "reusing the existing scene"
    (scene / "scene.json").write_text(json.dumps({"render": {"samples": 16}}))
    few = reuse_message(scene, "cloth", 64)
    assert "16 Cycles samples" in few and "new --out folder" in few and str(tmp_path / "out") in few and "64" in few
    (scene / "scene.json").write_text(json.dumps({"render": {"samples": 64}}))
    assert reuse_message(scene, "cloth", 64) == "reusing the existing scene (64 Cycles samples per pixel)"


def test_report_guard_warns_on_a_late_decline_and_stops_on_a_blank_model(capsys):
    from tools.demo import report_guard

    fell = "the object PSNR fell from 24.00 dB at step 400 to 19.50 dB (coverage 0.88)"
    event = {"step": 120, "action": "refit", "reason": "the object PSNR fell 4.1 dB"}
    assert report_guard([{"step": 1}, {"step": 9, "guard": {"events": [event], "declined": fell}}])
    out = capsys.readouterr()
    assert "the collapse guard at step 120: refit (the object PSNR fell 4.1 dB)" in out.out
    assert "WARNING: the fit lost quality late in its budget: " + fell in out.err and "ERROR" not in out.err
    blank = {"guard": {"collapsed": "object PSNR 5.1 dB at the blank frame's", "declined": fell}}
    assert not report_guard([blank])
    err = capsys.readouterr().err
    assert "ERROR: the trained model renders the blank frame" in err and "WARNING" not in err  # one message
    assert report_guard([blank], allow_blank=True) and "ERROR" in capsys.readouterr().err
    assert report_guard([{"step": 9}]) and capsys.readouterr() == ("", "")  # a healthy fit: nothing said
