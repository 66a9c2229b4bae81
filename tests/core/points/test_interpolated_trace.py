"""The `upsampled` mode's full-size trace, interpolated from the training-scale trace
(core.points.resolution.interpolate_trace): identity at the training size, the Trace invariants, no blending across
an occlusion edge, close to tracing every full-size ray, and the correspondence and paint transfer built on it."""
import pytest
import torch

from core.images.cameras import look_at, pixel_rays
from core.points.render import render_frame, trace_frame
from core.points.resolution import interpolate_rays, interpolate_trace
from core.points.trace import Trace
from tests.helpers.tiny import tiny_bundle


@pytest.fixture(scope="module")
def card():
    bundle, _, test = tiny_bundle("card")
    return bundle, test


def _invariants(tr: Trace):
    h, w = tr.shape
    assert tr.x.shape == (h * w, 3) and tr.idx.shape == tr.weights.shape == tr.fg_weights.shape
    assert bool(torch.isfinite(tr.x).all()) and bool(torch.isfinite(tr.weights).all())
    assert torch.allclose(tr.weights.sum(1) + tr.bg, torch.ones_like(tr.bg), atol=1e-5)
    act = tr.active
    assert bool(((tr.idx >= 0).any(1) == act).all())
    assert bool((tr.idx[~act] == -1).all()) and bool((tr.fg_weights[~act] == 0).all())
    assert bool((tr.bg[~act] == 1).all()) and torch.equal(tr.x[~act], tr.origins[~act])
    assert torch.allclose(tr.fg_weights[act].sum(1), torch.ones(int(act.sum())), atol=1e-5)
    assert float(tr.bg.min()) >= 0 and float(tr.bg.max()) <= 1


def test_at_the_training_size_it_is_the_trace_itself(card):
    bundle, test = card
    c2w, h, w, f = test.c2w[0], test.height, test.width, test.focal
    low = trace_frame(bundle.model, c2w, h, w, f)
    tr = interpolate_trace(low, c2w, h, w, f, f)
    assert torch.equal(tr.active, low.active) and torch.equal(tr.idx, low.idx)
    assert torch.equal(tr.fg_weights, low.fg_weights)
    assert torch.allclose(tr.x, low.x, atol=1e-6) and torch.allclose(tr.bg, low.bg, atol=1e-6)
    assert torch.allclose(tr.origins, low.origins) and torch.allclose(tr.dirs, low.dirs)
    assert tr.coarse.low is low


@pytest.mark.parametrize("factor", [3, 4, 2.5])
def test_it_keeps_the_trace_invariants_and_follows_the_traced_rays(card, factor):
    bundle, test = card
    model = bundle.model
    c2w, h, w, f = test.c2w[0], test.height, test.width, test.focal
    H, W = int(round(factor * h)), int(round(factor * w))
    low = trace_frame(model, c2w, h, w, f)
    tr = interpolate_trace(low, c2w, H, W, f * H / h, f)
    _invariants(tr)
    full = trace_frame(model, c2w, H, W, f * H / h)
    both = tr.active & full.active & (full.bg < 0.5)
    assert int(both.sum()) > 0.5 * int((full.bg < 0.5).sum())
    d = (tr.x[both] - full.x[both]).norm(dim=-1)
    assert float(d.median()) < 0.5 * float(model.spacing)  # the same surface, within half a point spacing
    # every traced object ray is covered by the interpolation (nothing goes missing inside the silhouette)
    assert bool(tr.active[full.bg < 0.05].all())


def test_it_does_not_blend_across_an_occlusion_edge():
    """Two surfaces side by side at depth 1 and 5: a full-size ray takes its surface point from one of them."""
    h = w = 4
    c2w = look_at(torch.tensor([0.0, 0.0, 0.0]), torch.tensor([0.0, 0.0, -1.0]), torch.tensor([0.0, 1.0, 0.0]))
    o, d = pixel_rays(c2w, h, w, 4.0)
    o, d = o.reshape(-1, 3), d.reshape(-1, 3)
    depth = torch.tensor([1.0, 1.0, 5.0, 5.0]).repeat(h)  # columns 0-1 near, 2-3 far
    k = 2
    low = Trace(origins=o, dirs=d, idx=torch.arange(h * w * k).reshape(-1, k), weights=torch.full((h * w, k), 0.5),
                fg_weights=torch.full((h * w, k), 0.5), bg=torch.zeros(h * w), x=o + depth[:, None] * d,
                active=torch.ones(h * w, dtype=torch.bool), shape=(h, w))
    tr = interpolate_trace(low, c2w, 4 * h, 4 * w, 16.0, 4.0)
    _invariants(tr)
    dist = tr.depth
    near, far = (dist - 1.0).abs() < 0.05, (dist - 5.0).abs() < 0.25
    assert bool((near | far).all())  # never in between
    cols = torch.arange(4 * w).repeat(4 * h)
    assert bool(near[cols < 8].all()) and bool(far[cols >= 8].all())


