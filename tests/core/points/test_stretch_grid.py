"""The stretch grid (core.points.resolution.StretchGrid, EditConfig.stretch_grid and squash_grid): the turned,
per-axis scaled training-scale frame of a stretched or squashed pose. Its camera sees every output ray where its
coords say, it holds the frame, its resampling keeps constants, is the identity at scale 1 and averages a grid
finer than the output over each output pixel; the screen stretch of a pose is what the pose does; frames without a
stretch or a squash are the frames without the grid, stretched ones stay finite and keep the detail across the
stretch, squashed ones are traced finer across the squash."""
import math

import pytest
import torch

from core.frames.edited import EditConfig, EditState, _scales, render_edited
from core.images.cameras import Intrinsics, look_at, pixel_rays, project_points
from core.points.render import trace_frame
from core.points.resolution import MIN_GRID_SCALE, interpolate_trace, stretch_grid, warp_frame
from tests.helpers.tiny import tiny_bundle


@pytest.fixture(scope="module")
def card():
    bundle, _, test = tiny_bundle("card")
    return bundle, test


@pytest.mark.parametrize("focal", [60.0, Intrinsics(55.0, 65.0, 21.0, 23.0)])
@pytest.mark.parametrize("scales, angle", [((4.0, 1.0), 0.6), ((2.5, 1.5), -2.0), ((1.0, 1.0), 0.0),
                                           ((7.0, 0.3), math.pi / 2), ((1.0, 0.1), -0.4)])
def test_the_grid_camera_sees_each_output_ray_at_its_coords(focal, scales, angle):
    c2w = look_at((0.3, -4.0, 1.0), target=(0.0, 0.0, 0.0)).float()
    h, w = 40, 50
    g = stretch_grid(c2w, h, w, focal, scales, angle)
    o, d = pixel_rays(c2w, h, w, focal)
    pts = (o + 2.0 * d).reshape(-1, 3)
    uv, depth = project_points(pts, g.c2w, g.height, g.width, g.focal)
    assert bool((depth > 0).all())
    assert float((uv.double() - g.coords[:, [1, 0]]).abs().max()) < 1e-3
    # the grid holds the frame, and its pixels are the scales (at least MIN_GRID_SCALE) times the output's
    assert float(g.coords.min()) >= -1e-6
    assert float(g.coords[:, 0].max()) <= g.height + 1e-6 and float(g.coords[:, 1].max()) <= g.width + 1e-6
    f = math.sqrt(float(Intrinsics(*focal.as_list()).fx * focal.fy) if isinstance(focal, Intrinsics) else focal ** 2)
    s_along, s_across = (max(v, MIN_GRID_SCALE) for v in scales)
    assert g.focal.fx == pytest.approx(f / s_along) and g.focal.fy == pytest.approx(f / s_across)
    assert g.scales == (s_along, s_across)


def test_warp_keeps_constants_and_is_the_identity_at_scale_one():
    c2w = look_at((0.0, -4.0, 0.0), target=(0.0, 0.0, 0.0)).float()
    h, w = 12, 16
    g = stretch_grid(c2w, h, w, 20.0, (1.0, 1.0), 0.0)
    assert (g.height, g.width) == (h, w)
    img = torch.rand(h, w, 3, generator=torch.Generator().manual_seed(0))
    assert torch.allclose(warp_frame(img, g, h, w), img, atol=1e-5)
    turned = stretch_grid(c2w, h, w, 20.0, (3.0, 1.0), 0.7)
    const = torch.full((turned.height, turned.width), 0.25)
    out = warp_frame(const, turned, h, w)
    assert out.shape == (h, w) and torch.allclose(out, torch.full((h, w), 0.25), atol=1e-6)
    nan = torch.full((turned.height, turned.width, 3), float("nan"))
    assert bool(torch.isfinite(warp_frame(nan, turned, h, w)).all())


