"""Compositing and caches of pointgt_blender/bridge/frame_renderer.py, against plain references (no Blender)."""
import numpy as np
import pytest

from core.util.errors import InputError, ModelFileError
from pointgt_blender.bridge.frame_renderer import ModelCache, ObjectInputs, StateCache, composite


def _layers(rng, n=3, h=5, w=4):
    out = []
    for _ in range(n):
        a = rng.uniform(0, 1, (h, w)).astype(np.float32)
        c = rng.uniform(0, 1, (h, w, 3)).astype(np.float32)
        d = rng.uniform(1, 5, (h, w)).astype(np.float32)
        d[rng.uniform(size=(h, w)) < 0.2] = np.inf  # off this object
        out.append({"premul": a[..., None] * c, "alpha": a, "depth": d})
    return out


def _reference(layers, bg, transparent):
    h, w = layers[0]["alpha"].shape
    rgb = np.zeros((h, w, 3), np.float32)
    alpha = np.zeros((h, w), np.float32)
    for r in range(h):
        for c in range(w):
            acc, acc_a = np.zeros(3), 0.0
            for l in sorted(layers, key=lambda l: l["depth"][r, c]):
                acc = acc + (1 - acc_a) * l["premul"][r, c]
                acc_a = acc_a + (1 - acc_a) * l["alpha"][r, c]
            rgb[r, c] = acc / acc_a if transparent and acc_a > 1e-6 else (0 if transparent else acc + (1 - acc_a) * bg)
            alpha[r, c] = acc_a
    return rgb, alpha


@pytest.mark.parametrize("transparent", [False, True])
def test_composite_matches_per_pixel_reference(transparent):
    layers = _layers(np.random.default_rng(0))
    bg = np.array([0.2, 0.5, 0.9], np.float32)
    rgb, alpha = composite(layers, background=bg, transparent=transparent)
    ref_rgb, ref_a = _reference(layers, bg, transparent)
    np.testing.assert_allclose(alpha, ref_a, atol=1e-6)
    np.testing.assert_allclose(rgb, np.clip(ref_rgb, 0, 1), atol=1e-5)


def test_composite_is_finite_for_empty_and_nan_layers():
    h, w = 3, 3
    layer = {"premul": np.full((h, w, 3), np.nan, np.float32), "alpha": np.zeros((h, w), np.float32),
             "depth": np.full((h, w), np.inf, np.float32)}
    rgb, alpha = composite([layer], background=(1, 1, 1), transparent=True)
    assert np.isfinite(rgb).all() and (alpha == 0).all()
    with pytest.raises(InputError, match="no PointGT object"):
        composite([])


def _inputs(pos, atlas=None):
    return ObjectInputs(name="o", model_path="m.pgt", device="cpu", k=8, correspondence="DEFORM_AWARE",
                        point_count=len(pos), positions=pos, ids=np.arange(len(pos)), atlas=atlas)


def test_state_cache_rebuilds_only_when_inputs_change(monkeypatch):
    import pointgt_blender.bridge.frame_renderer as fr

    built = []
    monkeypatch.setattr(fr, "EditState", lambda *a, **k: built.append(1) or object())
    cache = StateCache()
    bundle, cfg = object(), fr.EditConfig()
    pos = np.zeros((4, 3), np.float32)
    s1, new1 = cache.get(_inputs(pos), bundle, cfg)
    pos[0, 0] = 0.0  # same values written again (a frame change that moved nothing)
    s2, new2 = cache.get(_inputs(pos.copy()), bundle, cfg)
    assert s1 is s2 and new1 and not new2
    pos[1, 2] = 1e-3
    s3, new3 = cache.get(_inputs(pos), bundle, cfg)
    s4, new4 = cache.get(_inputs(pos, atlas=np.zeros((2, 2, 3), np.float32)), bundle, cfg)
    assert new3 and new4 and s3 is not s2 and len(built) == 3


def test_state_cache_passes_the_prepared_paint_to_a_new_pose(monkeypatch):
    """A new pose of an unchanged atlas builds its state from the previous one's painted textures (paint_from);
    a changed atlas does not."""
    import pointgt_blender.bridge.frame_renderer as fr

    made = []
    monkeypatch.setattr(fr, "EditState", lambda *a, **k: made.append(k.get("paint_from")) or object())
    cache = StateCache()
    bundle, cfg = object(), fr.EditConfig()
    pos = np.zeros((4, 3), np.float32)
    atlas = np.full((2, 2, 3), 0.5, np.float32)
    s1, _ = cache.get(_inputs(pos, atlas=atlas), bundle, cfg)
    pos[1, 2] = 1e-3  # a new pose
    s2, _ = cache.get(_inputs(pos, atlas=atlas.copy()), bundle, cfg)
    painted = atlas.copy()
    painted[0, 0] = 0.9  # a stroke
    cache.get(_inputs(pos, atlas=painted), bundle, cfg)
    cache.get(_inputs(pos, atlas=painted), object(), cfg)  # another model (its file changed)
    assert made == [None, s1, None, None]


@pytest.mark.parametrize("field, values, config, default, configured", [
    ("antialias", (2, 1, 1), "antialias", 2, (2, 1)),
    ("occlusion", (True, False, False), "f_occlusion", True, (True, False)),
    ("reshade", ("OFF", "AUTO", "AUTO"), "reshade", "OFF", ("off", "auto"))])
