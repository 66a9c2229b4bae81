"""Edited rendering on a tiny trained model: skips, texture persistence, edit order, part removal/duplication."""
import copy

import pytest
import torch

from core.edits.bake import bake
from core.frames.edited import EditConfig, EditState, render_edited, warm_up
from core.points.render import render_frame
from core.util.errors import InputError
from tests.helpers.tiny import tiny_bundle


@pytest.fixture(scope="module")
def tiny():
    return tiny_bundle("card")


def _render(state, split, i=0, c2w=None):
    m = split.c2w[i] if c2w is None else c2w
    return render_edited(state, m, split.height, split.width, split.focal)


def _half_split(x):
    """Red where x > 0, blue elsewhere: a coarse global retexture the tiny atlas can hold."""
    red = (x[:, 0] > 0).float()[:, None]
    return red * torch.tensor([1.0, 0.0, 0.0]) + (1 - red) * torch.tensor([0.0, 0.0, 1.0]), None


def test_unedited_render_skips_texture_and_correspondence(tiny):
    bundle, _, test = tiny
    out = _render(EditState(bundle, atlas=bundle.atlas.packed_image()), test)
    ref = render_frame(bundle.model, test.c2w[0], test.height, test.width, test.focal)
    assert out["stats"]["texture_rays"] == 0 and out["stats"]["correspondence"] == "skipped"
    assert torch.allclose(out["rgb"], ref["rgb"], atol=1e-6)
    assert out["stats"]["rays_shaded"] <= out["stats"]["rays"]


def test_global_retexture_lands_on_the_surface(tiny):
    bundle, _, test = tiny
    _check_retexture(bundle, test)


def test_retexture_with_the_unet_decoder():
    """The decoder renders the feature image; texture edits are composited on its output, deformed or not."""
    bundle, _, test = tiny_bundle("card", steps=400, decoder="unet")  # the decoder's points need longer to settle
    assert bundle.model.decoder is not None
    _check_retexture(bundle, test)
    state = EditState(bundle, atlas=bake(bundle.atlas, _half_split),
                      points=bundle.model.xyz.detach() * torch.tensor([1.0, 1.0, 0.05]))  # squash to 5 %
    out = _render(state, test, 0)
    assert torch.isfinite(out["rgb"]).all() and out["stats"]["texture_rays"] > 0


def _check_retexture(bundle, test):
    atlas = bake(bundle.atlas, _half_split)
    state = EditState(bundle, atlas=atlas)
    hits = correct = 0
    for i in range(len(test)):
        out = _render(state, test, i)
        obj = (out["alpha"] > 0.5) & (test.alphas[i] > 0.99)
        x = out["x_can"][obj]
        rgb = out["rgb"][obj]
        sure = x[:, 0].abs() > 0.15  # away from the colour border
        want_red = x[sure, 0] > 0
        is_red = rgb[sure, 0] > rgb[sure, 2]
        hits += int(sure.sum())
        correct += int((want_red == is_red).sum())
    assert hits > 100 and correct / hits > 0.9


def test_rigid_motion_keeps_the_texture(tiny):
    """Move the points and the camera by the same rigid translation: the frame must not change."""
    bundle, _, test = tiny
    atlas = bake(bundle.atlas, _half_split)
    shift = torch.tensor([0.3, -0.2, 0.1])
    rest = _render(EditState(bundle, atlas=atlas), test)
    moved_pts = bundle.model.xyz.detach() + shift
    cam = test.c2w[0].clone()
    cam[:3, 3] += shift
    for mode in ("deform-aware", "naive"):
        moved = _render(EditState(bundle, points=moved_pts, atlas=atlas, cfg=EditConfig(correspondence=mode)),
                        test, c2w=cam)
        assert moved["stats"]["correspondence"] == mode
        diff = (moved["rgb"] - rest["rgb"]).abs()
        if mode == "deform-aware":  # exact up to float rounding (and rare neighbour ties)
            assert float(diff.mean()) < 1e-3 and float(diff.flatten().quantile(0.99)) < 1e-2
        else:  # naive skips the ray projection: close, not exact
            assert float(diff.mean()) < 2e-2