def test_a_grid_finer_than_the_output_is_averaged_over_each_output_pixel():
    """Across a squash the grid is finer than the output: stripes one grid pixel wide (finer than an output pixel)
    come back as their mean, not as the stripe the output pixel's centre happens to fall on; constants stay."""
    c2w = look_at((0.0, -4.0, 0.0), target=(0.0, 0.0, 0.0)).float()
    h, w = 12, 16
    fine = stretch_grid(c2w, h, w, 20.0, (1.0, 0.25), 0.0)  # filtered with the default tent
    assert (fine.height, fine.width) == (4 * h, w)
    rows = torch.arange(fine.height)[:, None].expand(fine.height, fine.width)
    stripes = (rows % 2).float()
    out = warp_frame(stripes, fine, h, w)
    assert float((out[1:-1] - 0.5).abs().max()) < 0.05  # away from the replicated edges
    point_sampled = stripes[(fine.coords[:, 0].floor().long()).clamp(0, fine.height - 1), 0].reshape(h, w)
    assert float((point_sampled - 0.5).abs().min()) == 0.5  # what sampling without the filter would show
    const = torch.full((fine.height, fine.width, 3), 0.7)
    assert torch.allclose(warp_frame(const, fine, h, w), torch.full((h, w, 3), 0.7), atol=1e-6)
    turned = stretch_grid(c2w, h, w, 20.0, (1.0, 0.3), 1.1)
    nan = torch.full((turned.height, turned.width), float("nan"))
    assert bool(torch.isfinite(warp_frame(nan, turned, h, w)).all())


def test_interpolating_on_an_unscaled_grid_is_the_plain_interpolation(card):
    bundle, test = card
    c2w, h, w, f = test.c2w[0], test.height, test.width, test.focal
    g = stretch_grid(c2w, h, w, f, (1.0, 1.0), 0.0)
    low = trace_frame(bundle.model, c2w, h, w, f)
    a = interpolate_trace(low, c2w, h, w, f, f)
    b = interpolate_trace(low, c2w, h, w, f, g.focal, coords=g.coords)
    assert torch.equal(a.active, b.active) and torch.equal(a.idx, b.idx)
    assert torch.allclose(a.x, b.x, atol=1e-5) and torch.allclose(a.bg, b.bg, atol=1e-5)


def _cam(test):
    """The first test camera turned so that its image x axis is world x (a stretch along x lies along the rows)."""
    c2w = test.c2w[0].clone()
    eye = c2w[:3, 3]
    centre = torch.zeros(3)
    return look_at(tuple(float(v) for v in centre + torch.tensor([0.0, -1.0, 0.0]) * float((eye - centre).norm())),
                   target=(0.0, 0.0, 0.0)).float()


def test_the_screen_stretch_is_the_pose_on_the_screen(card):
    bundle, test = card
    xyz = bundle.model.xyz.detach()
    n = xyz.shape[0]
    c2w = _cam(test)
    rest = EditState(bundle)
    assert rest.screen_stretch(c2w) == (1.0, 1.0, 0.0)
    forced = EditState(bundle, points=xyz.clone(), ids=torch.arange(n))
    along, across, _ = forced.screen_stretch(c2w)
    assert along == pytest.approx(1.0, abs=1e-3) and across == pytest.approx(1.0, abs=1e-3)
    a = 0.8
    rot = torch.tensor([[math.cos(a), -math.sin(a), 0.0], [math.sin(a), math.cos(a), 0.0], [0.0, 0.0, 1.0]])
    along, across, _ = EditState(bundle, points=xyz @ rot.T).screen_stretch(c2w)
    assert along == pytest.approx(1.0, abs=0.02) and across == pytest.approx(1.0, abs=0.02)  # rigid: no stretch
    along, across, angle = EditState(bundle, points=xyz * 2.0).screen_stretch(c2w)
    assert along == pytest.approx(2.0, rel=0.02) and across == pytest.approx(2.0, rel=0.02)
    along, across, angle = EditState(bundle, points=xyz * torch.tensor([5.0, 1.0, 1.0])).screen_stretch(c2w)
    assert along == pytest.approx(5.0, rel=0.05) and across == pytest.approx(1.0, rel=0.05)
    assert min(abs(angle), abs(abs(angle) - math.pi)) < 0.05  # along the image's x axis
    for pts in (xyz * torch.tensor([1e3, 1.0, 1.0]), xyz * torch.tensor([1.0, 1.0, 0.0]),
                torch.where(torch.arange(n)[:, None] % 7 == 0, torch.full_like(xyz, float("nan")), xyz)):
        got = EditState(bundle, points=pts).screen_stretch(c2w)
        assert all(math.isfinite(v) for v in got) and got[0] >= got[1] >= 0


