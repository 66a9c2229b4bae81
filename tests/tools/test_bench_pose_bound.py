"""tools/bench/pose_bound.py: the low-pass of a texture function, the object PSNR and the table (the Blender side
is the eval-edits ground truth, tested there)."""
import math

import torch

from tools.bench.pose_bound import lowpassed, markdown, object_psnr, surface_projector


def test_lowpass_keeps_a_linear_texture_and_averages_a_step():
    def linear(x):
        return (x @ torch.tensor([[0.3, 0.1, 0.0], [0.2, 0.0, 0.5], [0.1, 0.4, 0.2]])) + 0.1

    x = torch.randn(50, 3)
    assert lowpassed(linear, 0.0) is linear
    assert torch.allclose(lowpassed(linear, 0.7)(x), linear(x), atol=1e-5)  # a symmetric mean of a linear map

    def step(x):
        return (x[:, :1] > 0).float().expand(-1, 3)

    on_edge = torch.zeros(1, 3)
    assert float(lowpassed(step, 1.0)(on_edge)[0, 0]) == 0.5  # half the cube on each side
    far = torch.tensor([[2.0, 0.0, 0.0]])
    assert float(lowpassed(step, 1.0)(far)[0, 0]) == 1.0
    assert torch.isfinite(lowpassed(step, 1e30)(x)).all()


def test_object_psnr_pools_the_union_of_both_masks():
    img = torch.ones(4, 4, 3)
    rgb = img.clone()
    rgb[0, 0] = 0.0  # one object pixel off by 1 in each channel
    gt_alpha = torch.zeros(4, 4)
    gt_alpha[:2, :2] = 1.0
    alpha = torch.zeros(4, 4)
    alpha[:2, :3] = 1.0  # the render covers 6 pixels: the union is 6
    assert math.isclose(object_psnr(rgb, alpha, img, gt_alpha), -10 * math.log10(3 / 18), rel_tol=1e-6)
    assert object_psnr(img, alpha, img, gt_alpha) > 100  # no error: finite, bounded by the 1e-12 floor


def test_markdown_gives_the_gap_to_rest():
    res = {"scene": "cloth", "texture": "flag", "views": 2,
           "poses": {"rest": {"render x": 30.0, "perfect texture": 29.0},
                     "stretch": {"render x": 23.5, "perfect texture": 29.5}}}
    text = markdown(res)
    assert "| stretch | 23.50 (-6.50) | 29.50 (+0.50) |" in text and "| rest | 30.00 | 29.00 |" in text


def test_surface_projector_moves_points_to_the_nearest_point_of_the_mesh():
    import numpy as np

    import bpy  # noqa: F401  (mathutils)
    from mathutils.bvhtree import BVHTree

    verts = np.array([[0.0, 0.0, 0.0], [1.0, 0.0, 0.0], [1.0, 1.0, 0.0], [0.0, 1.0, 0.0]])  # unit square at z = 0
    project = surface_projector(BVHTree.FromPolygons([tuple(v) for v in verts], [(0, 1, 2), (0, 2, 3)]))
    x = torch.tensor([[0.3, 0.6, 0.25], [0.5, 0.5, -0.1], [2.0, 0.5, 0.3], [float("nan"), 0.0, 0.0]])
    y = project(x)
    assert y.dtype == x.dtype and y.shape == x.shape
    assert torch.allclose(y[:3], torch.tensor([[0.3, 0.6, 0.0], [0.5, 0.5, 0.0], [1.0, 0.5, 0.0]]), atol=1e-6)
    assert torch.isnan(y[3, 0])  # a non-finite point stays as it is


def test_run_adds_the_decoder_free_rows_only_when_asked(tmp_path, monkeypatch):
    """`run` with Blender, the model and the renderer stubbed: the rows it scores per pose (the scene's texture name
    must not switch the decoder-free rows on)."""
    import json
    import types

    import core.bundle
    import core.edits.procedural
    import core.frames.edited
    import tools.bench.colour_field_bound
    import tools.bench.pose_bound as pb
    import tools.eval_edits

    (tmp_path / "scene.json").write_text(json.dumps({"name": "s", "bbox": {"center": [0, 0, 0], "half_size": 1.0},
                                                     "texture": {"base": "flag"}}))
    resets = []

    class Decoder:
        def reset_correction(self):
            resets.append(1)

    def load_bundle(path):
        cfg = types.SimpleNamespace(decoder_residual=True)
        return types.SimpleNamespace(model=types.SimpleNamespace(train_footprint=0.01, xyz=torch.zeros(4, 3),
                                                                 decoder=Decoder(), cfg=cfg))

    gt = types.SimpleNamespace(c2w=torch.eye(4)[None].repeat(2, 1, 1), height=4, width=4, focal=4.0,
                               images=torch.full((2, 4, 4, 3), 0.5), alphas=torch.ones(2, 4, 4))
    monkeypatch.setattr(core.bundle, "load_bundle", load_bundle)
    monkeypatch.setattr(tools.eval_edits, "ground_truth", lambda *a, **k: gt)
    monkeypatch.setattr(tools.eval_edits, "deform_points", lambda can, *a: can)
    monkeypatch.setattr(tools.eval_edits, "view_subset_dir", lambda scene, views: scene)
    monkeypatch.setattr(core.frames.edited, "EditState", lambda *a, **k: None)
    monkeypatch.setattr(core.frames.edited, "render_edited",
                        lambda *a, **k: {"rgb": torch.full((4, 4, 3), 0.4), "alpha": torch.ones(4, 4)})
    monkeypatch.setattr(core.edits.procedural, "evaluate", lambda name, x, *a: (torch.zeros_like(x),))
    monkeypatch.setattr(tools.bench.colour_field_bound, "rest_mesh_tree", lambda scene: None)
    monkeypatch.setattr(pb, "surface_projector", lambda tree: (lambda x: x))
    renderer = next(iter(tools.eval_edits.RENDERERS))
    for base_rows in (False, True):
        res = pb.run(tmp_path / "m.pgt", tmp_path, poses=("arm",), views=2, renderers=(renderer,),
                     footprints=(1.0,), base_rows=base_rows, log=lambda *a: None)
        rows = set(res["poses"]["arm"])
        assert ({f"render {renderer}, base"} <= rows) == base_rows
        assert {"perfect texture", "perfect texture on the surface", "texture at 1 px on the surface"} <= rows
        assert res["texture"] == "flag"
    assert len(resets) == 1  # the decoder's correction zeroed on the second (base) copy only