def test_edit_order_is_interchangeable(tiny):
    bundle, _, test = tiny
    g = torch.Generator().manual_seed(0)
    pts = bundle.model.xyz.detach() * torch.tensor([1.0, 1.3, 1.0]) + 0.02 * torch.randn(bundle.model.num_points, 3,
                                                                                          generator=g)
    paint = bake(bundle.atlas, _half_split)
    # no fill: a filled state's points hold the added points too (they are not the posed input any more)
    cfg = EditConfig(f_fill=False)
    # paint, then pose
    s1 = EditState(bundle, atlas=paint, cfg=cfg)
    s1 = EditState(bundle, points=pts, atlas=s1.atlas_image, cfg=cfg)
    # pose, then paint
    s2 = EditState(bundle, points=pts, cfg=cfg)
    s2 = EditState(bundle, points=s2.points, atlas=paint, cfg=cfg)
    a, b = _render(s1, test), _render(s2, test)
    assert torch.equal(a["rgb"], b["rgb"])


def test_a_new_pose_reuses_the_prepared_paint(tiny):
    """paint_from (the add-on's next pose of one painted object): the same frame as a state built from the atlas,
    the previous state's textures reused; a state of other texture settings prepares its own."""
    bundle, _, test = tiny
    paint = bake(bundle.atlas, _half_split)
    first = EditState(bundle, atlas=paint)
    _render(first, test)  # unpacks the per-chart textures
    pts = bundle.model.xyz.detach() * torch.tensor([1.0, 1.4, 1.0])
    fresh = EditState(bundle, points=pts, atlas=paint)
    shared = EditState(bundle, points=pts, atlas=None, paint_from=first)  # atlas not read
    assert shared.edit_textures is first.edit_textures and shared.textured
    a, b = _render(fresh, test), _render(shared, test)
    assert a["stats"]["texture_rays"] > 0 and torch.equal(a["rgb"], b["rgb"])
    for cfg in (EditConfig(colour="atlas"), EditConfig(mask_threshold=0.5)):
        own = EditState(bundle, points=pts, atlas=paint, cfg=cfg, paint_from=first)
        assert own.edit_textures is not first.edit_textures
    assert not EditState(copy.copy(bundle), atlas=None, paint_from=first).textured  # another bundle


def test_removed_part_keeps_texture_on_the_rest(tiny):
    bundle, _, test = tiny
    atlas = bake(bundle.atlas, _half_split)
    xyz = bundle.model.xyz.detach()
    keep = torch.nonzero(xyz[:, 1] < 0.1).squeeze(1)  # drop the upper part of the card
    full = _render(EditState(bundle, atlas=atlas), test)
    part = _render(EditState(bundle, points=xyz[keep], ids=keep, atlas=atlas), test)
    x = full["x_can"]
    stable = (full["alpha"] > 0.5) & (part["alpha"] > 0.5) & (x[..., 1] < -0.1)  # away from the cut
    assert int(stable.sum()) > 30
    assert (full["rgb"][stable] - part["rgb"][stable]).abs().mean() < 0.03
    gone = (full["alpha"] > 0.5) & (x[..., 1] > 0.3)
    if bool(gone.any()):
        assert float(part["alpha"][gone].mean()) < 0.5  # the removed part is no longer drawn


def test_duplicated_part_carries_the_same_texture(tiny):
    bundle, _, test = tiny
    atlas = bake(bundle.atlas, _half_split)
    xyz = bundle.model.xyz.detach()
    n = xyz.shape[0]
    off = torch.tensor([0.0, 0.0, 0.0])
    cam = test.c2w[0]
    right = cam[:3, 0]
    off = 6.0 * right  # far enough sideways that each camera sees one copy only
    pts = torch.cat([xyz, xyz + off])
    ids = torch.cat([torch.arange(n), torch.arange(n)])
    state = EditState(bundle, points=pts, ids=ids, atlas=atlas)
    a = _render(state, test, c2w=cam)
    cam_b = cam.clone()
    cam_b[:3, 3] += off
    b = _render(state, test, c2w=cam_b)
    assert float(a["alpha"].sum()) > 20
    assert (a["rgb"] - b["rgb"]).abs().max() < 2e-3