def test_prepare_passes_the_objects_setting(monkeypatch, field, values, config, default, configured):
    """The object's Anti-aliasing, Folds (occlusion) and Re-shade settings reach EditConfig (antialias, f_occlusion,
    reshade); changing one rebuilds the state (a new preview)."""
    import pointgt_blender.bridge.frame_renderer as fr

    bundle = type("B", (), {"model": type("M", (), {"num_points": 4, "cfg": type("C", (), {"k": 8})()})(),
                            "atlas": None})()
    models = type("Models", (), {"get": lambda self, path, device: bundle})()
    made = []
    monkeypatch.setattr(fr, "EditState", lambda b, **k: made.append(k["cfg"]) or object())
    states = StateCache()
    pos = np.zeros((4, 3), np.float32)
    assert getattr(_inputs(pos), field) == default
    for v in values:
        inputs = _inputs(pos)
        setattr(inputs, field, v)
        fr.prepare(inputs, models, states)
    assert [getattr(c, config) for c in made] == list(configured)  # the third call changed nothing


def test_model_cache_reloads_changed_files_and_names_missing_ones(tmp_path, monkeypatch):
    import pointgt_blender.bridge.frame_renderer as fr

    loads = []
    monkeypatch.setattr(fr, "load_bundle", lambda path, device: loads.append(path) or object())
    path = tmp_path / "m.pgt"
    path.write_bytes(b"one")
    cache = ModelCache()
    a = cache.get(str(path), "cpu")
    assert cache.get(str(path), "cpu") is a and len(loads) == 1
    path.write_bytes(b"three")  # another model copied over it
    assert cache.get(str(path), "cpu") is not a and len(loads) == 2
    with pytest.raises(ModelFileError, match="gone.pgt.*not found"):
        cache.get(str(tmp_path / "gone.pgt"), "cpu")


def test_decoder_layer_composites_like_the_render_over_white():
    """A UNet model's layer is premultiplied over black (no trained-white fringe): composited over white it is
    the frame rendered over white, over black its empty pixels are black, transparent gives the mask as alpha."""
    from core.frames.edited import EditConfig, EditState, render_edited
    from pointgt_blender.bridge.frame_renderer import render_layer
    from tests.helpers.tiny import tiny_bundle

    bundle, _, test = tiny_bundle("card", steps=400, decoder="unet")
    state = EditState(bundle, cfg=EditConfig(colour="atlas", antialias=1))
    c2w = test.c2w[2]
    layer = render_layer(state, c2w.numpy(), test.height, test.width, test.focal)
    ref = render_edited(state, c2w, test.height, test.width, test.focal)["rgb"].numpy()
    white, _ = composite([layer], background=(1, 1, 1))
    unclamped = (layer["premul"] > 1e-3).all(-1) | (layer["alpha"] < 1e-3)
    assert unclamped.mean() > 0.9
    np.testing.assert_allclose(white[unclamped], ref[unclamped], atol=2e-3)
    black, alpha = composite([layer], background=(0, 0, 0))
    empty = (test.alphas[2].numpy() == 0) & (alpha < 0.02)
    assert empty.mean() > 0.3 and black[empty].max() < 0.03
    _, alpha_t = composite([layer], transparent=True)
    np.testing.assert_allclose(alpha_t, layer["alpha"], atol=1e-6)


def test_posed_layer_traces_like_render_edited():
    """Moved points: the add-on's layer trace uses the same F-aware keys (and filled points) as core's render, so
    the layer is the frame `render_edited` draws."""
    import torch

    from core.frames.edited import EditConfig, EditState, render_edited
    from pointgt_blender.bridge.frame_renderer import render_layer, trace_layer
    from tests.helpers.tiny import tiny_bundle

    bundle, _, test = tiny_bundle("card")
    pts = bundle.model.xyz.detach() * torch.tensor([2.5, 1.0, 1.0])
    state = EditState(bundle, points=pts, cfg=EditConfig(antialias=1))
    assert state.moved and state.cfg.f_attention
    c2w = test.c2w[0].clone()
    c2w[:3, 3] *= 2.0
    tr = trace_layer(state, c2w.numpy(), test.height, test.width, test.focal)
    ref = render_edited(state, c2w, test.height, test.width, test.focal)
    assert torch.equal(tr.weights, ref["trace"].weights) and torch.equal(tr.idx, ref["trace"].idx)
    layer = render_layer(state, c2w.numpy(), test.height, test.width, test.focal, trace=tr)
    np.testing.assert_allclose(layer["alpha"], ref["alpha"].numpy(), atol=1e-6)


def test_layer_trace_applies_the_occlusion_rule_like_render_edited():
    """One half of the card swung behind the other (a fold): with f_occlusion the add-on's layer trace keeps each
    ray's front layer exactly as core's render does, and the rule changes rays there."""
    import torch

    from core.frames.edited import EditConfig, EditState, render_edited
    from pointgt_blender.bridge.frame_renderer import trace_layer
    from tests.helpers.tiny import card_half_swung_behind, tiny_bundle

    bundle, _, test = tiny_bundle("card")
    xyz = bundle.model.xyz.detach()
    c2w = test.c2w[0]
    pts, half = card_half_swung_behind(xyz, c2w)
    on = EditState(bundle, points=pts, cfg=EditConfig(antialias=1, f_occlusion=True))
    off = EditState(bundle, points=pts, cfg=EditConfig(antialias=1, f_occlusion=False))
    tr = trace_layer(on, c2w.numpy(), test.height, test.width, test.focal)
    ref = render_edited(on, c2w, test.height, test.width, test.focal)["trace"]
    plain = trace_layer(off, c2w.numpy(), test.height, test.width, test.focal)
    assert torch.equal(tr.weights, ref.weights) and torch.equal(tr.x, ref.x)
    assert int((tr.weights != plain.weights).any(1).sum()) > 0
