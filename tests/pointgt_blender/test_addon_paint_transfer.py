"""Preview paint -> atlas texels (pointgt_blender/bridge/paint_transfer.py) with a small real Atlas, no Blender."""
import numpy as np
import pytest
import torch

from core.atlas.atlas import Atlas
from core.util.errors import InputError
from pointgt_blender.bridge.paint_transfer import painted_pixels, transfer

H, W = 12, 16


def _setup():
    torch.manual_seed(0)
    atlas = Atlas(n=4, R=16, pad=2, centre=(0, 0, 0), half=1.0, width_chart=8, depth_chart=1, width_map=16,
                  depth_map=1)
    atlas.eval()
    img = atlas.packed_image().numpy()
    g = np.stack(np.meshgrid(np.linspace(-0.6, 0.6, W), np.linspace(-0.4, 0.4, H)), -1)
    x_can = np.concatenate([g, np.zeros((H, W, 1))], -1).astype(np.float32)  # a plane seen head-on
    rendered = atlas.lookup(torch.from_numpy(x_can.reshape(-1, 3))).numpy().reshape(H, W, 3)
    return atlas, img, x_can, rendered


def test_painted_pixels_reappear_when_the_atlas_is_looked_up_there():
    atlas, img, x_can, rendered = _setup()
    painted = rendered.copy()
    painted[3:7, 5:9] = (1.0, 0.0, 0.5)
    x_can[0, 0] = np.nan  # a pixel off the object, painted too: ignored
    painted[0, 0] = (1.0, 0.0, 0.5)
    new, changed, n = transfer(atlas, img, painted, rendered, x_can, threshold=0.02, fill=False)
    assert n == 16 and changed.any()
    assert np.array_equal(new[~changed], img[~changed])  # untouched texels keep their exact values
    inner = x_can[4:6, 6:8].reshape(-1, 3)  # pixels whose whole bilinear footprint was painted
    got = atlas.lookup(torch.from_numpy(inner), torch.from_numpy(new)).numpy()
    # charts blended below the floor keep their colour, so allow that much mixing
    np.testing.assert_allclose(got, np.tile([1.0, 0.0, 0.5], (len(inner), 1)), atol=0.2)
    # (locality on a trained atlas - other pixels keep their colour - is checked in test_addon_render.py)


def test_fill_pass_paints_texels_whose_surface_point_was_painted():
    atlas, img, x_can, rendered = _setup()
    texel = np.full((*atlas.layout.shape, 3), np.nan, np.float32)
    texel[5, 7] = x_can[4, 6] + (0.01, 0.0, 0.0)  # within one pixel of a painted pixel
    texel[9, 9] = x_can[10, 14]  # under an unpainted pixel
    atlas.texel_xyz.copy_(torch.from_numpy(texel))
    painted = rendered.copy()
    painted[3:7, 5:9] = (0.0, 1.0, 0.0)
    new, changed, _ = transfer(atlas, img, painted, rendered, x_can, threshold=0.02, fill=True)
    assert changed[5, 7] and np.allclose(new[5, 7], (0.0, 1.0, 0.0))
    assert not changed[9, 9] or np.array_equal(new[9, 9], img[9, 9])


def test_nothing_painted_changes_nothing_and_bad_shapes_are_named():
    atlas, img, x_can, rendered = _setup()
    new, changed, n = transfer(atlas, img, rendered + 0.005, rendered, x_can, threshold=0.02)
    assert n == 0 and not changed.any() and np.array_equal(new, img)
    with pytest.raises(InputError, match="re-render the preview"):
        painted_pixels(rendered[:-1], rendered, x_can, 0.02)
    with pytest.raises(InputError, match="re-import"):
        transfer(atlas, img[:-1], rendered, rendered, x_can)
    nan_x = np.full_like(x_can, np.nan)
    new, changed, n = transfer(atlas, img, rendered * 0, rendered, nan_x)  # all off the object: finite, no-op
    assert n == 0 and np.isfinite(new).all()


@pytest.mark.parametrize("moved", [False, True])
def test_canonical_surface_is_where_the_render_looked_the_atlas_up(moved):
    """The paint transfer's x_can is the edited render's own (one correspondence function for both): equal on
    every pixel both cover, at rest and after a move (sheared, so the correspondence has work to do)."""
    from core.frames.edited import EditConfig, EditState, render_edited
    from pointgt_blender.bridge.paint_transfer import canonical_surface
    from tests.helpers.tiny import tiny_bundle

    bundle, _, test = tiny_bundle("card")
    pts = bundle.model.xyz.detach()
    if moved:
        pts = pts + torch.stack([0.2 * pts[:, 1], torch.zeros_like(pts[:, 0]), 0.1 * pts[:, 0]], 1)
    state = EditState(bundle, points=pts if moved else None, cfg=EditConfig(colour="atlas", antialias=1))
    out = render_edited(state, test.c2w[0], test.height, test.width, test.focal)
    mine = canonical_surface(state, out)
    theirs = out["x_can"].numpy()
    both = np.isfinite(mine).all(-1) & np.isfinite(theirs).all(-1)
    assert both.sum() > 100 and np.isfinite(theirs).all(-1)[np.isfinite(mine).all(-1)].all()
    np.testing.assert_allclose(mine[both], theirs[both], atol=1e-6)