def test_bad_edit_inputs_are_rejected(tiny):
    bundle, _, _ = tiny
    n = bundle.model.num_points
    with pytest.raises(InputError, match="ids"):
        EditState(bundle, points=torch.zeros(n - 1, 3))
    with pytest.raises(InputError, match="range|lie in"):
        EditState(bundle, points=torch.zeros(2, 3), ids=torch.tensor([0, n]))
    with pytest.raises(InputError, match="integers"):
        EditState(bundle, points=torch.zeros(2, 3), ids=torch.tensor([0.0, 1.0]))
    with pytest.raises(InputError, match="atlas"):
        EditState(bundle, atlas=torch.zeros(7, 7, 3))
    with pytest.raises(InputError, match="antialias"):
        EditState(bundle, cfg=EditConfig(antialias=0))


def test_antialiased_lookups_keep_flat_colours_and_the_one_lookup_path(tiny):
    """A flat painted colour is the same whether each pixel takes one lookup or a filtered 2x2/3x3 set (the filter
    is normalised, linear light round-trips); on a two-colour retexture the filtered frame differs only near the
    colour border, and only a little on average."""
    bundle, _, test = tiny
    # the splat bake paints every texel the flat colour; the fitted bake (the default) changes the fitted texture
    # only as smoothly as its samples allow, so a little of that texture's variation stays (~0.4 %)
    flat = bake(bundle.atlas, lambda x: (torch.tensor([0.8, 0.3, 0.1]).expand(len(x), 3), None), source="samples")
    split = bake(bundle.atlas, _half_split)
    for atlas, tol in ((flat, 3e-3), (split, None)):
        frames = {aa: _render(EditState(bundle, atlas=atlas, cfg=EditConfig(antialias=aa)), test)
                  for aa in (1, 2, 3)}
        assert frames[2]["stats"]["texture_rays"] == frames[1]["stats"]["texture_rays"] > 0
        obj = (frames[1]["alpha"] > 0.5)
        for aa in (2, 3):
            d = (frames[aa]["rgb"] - frames[1]["rgb"]).abs()[obj]
            assert torch.isfinite(frames[aa]["rgb"]).all()
            if tol is not None:  # edge pixels may see unpainted texels and the soft edit mask; the bulk may not
                assert d.mean() < tol and d.quantile(0.95) < 7 * tol, f"antialias {aa}: flat colour changed"
            else:
                assert 0 < d.mean() < 0.05


def test_painted_rays_take_the_decoder_mask_as_coverage():
    """With the UNet's mask head, atlas-coloured rays are composited with the decoder's alpha: force it to 0 and
    they show the background; to 1 and no background is mixed into their atlas colour."""
    import copy

    bundle, _, test = tiny_bundle("card", steps=400, decoder="unet")
    assert bundle.model.cfg.decoder_alpha
    frames = {}
    for name, bias in (("none", -60.0), ("full", 60.0)):
        b = copy.deepcopy(bundle)
        with torch.no_grad():
            b.model.decoder.alpha_head[-1].bias[0] = bias
        frames[name] = _render(EditState(b, cfg=EditConfig(colour="atlas", antialias=1, lookup="charts")), test)
    hit = frames["none"]["stats"]["texture_rays"]
    assert hit > 100
    painted = torch.isfinite(frames["none"]["x_can"]).all(-1).reshape(-1)
    assert painted.sum() == hit and frames["none"]["alpha"].max() < 1e-6  # alpha is the mask head's
    assert torch.allclose(frames["none"]["rgb"].reshape(-1, 3)[painted], torch.ones(1, 3), atol=1e-4)
    full = frames["full"]["rgb"].reshape(-1, 3)[painted]
    atlas_rgb = bundle.atlas.lookup(frames["full"]["x_can"].reshape(-1, 3)[painted])  # the charts, as configured
    assert torch.allclose(full, atlas_rgb.clamp(0, 1), atol=1e-3)