def test_frames_without_a_stretch_are_todays_and_stretched_ones_keep_the_detail_across(card):
    bundle, test = card
    xyz = bundle.model.xyz.detach()
    c2w, h, w, f = _cam(test), 4 * test.height, 4 * test.width, 4 * test.focal
    # the stretch grid alone (the small stretched object is below the training scale across: a squash grid's)
    on, off = EditConfig(stretch_grid=1.5, squash_grid=0.0), EditConfig(stretch_grid=0.0, squash_grid=0.0)
    small = xyz * torch.tensor([3.0, 1.0, 1.0]) * 0.3
    # a shift, a uniform scale (no stretch on the screen); a stretched object small enough that the frame is
    # traced at its own size (dscale 1: nothing to spread otherwise)
    for pts, size in ((xyz + 0.01, 4), (xyz * 2.0, 4), (small, 1)):
        args = (c2w, size * test.height, size * test.width, size * test.focal)
        a = render_edited(EditState(bundle, points=pts, cfg=on), *args)
        b = render_edited(EditState(bundle, points=pts, cfg=off), *args)
        assert torch.equal(a["rgb"], b["rgb"]) and torch.equal(a["alpha"], b["alpha"])
        assert size > 1 or a["trace"].coarse is None
    rest_on = render_edited(EditState(bundle, cfg=on), c2w, h, w, f)
    rest_off = render_edited(EditState(bundle, cfg=off), c2w, h, w, f)
    assert torch.equal(rest_on["rgb"], rest_off["rgb"])
    pts = xyz * torch.tensor([3.0, 1.0, 1.0])
    st_on, st_off = EditState(bundle, points=pts, cfg=on), EditState(bundle, points=pts, cfg=off)
    a, b = render_edited(st_on, c2w, h, w, f), render_edited(st_off, c2w, h, w, f)
    low_on, low_off = a["trace"].coarse.low, b["trace"].coarse.low
    # the one-scale frame is as coarse both ways; the grid (along the rows here) is coarser along the stretch and
    # finer across it, with no more pixels than the one-scale frame
    grid = st_on._grid[1]
    assert grid is not None and grid.scales[0] > grid.scales[1] and abs(grid.angle) < 0.05
    dscale = _scales(st_off, c2w, f)[1]
    assert grid.scales[1] < 0.95 * dscale < grid.scales[0]
    assert grid.scales[0] * grid.scales[1] == pytest.approx(dscale * dscale, rel=0.05)
    assert low_on.shape[0] * low_on.shape[1] <= 1.05 * low_off.shape[0] * low_off.shape[1]
    for out in (a, b):
        assert bool(torch.isfinite(out["rgb"]).all()) and bool(torch.isfinite(out["alpha"]).all())
    # the same object: coverage of the two frames agrees on most pixels
    agree = ((a["alpha"] > 0.5) == (b["alpha"] > 0.5)).float().mean()
    assert float(agree) > 0.9
    for pts in (xyz * torch.tensor([1e3, 1.0, 1.0]), xyz * torch.tensor([1.0, 1.0, 0.0])):
        out = render_edited(EditState(bundle, points=pts, cfg=on), c2w, h, w, f)
        assert bool(torch.isfinite(out["rgb"]).all()) and bool(torch.isfinite(out["alpha"]).all())


