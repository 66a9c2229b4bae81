"""tools.bench.regions: the per-region split of a frame's error (pure arithmetic; the Blender side runs in the
benchmark itself)."""
import math

import numpy as np

from tools.bench.regions import markdown, region_gains, rig_offsets


def test_region_gains_are_the_db_won_by_zeroing_each_region():
    err = np.array([0.3, 0.3, 0.03, 0.0])  # per pixel, summed over 3 channels
    m = {"a": np.array([True, False, False, False]), "ab": np.array([True, True, False, False]),
         "none": np.zeros(4, bool), "all": np.ones(4, bool)}
    g = region_gains(err, m)
    base = -10 * math.log10(0.63 / 12)
    assert math.isclose(g["a"][0], -10 * math.log10(0.33 / 12) - base)
    assert math.isclose(g["ab"][0], -10 * math.log10(0.03 / 12) - base)
    assert g["none"] == (0.0, 0) and g["a"][1] == 1 and g["ab"][1] == 2
    assert g["all"][0] > 100  # a perfect frame: bounded, finite
    assert math.isfinite(g["all"][0])


def test_markdown_has_a_row_per_renderer_and_every_region():
    regions = {f"{r} {w}": {"gain_db": 0.5, "pixels": 3} for r in ("hole", "spill", "deep", "ok")
               for w in ("joint", "elsewhere")}
    res = {"scene": "cloth", "pose": "arm", "magnitude": 1.0, "views": 2, "size": 64, "joint": 0.5, "tau": 0.15,
           "renderers": {"paper": {"psnr_object": 12.0, "regions": regions, "deep_joint_true_share": 0.2,
                                   "deep_joint_others_behind_spacings": 5.0}}}
    text = markdown(res)
    assert "| paper | 12.00 |" in text and text.count("0.50 / 3") == 8


def test_variant_changes_named_fields_of_a_renderer():
    import pytest

    from tools.bench.regions import parse_variant
    from tools.eval_edits import RENDERERS

    name, fields = parse_variant("f-fill-fold:f_fill_ratio=2.5,temperature=0.5,f_occlusion=true", RENDERERS)
    assert name == "f-fill-fold:f_fill_ratio=2.5,temperature=0.5,f_occlusion=true"
    assert fields == {**RENDERERS["f-fill-fold"], "f_fill_ratio": 2.5, "temperature": 0.5, "f_occlusion": True}
    with pytest.raises(SystemExit, match="unknown renderer"):
        parse_variant("nope:f_fill_ratio=2", RENDERERS)
    with pytest.raises(SystemExit, match="not FIELD=VALUE"):
        parse_variant("paper:no_such_field=1", RENDERERS)


def test_rig_offsets_measure_how_far_the_rig_put_the_points_from_the_mesh():
    """A rig that moves the points exactly as the mesh: 0; one that shifts the joint band's points by 3 spacings:
    3 there, 0 elsewhere; non-finite points and pixels are left out, an empty group is NaN."""
    g = np.random.default_rng(0)
    can = g.uniform(-1, 1, (400, 3))
    shift = np.where(np.abs(can[:, :1]) < 0.3, [[0.0, 0.0, 0.3]], 0.0)  # spacing 0.1: 3 spacings in the band
    true_can = can[:100] + 1e-4
    joint = np.abs(true_can[:, 0]) < 0.3
    exact = rig_offsets(can, can + 1.0, true_can, true_can + 1.0, joint, 0.1)
    assert exact["joint"][0] < 0.01 and exact["elsewhere"][1] < 0.01
    posed = can + 1.0 + shift
    posed[150] = np.nan
    tp = true_can + 1.0
    tp[5] = np.nan
    got = rig_offsets(can, posed, true_can, tp, joint, 0.1, near=1)
    assert abs(got["joint"][0] - 3.0) < 0.01 and got["elsewhere"][1] < 0.01
    none = rig_offsets(can, posed, true_can, tp, np.zeros(100, bool), 0.1)
    assert math.isnan(none["joint"][0]) and math.isfinite(none["elsewhere"][0])