@pytest.mark.parametrize("decoder", ["none", "unet"])
def test_renders_over_any_background(decoder):
    """A decoder paints the white it was trained on; over another background its share must move there: over
    black the background pixels are black, and white minus black is the uncovered share 1 − alpha everywhere."""
    bundle, _, test = tiny_bundle("card", steps=400 if decoder == "unet" else 200, decoder=decoder)
    state = EditState(bundle, cfg=EditConfig(colour="atlas", antialias=1))
    for render in (lambda bg: render_frame(bundle.model, test.c2w[1], test.height, test.width, test.focal,
                                           background=bg),
                   lambda bg: render_edited(state, test.c2w[1], test.height, test.width, test.focal, background=bg)):
        white, black = render((1.0, 1.0, 1.0)), render((0.0, 0.0, 0.0))
        assert torch.allclose(white["alpha"], black["alpha"])
        empty = (test.alphas[1] == 0) & (black["alpha"] < 0.02)
        assert empty.float().mean() > 0.3
        assert black["rgb"][empty].max() < 0.03
        unclamped = (black["rgb"] > 1e-3).all(-1)
        share = (white["rgb"] - black["rgb"])[unclamped]
        assert torch.allclose(share, (1 - black["alpha"])[unclamped][:, None].expand_as(share), atol=2e-3)


def test_threshold_blend_applies_per_subpixel_before_the_filter(tiny):
    """With filtered lookups the paper's threshold rule (mask > 0.95) is applied to every sub-pixel lookup:
    a mask just below it everywhere leaves the frame unedited, a full mask paints like the soft blend, and where
    a painted region's edge crosses a pixel's footprint the pixel is a filtered mix of both (thresholding the
    filtered mask instead would give every pixel either the painted or the unedited colour)."""
    bundle, _, test = tiny
    painted = bake(bundle.atlas, _half_split)
    stripes = torch.zeros(bundle.atlas.layout.shape)
    stripes[:, (torch.arange(stripes.shape[1]) // 4) % 2 == 0] = 1.0  # painted texel stripes, 4 texels wide
    frames = {}
    for name, mask in (("below", 0.9), ("full", 1.0), ("stripes", stripes[..., None])):
        for mode in ("soft", "threshold"):
            state = EditState(bundle, atlas=painted, cfg=EditConfig(blend=mode, antialias=2))
            state.mask_image = (torch.zeros_like(state.mask_image) + mask).contiguous()
            state._edit_textures = None
            frames[name, mode] = _render(state, test)["rgb"]
    plain = render_frame(bundle.model, test.c2w[0], test.height, test.width, test.focal)["rgb"]
    assert torch.allclose(frames["below", "threshold"], plain, atol=1e-5)
    assert not torch.allclose(frames["below", "soft"], plain, atol=1e-2)
    assert torch.allclose(frames["full", "threshold"], frames["full", "soft"], atol=1e-5)
    mixed = (((frames["stripes", "threshold"] - plain).abs().amax(-1) > 1e-3)
             & ((frames["stripes", "threshold"] - frames["full", "threshold"]).abs().amax(-1) > 1e-3))
    assert mixed.sum() > 10


def test_warm_up_renders_tiny_frames_and_leaves_the_model_alone(tiny):
    bundle, _, test = tiny
    before = bundle.model.xyz.detach().clone()
    ref = _render(EditState(bundle), test)["rgb"]
    assert warm_up(bundle) > 0 and torch.equal(bundle.model.xyz, before)
    assert torch.equal(_render(EditState(bundle), test)["rgb"], ref)  # nothing cached that changes a frame
    no_atlas = copy.copy(bundle)
    no_atlas.atlas = None  # a model without an atlas: the deformed frame alone, any renderer switch
    assert warm_up(no_atlas, EditConfig(f_attention=True, f_fill=True), size=8) > 0