def test_cutting_the_grid_to_the_points_keeps_the_frame(card, monkeypatch):
    """The grid cut to the points' outline traces the frame of the whole turned grid: its rays are a subset, the
    rest background (with the search's pixel cap fixed: "auto" estimates it from the points' density per cell of
    the frame, which the cut moves a little); a point behind the camera leaves the grid whole."""
    bundle, test = card
    model = bundle.model
    monkeypatch.setattr(model.cfg, "neighbor_radius_px", 3.0)
    pts = model.xyz.detach() * torch.tensor([2.0, 1.0, 1.0])
    c2w, h, w, f = _cam(test), 4 * test.height, 4 * test.width, 4 * test.focal
    c2w[:3, 3] *= 2.0
    whole = stretch_grid(c2w, h, w, f, (2.0, 1.0), 0.3)
    cut = stretch_grid(c2w, h, w, f, (2.0, 1.0), 0.3, points=pts)
    assert cut.height * cut.width < 0.8 * whole.height * whole.width
    a, b = (interpolate_trace(trace_frame(model, g.c2w, g.height, g.width, g.focal, points=pts), c2w, h, w, f,
                              g.focal, coords=g.coords) for g in (whole, cut))
    assert int(a.active.sum()) > 100 and torch.equal(a.active, b.active)
    assert torch.allclose(a.x, b.x, atol=1e-5) and torch.allclose(a.bg, b.bg, atol=1e-5)
    behind = torch.cat([pts, c2w[:3, 3][None] + c2w[:3, 2][None]])  # one point just behind the camera
    kept = stretch_grid(c2w, h, w, f, (2.0, 1.0), 0.3, points=behind)
    assert (kept.height, kept.width) == (whole.height, whole.width)


def test_a_stretched_frame_through_an_off_centre_camera(card):
    """Non-square pixels and an off-centre principal point (a real capture's camera): the stretched frame is traced
    on a grid, finite, and shows the object where the one-scale frame does."""
    bundle, test = card
    xyz = bundle.model.xyz.detach()
    c2w, h, w = _cam(test), 4 * test.height, 4 * test.width
    k = Intrinsics(4.2 * test.focal, 3.8 * test.focal, 0.45 * w, 0.55 * h)
    pts = xyz * torch.tensor([3.0, 1.0, 1.0])
    on = EditState(bundle, points=pts, cfg=EditConfig(stretch_grid=1.5))
    a = render_edited(on, c2w, h, w, k)
    b = render_edited(EditState(bundle, points=pts, cfg=EditConfig(stretch_grid=0.0)), c2w, h, w, k)
    assert on._grid[1] is not None
    assert bool(torch.isfinite(a["rgb"]).all()) and bool(torch.isfinite(a["alpha"]).all())
    assert float(((a["alpha"] > 0.5) == (b["alpha"] > 0.5)).float().mean()) > 0.9


def test_frames_without_a_squash_are_todays_and_squashed_ones_are_traced_finer_across(card):
    """squash_grid: a frame at the output's pixels whose surface is squashed on the screen is traced on a grid
    finer across the squash (at the training scale, at most 1 / MIN_GRID_SCALE times) and the output's pixels along
    it; rest frames, a shift, a uniform scale and a squash along the view axis are the frames without it, bit for
    bit; extreme squashes stay finite."""
    bundle, test = card
    xyz = bundle.model.xyz.detach()
    c2w, h, w, f = _cam(test), test.height, test.width, test.focal
    on, off = EditConfig(squash_grid=1.5), EditConfig(squash_grid=0.0)
    view = c2w[:3, 2]  # the camera's back axis: a squash along it leaves the screen alone
    flat_view = xyz - 0.9 * (xyz @ view)[:, None] * view[None]
    for pts in (None, xyz + 0.01, xyz * 0.5, flat_view):
        st = EditState(bundle, points=pts, cfg=on)
        a = render_edited(st, c2w, h, w, f)
        b = render_edited(EditState(bundle, points=pts, cfg=off), c2w, h, w, f)
        assert torch.equal(a["rgb"], b["rgb"]) and torch.equal(a["alpha"], b["alpha"])
        assert st._grid is None or st._grid[1] is None
    pts = xyz * torch.tensor([1.0, 1.0, 0.3])  # squashed along world z: the image's up axis
    st = EditState(bundle, points=pts, cfg=on)
    a = render_edited(st, c2w, h, w, f)
    b = render_edited(EditState(bundle, points=pts, cfg=off), c2w, h, w, f)
    grid = st._grid[1]
    assert grid is not None and grid.scales[0] == 1.0 and MIN_GRID_SCALE <= grid.scales[1] < 0.5
    assert abs(grid.angle) < 0.05  # the output's rows run along the unsquashed x axis
    assert a["trace"].coarse is not None and a["trace"].coarse.low.shape[0] > a["rgb"].shape[0] * 0.3 / 0.5
    for out in (a, b):
        assert bool(torch.isfinite(out["rgb"]).all()) and bool(torch.isfinite(out["alpha"]).all())
    assert float(((a["alpha"] > 0.5) == (b["alpha"] > 0.5)).float().mean()) > 0.9
    for pts in (xyz * torch.tensor([1.0, 1.0, 1e-6]), xyz * torch.tensor([1.0, 1.0, 0.0]),
                xyz * torch.tensor([1.0, 1e-3, 1e-3])):
        out = render_edited(EditState(bundle, points=pts, cfg=on), c2w, h, w, f)
        assert bool(torch.isfinite(out["rgb"]).all()) and bool(torch.isfinite(out["alpha"]).all())