def test_interpolate_rays_blends_with_the_link_weights(card):
    bundle, test = card
    c2w, h, w, f = test.c2w[0], test.height, test.width, test.focal
    low = trace_frame(bundle.model, c2w, h, w, f)
    tr = interpolate_trace(low, c2w, 3 * h, 3 * w, 3 * f, f)
    sel = torch.nonzero(tr.active).squeeze(1)
    # the low trace's own surface points, blended, are the interpolated trace's x
    assert torch.allclose(interpolate_rays(tr.coarse, low.x, sel), tr.x[sel], atol=1e-6)
    bad = low.x.clone()
    bad[tr.coarse.corners[sel[0]][tr.coarse.weights[sel[0]] > 0][0]] = float("nan")
    assert not bool(torch.isfinite(interpolate_rays(tr.coarse, bad, sel[:1])).all())  # a broken input shows


def test_moved_upsampled_frames_look_the_texture_up_where_every_ray_traced_does(card):
    """A moved object (a rigid shift and turn, so every correspondence is exact): the upsampled frame's canonical
    points, interpolated from the training scale, agree with the per-ray correspondence of a fully traced frame,
    and the texture they look up is as sharp."""
    from core.frames.edited import EditConfig, EditState, render_edited

    bundle, test = card
    c2w, h, w, f = test.c2w[0], 4 * test.height, 4 * test.width, 4 * test.focal
    p = bundle.model.xyz.detach()
    a = torch.tensor(0.3)
    rot = torch.tensor([[torch.cos(a), -torch.sin(a), 0.0], [torch.sin(a), torch.cos(a), 0.0], [0.0, 0.0, 1.0]])
    c = p.mean(0)
    moved = (p - c) @ rot.T + c + torch.tensor([0.02, -0.01, 0.0])

    def checker(x):
        v = (torch.floor(x[:, 0] * 40) + torch.floor(x[:, 1] * 40)) % 2
        return torch.stack([v, 1 - v, 0.5 * torch.ones_like(v)], 1)
    painted = bundle.atlas.packed_image().clone()
    painted[::2] = 1.0 - painted[::2]
    out = {}
    for corr in ("deform-aware", "naive", "deform-gradient"):
        for mode in ("pixels", "upsampled"):
            state = EditState(bundle, points=moved, atlas=painted,
                              cfg=EditConfig(render_mode=mode, correspondence=corr))
            out[corr, mode] = render_edited(state, c2w, h, w, f, texture_fn=checker)
        up, px = out[corr, "upsampled"], out[corr, "pixels"]
        assert up["trace"].coarse is not None and px["trace"].coarse is None
        both = torch.isfinite(up["x_can"]).all(-1) & torch.isfinite(px["x_can"]).all(-1) & (px["alpha"] > 0.5)
        assert int(both.sum()) > 200
        d = (up["x_can"][both] - px["x_can"][both]).norm(dim=-1)
        assert float(d.median()) < 0.5 * float(bundle.model.spacing), corr

        def detail(img):
            dd = (img[1:, :] - img[:-1, :]).abs().sum(-1)
            return float(dd[both[1:, :] & both[:-1, :]].mean())
        assert detail(up["rgb"]) > 0.8 * detail(px["rgb"]), corr


def test_paint_transfer_reads_the_interpolated_canonical_points(card):
    """The add-on maps painted preview pixels through `canonical_surface(state, result)`: on an upsampled frame
    it gives the canonical points render_edited looked the texture up at."""
    from core.frames.edited import EditConfig, EditState, render_edited
    from pointgt_blender.bridge.paint_transfer import canonical_surface

    bundle, test = card
    c2w, h, w, f = test.c2w[0], 3 * test.height, 3 * test.width, 3 * test.focal
    moved = bundle.model.xyz.detach() + torch.tensor([0.01, 0.0, 0.0])
    painted = bundle.atlas.packed_image().clone()
    painted[::2] = 1.0 - painted[::2]
    state = EditState(bundle, points=moved, atlas=painted, cfg=EditConfig(render_mode="upsampled"))
    res = render_edited(state, c2w, h, w, f)
    xc = torch.as_tensor(canonical_surface(state, res, min_alpha=0.5))
    both = torch.isfinite(xc).all(-1) & torch.isfinite(res["x_can"]).all(-1)
    assert int(both.sum()) > 100
    assert torch.allclose(xc[both], res["x_can"][both], atol=1e-5)

