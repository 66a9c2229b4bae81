"""The point renderer (trace, shade, render a frame) against per-ray references, and the neighbour selector."""
import pytest
import torch

from core.images.cameras import pixel_rays
from core.points import neighbors
from core.points.render import pixel_grid, render_frame, shade_frame, straight_colour, trace_frame
from core.points.neighbors.select import select_neighbors
from tests.helpers.tiny import tiny_bundle


@pytest.fixture(scope="module")
def scene():
    bundle, _, test = tiny_bundle("fast")
    return bundle.model, test


def _view(test, i=0):
    return test.c2w[i], test.height, test.width, test.focal


def test_trace_matches_per_ray_attention_and_chunks_do_not_matter(scene):
    model, test = scene
    c2w, h, w, f = _view(test)
    tr = trace_frame(model, c2w, h, w, f)
    r = h * w
    assert tr.shape == (h, w) and tr.idx.shape == (r, model.cfg.k) and tr.x.shape == (r, 3)
    o, d = pixel_rays(c2w.float(), h, w, f)
    assert torch.allclose(tr.origins, o.reshape(-1, 3)) and torch.allclose(tr.dirs, d.reshape(-1, 3))
    idx = select_neighbors(model.xyz, model.cfg.neighbors, model.cfg.k, c2w.float(), h, w, f, pixel_grid(h, w, "cpu"),
                           tr.origins, tr.dirs)
    assert torch.equal(tr.idx, idx)
    active = (idx >= 0).any(1)
    assert torch.equal(tr.active, active) and 0 < int(active.sum()) < r
    # rays without a neighbour: pure background, surface point at the ray origin
    assert bool((tr.bg[~active] == 1).all()) and bool((tr.weights[~active] == 0).all())
    assert torch.equal(tr.x[~active], tr.origins[~active])
    # active rays: the model's attention evaluated ray by ray
    for i in torch.nonzero(active).squeeze(1)[::37].tolist():
        with torch.no_grad():
            a = model.attend(model.xyz, model.influence, tr.origins[i:i + 1], tr.dirs[i:i + 1], idx[i:i + 1])
        assert torch.allclose(tr.weights[i], a["weights"][0], atol=1e-6)
        assert torch.allclose(tr.bg[i], a["bg"][0], atol=1e-6)
        assert torch.allclose(tr.x[i], a["x"][0], atol=1e-5)
    small = trace_frame(model, c2w, h, w, f, chunk=13)
    for key in ("weights", "fg_weights", "bg", "x"):
        assert torch.allclose(getattr(small, key), getattr(tr, key), atol=1e-6), key


def test_shade_puts_the_background_weight_on_the_background(scene):
    model, test = scene
    assert model.decoder is None
    tr = trace_frame(model, *_view(test, 1))
    h, w = tr.shape
    grey = shade_frame(model, tr, background=(0.5, 0.5, 0.5))
    black = shade_frame(model, tr, background=(0.0, 0.0, 0.0))
    bg = tr.bg.reshape(h, w, 1).expand(h, w, 3)
    inside = (grey < 1) & (grey > 0) & (black > 0)  # not clamped
    assert int(inside.sum()) > 100
    assert torch.allclose((grey - black)[inside], 0.5 * bg[inside], atol=1e-5)
    out = render_frame(model, *_view(test, 1), background=(0.0, 0.0, 0.0))
    assert torch.allclose(out["rgb"], black) and torch.allclose(out["alpha"], (1 - tr.bg).reshape(h, w))
    assert torch.allclose(out["x"], tr.x.reshape(h, w, 3))


def test_point_values_only_where_rays_hold_points_shade_the_same(scene, monkeypatch):
    """point_table(rows=...) gives the whole table's values at those rows and 0 elsewhere; shade_frame, which asks
    for the held rows only when a frame holds fewer than HELD_TABLE of the points (a close-up here), shades the
    same frame as with every point's value computed."""
    import core.points.render as render
    from core.images.cameras import look_at

    model, test = scene
    with torch.no_grad():
        full = model.point_table()
        rows = torch.tensor([0, 5, 17, model.xyz.shape[0] - 1])
        part = model.point_table(rows=rows)
    assert torch.allclose(part[rows], full[rows], atol=1e-6)
    others = torch.ones(full.shape[0], dtype=torch.bool)
    others[rows] = False
    assert bool((part[others] == 0).all())
    # a close-up of one corner: few of the points are held
    corner = model.xyz.detach()[0]
    c2w = look_at(tuple(float(v) for v in corner + torch.tensor([0.0, -0.6, 0.3])),
                  target=tuple(float(v) for v in corner)).float()
    tr = trace_frame(model, c2w, test.height, test.width, test.focal)
    held = tr.held
    assert 0 < held.numel() < render.HELD_TABLE * model.xyz.shape[0]
    some = shade_frame(model, tr)
    monkeypatch.setattr(render, "HELD_TABLE", 0.0)  # never restricted
    assert torch.allclose(shade_frame(model, tr), some, atol=1e-6)


def test_non_finite_points_are_absent(scene):
    model, test = scene
    pts = model.xyz.detach().clone()
    used = trace_frame(model, *_view(test)).idx
    victim = int(used[used >= 0][0])
    pts[victim] = float("nan")
    tr = trace_frame(model, *_view(test), points=pts)
    assert tr.non_finite_points == 1 and not bool((tr.idx == victim).any())
    assert all(bool(torch.isfinite(getattr(tr, k)).all()) for k in ("weights", "bg", "x"))
    assert bool(torch.isfinite(shade_frame(model, tr)).all())


def test_straight_colour_undoes_premultiplication():
    c = torch.rand(4, 5, 3, generator=torch.Generator().manual_seed(0))
    a = torch.linspace(0, 1, 20).reshape(4, 5)
    got = straight_colour(a[..., None] * c, a)
    keep = a >= 1 / 510
    assert torch.allclose(got[keep], c[keep], atol=1e-5) and bool((got[~keep] == 0).all())


def test_selector_picks_the_configured_search():
    g = torch.Generator().manual_seed(1)
    pts = torch.randn(300, 3, generator=g) * 0.5
    c2w = torch.eye(4)
    c2w[2, 3] = 3.0  # on +Z looking down -Z at the origin
    h = w = 12
    f = 14.0
    px = pixel_grid(h, w, "cpu")
    o, d = pixel_rays(c2w, h, w, f)
    o, d = o.reshape(-1, 3), d.reshape(-1, 3)
    k = 6
    # perpendicular: the k points nearest to each ray, in front of its origin (plain-torch reference)
    got = select_neighbors(pts.requires_grad_(), "perpendicular", k, c2w, h, w, f, px, o, d)
    rel = pts.detach()[None] - o[:, None]
    t = (rel * d[:, None]).sum(-1)
    perp = (rel - t[..., None] * d[:, None]).norm(dim=-1)
    perp = torch.where(t > 0, perp, torch.full_like(perp, float("inf")))
    ref = perp.topk(k, largest=False).indices
    assert torch.equal(got.sort(1).values, ref.sort(1).values)
    for method, depth in (("screen", False), ("screen_depth", True)):
        got = select_neighbors(pts, method, k, c2w, h, w, f, px, o, d)
        want = neighbors.screen_knn(pts.detach(), c2w, h, w, f, px, k, depth_factor=depth).idx
        assert torch.equal(got, want), method