def test_a_squash_grid_holds_at_most_its_pixel_budget(card):
    """A squashed object with a point behind the camera leaves the grid uncut: its pixels are coarsened to at most
    SQUASH_GRID_MAX_PIXELS times the output's, still finer than the output across the squash; the frame is finite."""
    from core.frames.edited import SQUASH_GRID_MAX_PIXELS

    bundle, test = card
    xyz = bundle.model.xyz.detach()
    c2w, h, w, f = _cam(test), test.height, test.width, test.focal
    pts = xyz * torch.tensor([1.0, 1.0, 0.02])
    behind = torch.cat([pts, (c2w[:3, 3] + c2w[:3, 2])[None]])  # one point just behind the camera
    n = behind.shape[0]
    st = EditState(bundle, points=behind, ids=torch.cat([torch.arange(n - 1), torch.tensor([0])]),
                   cfg=EditConfig(squash_grid=1.5))
    out = render_edited(st, c2w, h, w, f)
    grid = st._grid[1]
    assert grid is not None and grid.height * grid.width <= SQUASH_GRID_MAX_PIXELS * h * w * 1.02
    assert MIN_GRID_SCALE < grid.scales[1] < 1.0
    assert bool(torch.isfinite(out["rgb"]).all()) and bool(torch.isfinite(out["alpha"]).all())


def test_a_squash_grid_averages_the_painted_texture_like_the_colour(card):
    """grid_texture: on a squash grid finer than grid_texture output pixels across the squash, the painted texture
    is looked up per grid ray and averaged back over each output pixel: stripes squashed to several per pixel come
    out near their mean instead of aliased; frames without such a grid (no squash, or a grid coarser than the
    threshold) are the frames without it, bit for bit; both blends stay finite."""
    bundle, test = card
    xyz = bundle.model.xyz.detach()
    h, w, f = test.height, test.width, test.focal
    c2w = look_at((0.0, 0.01, float(test.c2w[0][:3, 3].norm())), target=(0.0, 0.0, 0.0)).float()  # face-on

    def stripes(x):  # 0.08 units a period along y: squashed 5x, ~4 periods per output pixel
        v = (torch.sin(x[:, 1] * (2 * math.pi / 0.08)) > 0).to(x.dtype)
        return torch.stack([v, v, v], 1)
    painted = bundle.atlas.packed_image().clone()
    painted[::2] = 1.0 - painted[::2]

    def frame(pts, gt, blend="soft"):
        st = EditState(bundle, points=pts, atlas=painted, cfg=EditConfig(squash_grid=1.5, grid_texture=gt,
                                                                         blend=blend))
        out = render_edited(st, c2w, h, w, f, texture_fn=stripes)
        grid = st._grid[1] if st._grid is not None else None
        a = out["alpha"] > 0.5
        al = out["alpha"][a][:, None]
        return out, grid, ((out["rgb"][a] - (1 - al)) / al).clamp(0, 1)  # the object colour under a white bg
    squashed = xyz * torch.tensor([1.0, 0.2, 1.0])
    off, grid, tex_off = frame(squashed, 0.0)
    on, _, tex_on = frame(squashed, 0.25)
    assert grid is not None and grid.scales[1] <= 0.25 and tex_on.shape[0] > 20
    assert float(tex_on.std()) < 0.5 * float(tex_off.std())
    assert abs(float(tex_on.mean()) - float(tex_off.mean())) < 0.05
    assert abs(float(tex_on.mean()) - 0.735) < 0.06  # linear-light mean of black and white stripes, in sRGB
    coarse, _, _ = frame(squashed, 0.1)  # the grid is coarser than the threshold: per-pixel lookups
    assert torch.equal(coarse["rgb"], off["rgb"])
    a, grid, _ = frame(xyz + 0.01, 0.25)  # moved, not squashed: no grid
    assert grid is None and torch.equal(a["rgb"], frame(xyz + 0.01, 0.0)[0]["rgb"])
    for pts, blend in ((xyz * torch.tensor([1.0, 0.0, 1.0]), "soft"), (squashed, "threshold")):  # flat; the paper's
        a, _, _ = frame(pts, 0.25, blend)
        assert bool(torch.isfinite(a["rgb"]).all()) and bool(torch.isfinite(a["alpha"]).all())


def test_the_grid_texture_weights_the_colour_by_the_mask(card, monkeypatch):
    """_grid_lookup: a painted stripe pattern whose unpainted stripes (mask 0) hold black comes back as the
    painted colour (white) at the stripes' share of mask, so the soft blend m T + (1 − m) c of the averages is the
    average of each grid ray's blend, not a painted colour darkened by the unpainted texels' black."""
    import core.frames.edited as edited

    bundle, test = card
    xyz = bundle.model.xyz.detach()
    h, w, f = test.height, test.width, test.focal
    c2w = look_at((0.0, 0.01, float(test.c2w[0][:3, 3].norm())), target=(0.0, 0.0, 0.0)).float()
    painted = bundle.atlas.packed_image().clone()
    painted[::2] = 1.0 - painted[::2]
    st = EditState(bundle, points=xyz * torch.tensor([1.0, 0.2, 1.0]), atlas=painted,
                   cfg=EditConfig(squash_grid=1.5, grid_texture=0.25))
    out = render_edited(st, c2w, h, w, f)
    grid, low = st._grid[1], out["trace"].coarse.low
    assert grid is not None and grid.scales[1] <= 0.25

    def stripes(state, x, texture_fn=None):  # painted white on every other 0.08-unit stripe, unpainted black between
        v = (torch.sin(x[:, 1] * (2 * math.pi / 0.08)) > 0).to(x.dtype)
        return torch.stack([v, v, v, v], 1)
    monkeypatch.setattr(edited, "_lookup", stripes)
    tr = out["trace"]
    sel = torch.nonzero(tr.active & (tr.fg > 1e-4)).squeeze(1)
    rgb, m, ok = edited._grid_lookup(st, low, grid, sel, h, w)
    inner = ok & (m > 0.2)
    assert int(inner.sum()) > 20 and bool(torch.isfinite(rgb).all())
    assert float((rgb[inner] - 1.0).abs().max()) < 1e-3  # the painted colour, not the mean with the black
    assert 0.3 < float(m[inner].mean()) < 0.7  # about half of each pixel painted


def test_a_stretch_grid_never_takes_the_grid_texture(card):
    """grid_texture applies to squash grids only: a stretched frame whose stretch grid is at the output's pixels
    across the stretch (scale 1, the largest grid_texture) renders the same with grid_texture 1 as with 0."""
    bundle, test = card
    xyz = bundle.model.xyz.detach()
    painted = bundle.atlas.packed_image().clone()
    painted[::2] = 1.0 - painted[::2]
    args = (_cam(test), 2 * test.height, 2 * test.width, 2 * test.focal)
    pts = xyz * torch.tensor([3.0, 1.0, 0.3])  # stretched along the rows, thinner across: across at the output scale
    outs = [render_edited(EditState(bundle, points=pts, atlas=painted, cfg=EditConfig(grid_texture=g)), *args)
            for g in (0.0, 1.0)]
    assert outs[1]["stats"]["grid"] is not None and outs[1]["stats"]["grid"][1] == 1.0
    assert not outs[1]["stats"]["grid_texture"]
    assert torch.equal(outs[0]["rgb"], outs[1]["rgb"])
