"""Rendering with local deformation gradients: rest frames unchanged, the canonical-frame attention undoes a
uniform scale, the deform-gradient correspondence works through render_edited."""
import dataclasses

import pytest
import torch

from core.edits.bake import bake
from core.edits.deformation import DeformationConfig
from core.frames.edited import EditConfig, EditState, render_edited
from core.points.neighbors.select import screen_index
from core.points.render import pixel_grid, render_frame, trace_frame
from core.images.rays import project_on_ray
from tests.helpers.tiny import card_half_swung_behind, tiny_bundle

# every part on (at rest the fold rule sees one displacement, 0, and drops nothing; the occlusion rule finds every
# neighbour in every other's layer)
ALL_ON = EditConfig(correspondence="deform-gradient", f_attention=True, f_radius=True, f_fill=True, fold_radius=2.0,
                    f_occlusion=True, f_fill_tear=13.5)


@pytest.fixture(scope="module")
def tiny():
    return tiny_bundle("card")


def _half_split(x):
    red = (x[:, 0] > 0).float()[:, None]
    return red * torch.tensor([1.0, 0.0, 0.0]) + (1 - red) * torch.tensor([0.0, 0.0, 1.0]), None


def _extreme_poses(xyz):
    """Non-finite and huge positions, a 1000× stretch and a squash to a plane of the points xyz [N, 3]."""
    wild = xyz.clone()
    wild[::13] = float("nan")
    wild[1::17] = 1e30
    return wild, xyz * torch.tensor([1e3, 1.0, 1.0]), xyz * torch.tensor([1.0, 1.0, 0.0])


def test_rest_frames_equal_todays_with_every_part_on(tiny):
    bundle, _, test = tiny
    n = bundle.model.num_points
    xyz = bundle.model.xyz.detach()
    atlas = bake(bundle.atlas, _half_split)
    today = EditState(bundle, atlas=atlas)
    # ids force the "moved" path: F is fitted (≈ I), attention keys, radius and correspondence all use it
    forced = EditState(bundle, points=xyz.clone(), ids=torch.arange(n), atlas=atlas, cfg=ALL_ON)
    assert forced.moved and forced.radius_scale == 1.0 and forced.filled_points == 0 and forced.rebase_depth
    assert torch.allclose(forced.inv_f, torch.eye(3).expand(n, 3, 3), atol=1e-5)
    for i in range(len(test)):
        a = render_edited(today, test.c2w[i], test.height, test.width, test.focal)
        b = render_edited(forced, test.c2w[i], test.height, test.width, test.focal)
        # colours to 1e-4: the half-split texture's hard edge turns the float32 rounding of the two
        # correspondence forms (≈ 1e-7 of a coordinate) into up to a few 1e-5 of colour; the attention below to 1e-5
        assert torch.allclose(a["rgb"], b["rgb"], atol=1e-4)
        assert torch.allclose(a["alpha"], b["alpha"], atol=1e-5)
        ta = trace_frame(bundle.model, test.c2w[i], test.height, test.width, test.focal)
        tb = trace_frame(bundle.model, test.c2w[i], test.height, test.width, test.focal,
                         inv_f=torch.eye(3).expand(n, 3, 3))
        assert torch.allclose(ta.weights, tb.weights, atol=1e-5)
        # f_depth nearest (the default, on in `forced`): at F = I the rebased depths are today's
        tc = trace_frame(bundle.model, test.c2w[i], test.height, test.width, test.focal,
                         inv_f=torch.eye(3).expand(n, 3, 3), rebase_depth=True)
        assert torch.allclose(ta.weights, tc.weights, atol=1e-5)


def test_canonical_frame_attention_undoes_a_uniform_scale(tiny):
    """Points and camera scaled by 3 about the origin project to the same pixels; measured in each point's
    canonical frame (F = 3 I), the attention sees exactly the canonical frame's geometry again."""
    bundle, _, test = tiny
    xyz = bundle.model.xyz.detach()
    c2w = test.c2w[0].clone()
    c2w[:3, 3] *= 3.0
    ref = render_frame(bundle.model, test.c2w[0], test.height, test.width, test.focal)["rgb"]
    exact = DeformationConfig(sheet_ratio=0.0)  # the card is thin: fit all three directions (affine: exact)
    # the keys alone: no points added (a fill would make the scaled cloud denser than the canonical one), no reach
    on = EditState(bundle, points=xyz * 3.0, cfg=EditConfig(f_attention=True, f_fill=False, f_radius=False),
                   deformation=exact)
    off = EditState(bundle, points=xyz * 3.0, cfg=EditConfig(f_attention=False, f_fill=False, f_radius=False),
                    deformation=exact)
    assert torch.allclose(on.inv_f, torch.eye(3).expand_as(on.inv_f) / 3.0, atol=1e-4)
    got = render_edited(on, c2w, test.height, test.width, test.focal)["rgb"]
    plain = render_edited(off, c2w, test.height, test.width, test.focal)["rgb"]
    assert float((got - ref).abs().max()) < 1e-3
    assert float((plain - ref).abs().max()) > 1e-2  # today's keys see 3× the offsets


def test_deform_gradient_correspondence_undoes_a_stretch(tiny):
    """Stretch the card 3× along x: the true canonical point of a ray's surface point x_def is x_def / (3, 1, 1).
    deform-gradient recovers it (F is exact for this affine map); the translation-only deform-aware
    correspondence is off by (2/3)·|x̂ − x_def| along x, naive by x̂'s offset from its ray."""
    bundle, _, test = tiny
    xyz = bundle.model.xyz.detach()
    s = torch.tensor([3.0, 1.0, 1.0])
    atlas = bake(bundle.atlas, _half_split)
    c2w = test.c2w[0].clone()
    c2w[:3, 3] *= 2.0  # step back: the stretched card stays in the frame
    err = {}
    for mode in ("naive", "deform-aware", "deform-gradient"):
        # the fold rule off: it would take x̂ from a subset of the neighbours, not the trace's x̂ used below
        st = EditState(bundle, points=xyz * s, atlas=atlas,
                       cfg=EditConfig(correspondence=mode, f_attention=True, fold_radius=0.0, f_fill=False))
        out = render_edited(st, c2w, test.height, test.width, test.focal)
        tr = out["trace"]
        hit = torch.isfinite(out["x_can"].reshape(-1, 3)).all(1) & (out["alpha"].reshape(-1) > 0.5)
        assert int(hit.sum()) > 50
        x_def = project_on_ray(tr.x[hit], tr.origins[hit], tr.dirs[hit])
        err[mode] = float((out["x_can"].reshape(-1, 3)[hit] - x_def / s).norm(dim=1).mean())
    assert err["deform-gradient"] < 1e-3
    assert err["deform-gradient"] < 0.2 * min(err["naive"], err["deform-aware"]), err


def test_extreme_poses_render_finite_with_every_part_on(tiny):
    """Squash to 0, 1e30 outliers, NaN points and a stretch beyond max_stretch: finite frames, all parts on."""
    bundle, _, test = tiny
    xyz = bundle.model.xyz.detach()
    atlas = bake(bundle.atlas, _half_split)
    squash = xyz * torch.tensor([1.0, 1.0, 0.0])
    wild = xyz.clone()
    wild[::17] = 1e30
    wild[1::19] = float("nan")
    for pts in (squash, wild, xyz * torch.tensor([100.0, 1.0, 1.0])):
        for mode in ("tangent", "keep", "undo"):
            cfg = EditConfig(correspondence="deform-gradient", f_attention=True, f_radius=True, f_compression=mode,
                             f_occlusion=True)
            out = render_edited(EditState(bundle, points=pts, atlas=atlas, cfg=cfg), test.c2w[0], test.height,
                                test.width, test.focal)
            assert torch.isfinite(out["rgb"]).all() and torch.isfinite(out["alpha"]).all()
            x = out["x_can"][torch.isfinite(out["x_can"]).all(-1)]
            assert out["stats"]["texture_rays"] == 0 or x.numel() > 0


def test_rest_frames_unchanged_with_fill_and_fold_rule(tiny):
    """Points not moved (none given, or the canonical ones): every part, the fill and the fold rule included,
    leaves the frame as the paper's renderer draws it."""
    bundle, _, test = tiny
    atlas = bake(bundle.atlas, _half_split)
    paper = EditConfig(f_attention=False, f_fill=False, fold_radius=0.0)
    every = EditConfig(correspondence="deform-gradient", f_attention=True, f_radius=True, f_fill=True,
                       fold_radius=2.0, f_occlusion=True)
    a = EditState(bundle, atlas=atlas, cfg=paper)
    for b in (EditState(bundle, atlas=atlas, cfg=every),
              EditState(bundle, points=bundle.model.xyz.detach().clone(), atlas=atlas, cfg=every)):
        assert not b.moved and b.filled_points == 0
        for i in range(len(test)):
            ra = render_edited(a, test.c2w[i], test.height, test.width, test.focal)
            rb = render_edited(b, test.c2w[i], test.height, test.width, test.focal)
            assert torch.equal(ra["rgb"], rb["rgb"]) and torch.equal(ra["alpha"], rb["alpha"])


def test_fill_closes_a_stretch_and_keeps_ids_features_and_canonical_points(tiny):
    """The card stretched 4× along x with today's keys: its points pull apart and rays fall through between them;
    filled, the frame covers more of the stretched card. Added points carry their source's features (the "nearer"
    rule) and F and sit between their pair's canonical points."""
    bundle, _, test = tiny
    xyz = bundle.model.xyz.detach()
    s = torch.tensor([4.0, 1.0, 1.0])
    c2w = test.c2w[0].clone()
    c2w[:3, 3] *= 2.5
    cover = {}
    for fill in (False, True):
        st = EditState(bundle, points=xyz * s, cfg=EditConfig(f_attention=False, f_fill=fill, f_fill_budget=4.0,
                                                              f_fill_features="nearer"))
        out = render_edited(st, c2w, test.height, test.width, test.focal)
        assert torch.isfinite(out["rgb"]).all() and torch.isfinite(out["alpha"]).all()
        cover[fill] = int((out["alpha"] > 0.5).sum())
        if fill:
            n, p = bundle.model.num_points, st.filled_points
            assert p > 0 and st.points.shape[0] == n + p and st.ids.shape[0] == n + p
            assert torch.equal(st.features, bundle.model.features.detach()[st.ids])
            assert torch.allclose(st.points[n:], st.p_can[n:] * s, atol=1e-4)  # the stretch is affine
            assert st.f.shape[0] == n + p and torch.equal(st.f[n:], st.f[st.ids[n:]])
            assert out["stats"]["filled_points"] == p
    assert cover[True] > cover[False]


def test_fill_tear_leaves_pairs_pulled_past_it_open_and_rest_frames_unchanged(tiny):
    """f_fill_tear: under a 16× stretch along x (pairs grow up to 16×) a tear growth of 8 adds fewer points than the
    default (20) and none whose pair grew past 8; rest frames forced through the moved path equal today's."""
    bundle, _, test = tiny
    xyz = bundle.model.xyz.detach()
    n = bundle.model.num_points
    s = torch.tensor([16.0, 1.0, 1.0])
    states = {t: EditState(bundle, points=xyz * s, cfg=EditConfig(f_fill_budget=8.0, f_fill_tear=t))
              for t in (20.0, 8.0)}
    assert 0 < states[8.0].filled_points < states[20.0].filled_points
    st = states[8.0]
    a, b, _ = st._fill_blend
    grown = (xyz[b] - xyz[a]).mul(s).norm(dim=1) / (xyz[b] - xyz[a]).norm(dim=1)
    assert float(grown.max()) <= 8.0 + 1e-4 and float(states[20.0]._fill_blend[0].numel()) > 0
    c2w = test.c2w[0].clone()
    c2w[:3, 3] *= 4.0
    out = render_edited(st, c2w, test.height, test.width, test.focal)
    assert torch.isfinite(out["rgb"]).all() and torch.isfinite(out["alpha"]).all()
    today = EditState(bundle, cfg=EditConfig(f_attention=False, f_fill=False, fold_radius=0.0))
    rest = EditState(bundle, points=xyz.clone(), ids=torch.arange(n), cfg=EditConfig(f_fill_tear=8.0))
    assert rest.filled_points == 0
    for i in range(len(test)):
        ra = render_edited(today, test.c2w[i], test.height, test.width, test.focal)
        rb = render_edited(rest, test.c2w[i], test.height, test.width, test.focal)
        assert torch.allclose(ra["rgb"], rb["rgb"], atol=1e-5) and torch.allclose(ra["alpha"], rb["alpha"], atol=1e-5)


def test_blended_fill_mixes_both_ends_and_leaves_rest_frames_unchanged(tiny):
    """f_fill_features = blend: an added point's features and influence are its pair's two ends' mixed by where it
    lies between them (the given points keep theirs); nothing changes at rest, and extreme stretches stay finite."""
    bundle, _, test = tiny
    model = bundle.model
    xyz = model.xyz.detach()
    n = model.num_points
    s = torch.tensor([4.0, 1.0, 1.0])
    nearer = EditState(bundle, points=xyz * s, cfg=EditConfig(f_fill_budget=2.0, f_fill_features="nearer"))
    blend = EditState(bundle, points=xyz * s, cfg=EditConfig(f_fill_budget=2.0, f_fill_features="blend"))
    p = blend.filled_points
    assert p > 0 and p == nearer.filled_points and torch.equal(blend.points, nearer.points)
    assert torch.equal(blend.features[:n], nearer.features[:n]) and torch.equal(blend.influence[:n],
                                                                                 nearer.influence[:n])
    # each added point: features = (1 − t) f_a + t f_b with t its fraction of the canonical segment from a to b
    a, b, t = blend._fill_blend
    assert torch.equal(a, blend.ids[n:]) and bool((t > 0).all()) and bool((t <= 0.5).all())
    assert torch.allclose(blend.p_can[n:], (1 - t)[:, None] * xyz[a] + t[:, None] * xyz[b], atol=1e-5)
    feats = model.features.detach()
    assert torch.allclose(blend.features[n:], (1 - t)[:, None] * feats[a] + t[:, None] * feats[b], atol=1e-6)
    differs = (feats[a] - feats[b]).abs().amax(1) > 1e-3
    assert bool(differs.any()) and not torch.allclose(blend.features[n:][differs], nearer.features[n:][differs])
    c2w = test.c2w[0].clone()
    c2w[:3, 3] *= 2.5
    for pts in (xyz * s, xyz * torch.tensor([1e3, 1.0, 1.0])):
        out = render_edited(EditState(bundle, points=pts, cfg=EditConfig(f_fill_features="blend")), c2w,
                            test.height, test.width, test.focal)
        assert torch.isfinite(out["rgb"]).all() and torch.isfinite(out["alpha"]).all()
    # rest: the canonical points given (nothing moved) or forced through the moved path with ids
    today = EditState(bundle, cfg=EditConfig(f_attention=False, f_fill=False, fold_radius=0.0))
    for st in (EditState(bundle, points=xyz.clone(), cfg=EditConfig(f_fill_features="blend")),
               EditState(bundle, points=xyz.clone(), ids=torch.arange(n), cfg=EditConfig(f_fill_features="blend"))):
        assert st.filled_points == 0
        for i in range(len(test)):
            ra = render_edited(today, test.c2w[i], test.height, test.width, test.focal)
            rb = render_edited(st, test.c2w[i], test.height, test.width, test.focal)
            assert torch.allclose(ra["rgb"], rb["rgb"], atol=1e-5) and torch.allclose(ra["alpha"], rb["alpha"],
                                                                                       atol=1e-5)


def test_local_map_fold_test_leaves_rest_frames_and_a_uniform_stretch_alone(tiny):
    """fold_test = local-map: at rest (forced through the moved path, F ≈ I) the textured frame is today's; under a
    uniform stretch (F exact) the fold rule drops nothing, so the lookups equal those without the rule, while the
    displacement test at the same radius changes them."""
    bundle, _, test = tiny
    xyz = bundle.model.xyz.detach()
    atlas = bake(bundle.atlas, _half_split)
    local = dict(fold_test="local-map", fold_radius=0.5)
    _forced_rest(bundle, test, EditConfig(**local), atlas=atlas, rgb_atol=1e-4)
    exact = DeformationConfig(sheet_ratio=0.0)
    s = torch.tensor([4.0, 1.0, 1.0])
    c2w = test.c2w[0].clone()
    c2w[:3, 3] *= 2.5
    x = {}
    for name, extra in (("off", dict(fold_radius=0.0)), ("local", local),
                        ("displacement", dict(fold_radius=0.5))):
        st = EditState(bundle, points=xyz * s, atlas=atlas, cfg=EditConfig(f_fill=False, **extra), deformation=exact)
        x[name] = render_edited(st, c2w, test.height, test.width, test.focal)["x_can"]
    hit = torch.isfinite(x["off"]).all(-1)
    assert int(hit.sum()) > 50
    assert torch.allclose(x["local"][hit], x["off"][hit], atol=1e-5)
    assert float((x["displacement"][hit] - x["off"][hit]).norm(dim=-1).max()) > 1e-3


def test_gap_reach_only_where_the_fill_left_gaps_and_rest_unchanged(tiny):
    """f_radius with the gap rule: at rest (forced through the moved path) the frame is today's; a stretch the fill
    closes (a generous budget) reaches no farther; one the budget leaves sparse gets reach > 1 on those points and
    covers at least as much; extreme poses stay finite."""
    bundle, _, test = tiny
    xyz = bundle.model.xyz.detach()
    on = dict(f_radius=True, f_radius_rule="gap", f_reach_gate=0.0)
    forced = _forced_rest(bundle, test, EditConfig(**on))
    assert forced.search_radius()[1] is not None and bool((forced.reach == 1).all())
    s = torch.tensor([4.0, 1.0, 1.0])
    closed = EditState(bundle, points=xyz * s, cfg=EditConfig(f_fill_budget=8.0, **on))
    assert bool((closed.reach == 1).all())
    sparse = EditState(bundle, points=xyz * s, cfg=EditConfig(f_fill_budget=0.1, **on))
    off = EditState(bundle, points=xyz * s, cfg=EditConfig(f_fill_budget=0.1, f_radius=False))
    assert sparse.reach.shape[0] == sparse.points.shape[0] and float(sparse.reach.max()) > 1.5
    assert off.search_radius() == (1.0, None)
    c2w = test.c2w[0].clone()
    c2w[:3, 3] *= 2.5
    got = render_edited(sparse, c2w, test.height, test.width, test.focal)
    ref = render_edited(off, c2w, test.height, test.width, test.focal)
    assert int((got["alpha"] > 0.5).sum()) >= int((ref["alpha"] > 0.5).sum())
    assert int((got["trace"].idx >= 0).sum()) > int((ref["trace"].idx >= 0).sum())
    for pts in _extreme_poses(xyz):
        for rule in ("gap", "budget", "frame"):
            st = EditState(bundle, points=pts, cfg=EditConfig(f_radius=True, f_radius_rule=rule, f_fill_budget=0.1))
            out = render_edited(st, c2w, test.height, test.width, test.focal)
            assert torch.isfinite(out["rgb"]).all() and torch.isfinite(out["alpha"]).all()


def test_reach_gate_adds_far_points_only_to_rays_the_plain_search_covers(tiny):
    """f_reach_gate: with the gap reach, the rays that get neighbours are exactly those the plain search (no reach)
    gives one, and each of them gets the ungated reach search's neighbours; rest frames are today's; extreme poses
    stay finite."""
    bundle, _, test = tiny
    xyz = bundle.model.xyz.detach()
    # the gate alone: without the perspective reach (its own test below), which widens near points' gates
    gate = dict(f_radius=True, f_radius_rule="gap", f_reach_gate=1.0, f_reach_perspective=0.0)
    _forced_rest(bundle, test, EditConfig(**gate))
    s = torch.tensor([4.0, 1.0, 1.0])
    c2w = test.c2w[0].clone()
    c2w[:3, 3] *= 2.5
    # every ray traced (no squash grid: the far camera sees the stretched card below the training scale across)
    states = {name: EditState(bundle, points=xyz * s, cfg=EditConfig(f_fill_budget=0.1, squash_grid=0.0, **over))
              for name, over in (("plain", dict(f_radius=False)),
                                 ("reach", dict(gate, f_reach_gate=0.0)), ("gate", gate))}
    tr = {name: render_edited(st, c2w, test.height, test.width, test.focal)["trace"] for name, st in states.items()}
    assert float(states["gate"].reach.max()) > 1.5
    covered = tr["plain"].active
    assert torch.equal(tr["gate"].active, covered)
    assert bool((tr["reach"].active & ~covered).any())  # the ungated reach widens the covered rays
    assert torch.equal(tr["gate"].idx[covered], tr["reach"].idx[covered])
    assert torch.allclose(tr["gate"].weights[covered], tr["reach"].weights[covered], atol=1e-6)
    assert int((tr["gate"].idx >= 0).sum()) > int((tr["plain"].idx >= 0).sum())  # the reach still adds points
    for pts in _extreme_poses(xyz):
        out = render_edited(EditState(bundle, points=pts, cfg=EditConfig(f_fill_budget=0.1, **gate)), c2w,
                            test.height, test.width, test.focal)
        assert torch.isfinite(out["rgb"]).all() and torch.isfinite(out["alpha"]).all()


def test_reach_surround_adds_only_rays_the_reach_candidates_surround(tiny):
    """f_reach_surround: the gated frame's rays keep their neighbours; of the rays the gate emptied, those the
    screen index finds surrounded by candidates (tested against brute force in tests/core/points/test_neighbors.py)
    get the ungated reach search's neighbours — here the rays over a hole cut into the stretched card; rest frames
    are today's; extreme poses stay finite."""
    bundle, _, test = tiny
    xyz = bundle.model.xyz.detach()
    # render_mode pixels: every ray traced at the frame's size (the upsampled mode would trace the training scale)
    inside = dict(f_radius=True, f_radius_rule="gap", f_reach_gate=1.0, f_reach_surround=True, render_mode="pixels",
                  f_reach_perspective=0.0)  # the gate's rules alone (the perspective reach: its own test below)
    _forced_rest(bundle, test, EditConfig(**inside))
    keep = torch.nonzero((xyz[:, :2] - xyz[:, :2].mean(0)).norm(dim=1) > 0.45).squeeze(1)  # a hole in the card
    pts = xyz[keep] * torch.tensor([4.0, 1.0, 1.0])
    c2w = test.c2w[0].clone()
    c2w[:3, 3] *= 1.5
    states = {name: EditState(bundle, points=pts, ids=keep, cfg=EditConfig(f_fill=False, f_occlusion=False, **over))
              for name, over in (("reach", dict(inside, f_reach_gate=0.0)),
                                 ("gate", dict(inside, f_reach_surround=False)), ("inside", inside))}
    assert states["inside"].reach_surround and not states["reach"].reach_surround
    tr = {name: render_edited(st, c2w, test.height, test.width, test.focal)["trace"] for name, st in states.items()}
    gated, got, open_ = tr["gate"].active, tr["inside"].active, tr["reach"].active
    assert torch.equal(tr["inside"].idx[gated], tr["gate"].idx[gated])
    assert torch.equal(tr["inside"].idx[got], tr["reach"].idx[got])
    assert bool((got & ~gated).any()) and not bool((got & ~open_).any()) and bool((open_ & ~got).any())
    st, model = states["inside"], bundle.model
    index = screen_index(st.points, model.cfg.neighbors, model.cfg.k, c2w, test.height, test.width, test.focal,
                         model.cfg.neighbor_radius_px, reach=st.reach, reach_gate=1.0, reach_surround=True)
    want = (index.query(pixel_grid(test.height, test.width, "cpu"), model.cfg.k).idx >= 0).any(1)
    assert torch.equal(got, want)
    for pts in _extreme_poses(xyz):
        out = render_edited(EditState(bundle, points=pts, cfg=EditConfig(f_fill_budget=0.1, **inside)), c2w,
                            test.height, test.width, test.focal)
        assert torch.isfinite(out["rgb"]).all() and torch.isfinite(out["alpha"]).all()


def _forced_rest(bundle, test, cfg: EditConfig, atlas=None, rgb_atol=1e-5, views=None) -> EditState:
    """The model's points forced through the moved path (ids given, F ≈ I) with cfg: checks that its frames equal
    today's (rgb to rgb_atol, alpha to 1e-5) on `views` (default: every test camera); returns that state."""
    n = bundle.model.num_points
    today = EditState(bundle, atlas=atlas)
    forced = EditState(bundle, points=bundle.model.xyz.detach().clone(), ids=torch.arange(n), atlas=atlas, cfg=cfg)
    for i in range(len(test)) if views is None else views:
        a = render_edited(today, test.c2w[i], test.height, test.width, test.focal)
        b = render_edited(forced, test.c2w[i], test.height, test.width, test.focal)
        assert torch.allclose(a["rgb"], b["rgb"], atol=rgb_atol) and torch.allclose(a["alpha"], b["alpha"], atol=1e-5)
    return forced


def _gate_checked(bundle, pts, gate, c2w, height, width, focal, fill):
    """Renders the posed points pts [N, 3] with the gate options `gate` (f_reach_gate 1.5 plus the rule) and with
    the ungated reach, the 1-cap gate and the wide 1.5-cap gate; checks that the rule's rays with neighbours
    include the 1-cap gate's, lie within the wide gate's, keep the ungated search's neighbours and equal the
    screen index's answer. Returns (the rule's rays [H*W] bool, the 1-cap gate's)."""
    states = {name: EditState(bundle, points=pts, cfg=EditConfig(f_fill=fill, f_fill_budget=0.1, f_occlusion=False,
                                                                 **over))
              for name, over in (("reach", dict(gate, f_reach_gate=0.0)), ("one", dict(gate, f_reach_gate=1.0)),
                                 ("wide", dict(gate, f_reach_gate_own=False, f_reach_between=False)), ("own", gate))}
    st, model = states["own"], bundle.model
    assert st.reach_gate_own == gate["f_reach_gate_own"] and st.reach_between == gate["f_reach_between"]
    assert not (states["reach"].reach_gate_own or states["reach"].reach_between)
    tr = {name: render_edited(s, c2w, height, width, focal)["trace"] for name, s in states.items()}
    got = tr["own"].active
    assert not bool((tr["one"].active & ~got).any()) and not bool((got & ~tr["wide"].active).any())
    assert torch.equal(tr["own"].idx[got], tr["reach"].idx[got])
    index = screen_index(st.points, model.cfg.neighbors, model.cfg.k, c2w, height, width, focal,
                         model.cfg.neighbor_radius_px, reach=st.reach, reach_gate=1.5,
                         reach_gate_own=gate["f_reach_gate_own"], reach_between=gate["f_reach_between"])
    assert torch.equal(got, (index.query(pixel_grid(height, width, "cpu"), model.cfg.k).idx >= 0).any(1))
    return got, tr["one"].active


@pytest.mark.parametrize("rule", ["own", "between"])
def test_reach_gate_own_lies_between_the_plain_gate_and_the_wide_one(tiny, rule):
    """f_reach_gate_own / f_reach_between with a gate of 1.5 caps: rest frames are today's; on a card stretched
    along x and on a card torn in two (a slot between its halves) the rays that get neighbours include the 1-cap
    gate's and lie within the 1.5-cap gate's, each with the ungated reach search's neighbours, and equal the screen
    index's answer; both rules open rays in the slot beyond the 1-cap gate (the own-reach rule also beside the
    stretched card's outline, where the between rule keeps them shut); extreme poses stay finite."""
    bundle, _, test = tiny
    xyz = bundle.model.xyz.detach()
    flag = dict(f_reach_gate_own=True, f_reach_between=False) if rule == "own" else \
        dict(f_reach_gate_own=False, f_reach_between=True)
    # render_mode pixels: every ray traced at the frame's size (the upsampled mode would trace the training scale)
    own = dict(f_radius=True, f_radius_rule="gap", f_reach_gate=1.5, render_mode="pixels", f_reach_perspective=0.0,
               **flag)  # the gate's rules alone (the perspective reach: its own test below)
    _forced_rest(bundle, test, EditConfig(**own))
    c2w = test.c2w[0].clone()
    c2w[:3, 3] *= 2.5
    got, one = _gate_checked(bundle, xyz * torch.tensor([4.0, 1.0, 1.0]), own, c2w, test.height, test.width,
                             test.focal, fill=True)
    if rule == "own":  # a uniaxial stretch leaves no hole between points (they stay dense along y): the rays the
        assert bool((got & ~one).any())  # own-reach gate adds lie beside the outline, which the between rule keeps
    # the card torn: its right half moved 2.5 plain caps along x, without fill, so the slot between the halves stays
    # open; its middle lies beyond the 1-cap gate and within 1.5 caps of points on both sides. Rendered at 3x the
    # test size so that the slot is several pixels wide (the card's 1000 points at 40² lie at the cap's floor).
    h, w, f, cam = 3 * test.height, 3 * test.width, 3 * test.focal, test.c2w[0]
    cap = screen_index(xyz, bundle.model.cfg.neighbors, bundle.model.cfg.k, cam, h, w, f,
                       bundle.model.cfg.neighbor_radius_px).radius_px(bundle.model.cfg.k)
    torn = xyz.clone()
    torn[xyz[:, 0] > xyz[:, 0].median(), 0] += 2.5 * cap * float(cam[:3, 3].norm()) / f
    got, one = _gate_checked(bundle, torn, own, cam, h, w, f, fill=False)
    assert int((got & ~one).sum()) >= 10
    for pts in _extreme_poses(xyz):
        out = render_edited(EditState(bundle, points=pts, cfg=EditConfig(f_fill_budget=0.1, **own)), c2w,
                            test.height, test.width, test.focal)
        assert torch.isfinite(out["rgb"]).all() and torch.isfinite(out["alpha"]).all()


def test_occlusion_rule_hides_a_part_swung_behind(tiny):
    """Half of the card swung behind the other half: with the occlusion rule the frame is closer to the front half
    rendered alone (the hidden half's points removed by ids) where that half covers the pixels (alpha > 0.5)."""
    bundle, _, test = tiny
    xyz = bundle.model.xyz.detach()
    c2w = test.c2w[0]
    pts, half = card_half_swung_behind(xyz, c2w)
    front = torch.nonzero(~half).squeeze(1)
    alone = render_edited(EditState(bundle, points=xyz[front], ids=front, cfg=EditConfig(f_fill=False)), c2w,
                          test.height, test.width, test.focal)
    err = {}
    for on in (False, True):
        st = EditState(bundle, points=pts, cfg=EditConfig(f_fill=False, f_occlusion=on))
        out = render_edited(st, c2w, test.height, test.width, test.focal)
        covered = alone["alpha"] > 0.5
        assert int(covered.sum()) > 20
        err[on] = float((out["rgb"] - alone["rgb"])[covered].abs().mean())
    assert err[True] < 0.7 * err[False], err


def test_auto_compression_picks_tangent_for_a_sheet_and_undo_for_a_thick_shell(tiny):
    """f_compression auto routes by the model's median canonical spread against f_thick_spread (which the
    stability tests check tells a sheet from a thick cloud): below it the tangent rule's keys, at or above it F⁻¹
    (undo); rest frames stay today's."""
    from core.edits.deformation import field_for

    bundle, _, test = tiny
    xyz = bundle.model.xyz.detach()
    pts = xyz * torch.tensor([1.0, 1.0, 0.05]) + 0.02 * torch.sin(5 * xyz.flip(1))
    spread = field_for(bundle.model).median_spread
    assert 0.0 < spread < 1.0
    sheet = EditState(bundle, points=pts, cfg=EditConfig(f_compression="auto", f_thick_spread=min(1.0, 1.01 * spread),
                                                         f_fill=False))
    tangent = EditState(bundle, points=pts, cfg=EditConfig(f_compression="tangent", f_fill=False))
    thick = EditState(bundle, points=pts, cfg=EditConfig(f_compression="auto", f_thick_spread=spread, f_fill=False))
    assert sheet.compression == "tangent" and thick.compression == "undo"
    assert torch.equal(sheet.inv_f_keys, tangent.inv_f_keys)
    assert torch.equal(thick.inv_f_keys, thick.inv_f)
    assert not torch.allclose(sheet.inv_f_keys, thick.inv_f_keys, atol=1e-3)
    _forced_rest(bundle, test, EditConfig(f_compression="auto", f_thick_spread=0.0), views=[0])


def test_the_correspondence_compression_rule_is_its_own(tiny):
    """f_correspondence_compression: keys = the keys' inverse gradients (today's deform-gradient correspondence);
    keep undoes rotation and stretch but never a compression (no singular value of the inverse above 1, the
    stretch's 1/5 kept); undo = F⁻¹; auto follows the model's thickness like f_compression. Under a 5× stretch
    with a squash across it, every rule gives finite canonical points, and keep's stay within the canonical
    cloud's reach."""
    bundle, _, test = tiny
    xyz = bundle.model.xyz.detach()
    pts = xyz * torch.tensor([5.0, 1.0, 0.05]) + 0.01 * torch.sin(5 * xyz.flip(1))
    atlas = bake(bundle.atlas, _half_split)
    states = {m: EditState(bundle, points=pts, atlas=atlas,
                           cfg=EditConfig(f_fill=False, correspondence="deform-gradient",
                                          f_correspondence_compression=m))
              for m in ("keys", "keep", "undo", "tangent")}
    assert states["keys"].inv_f_correspondence is states["keys"].inv_f_keys
    assert torch.equal(states["undo"].inv_f_correspondence, states["undo"].inv_f)
    keep = states["keep"].inv_f_correspondence
    sv = torch.linalg.svdvals(keep)
    assert bool(torch.isfinite(keep).all()) and float(sv.max()) <= 1.0 + 1e-4
    assert float(sv.min()) < 0.3  # the 5x stretch is undone
    assert float(torch.linalg.svdvals(states["undo"].inv_f).max()) > 5.0  # full F^-1 amplifies the squash
    spread = EditState(bundle, points=pts, cfg=EditConfig(f_correspondence_compression="auto", f_thick_spread=0.0))
    assert torch.equal(spread.inv_f_correspondence, spread.inv_f)  # thick by that threshold: undo
    c2w = test.c2w[0].clone()
    c2w[:3, 3] *= 2.0  # step back: the stretched card stays in the frame
    lo, hi = xyz.min(0).values, xyz.max(0).values
    reach = float((hi - lo).norm())
    for m, st in states.items():
        out = render_edited(st, c2w, test.height, test.width, test.focal)
        x = out["x_can"][torch.isfinite(out["x_can"]).all(-1)]
        assert x.shape[0] > 20, m
        assert bool(torch.isfinite(out["rgb"]).all()), m
        if m == "keep":
            assert float(((x - lo).clamp_max(0).norm(dim=-1) + (x - hi).clamp_min(0).norm(dim=-1)).max()) < reach
    # the frame reads only its rays' neighbours' rows: the same frame as with every row computed first
    whole = EditState(bundle, points=pts, atlas=atlas, cfg=states["keep"].cfg)
    assert torch.equal(whole.inv_f_correspondence, keep)
    a = render_edited(whole, c2w, test.height, test.width, test.focal)
    b = render_edited(EditState(bundle, points=pts, atlas=atlas, cfg=states["keep"].cfg), c2w, test.height,
                      test.width, test.focal)
    assert torch.equal(a["rgb"], b["rgb"]) and torch.equal(a["x_can"].nan_to_num(7.0), b["x_can"].nan_to_num(7.0))
    _forced_rest(bundle, test, EditConfig(correspondence="deform-gradient", f_correspondence_compression="keep"),
                 atlas=atlas, views=[0])


def test_added_points_copy_their_sources_inverses(tiny):
    """The tables that depend on F alone (the deform-gradient correspondence's inverse gradients, F⁻¹ of the
    occlusion rule) are computed once per given point: a point f_fill added copies its source's row (its F is
    that row's copy), with the same numbers as computing every row on its own."""
    bundle, _, test = tiny
    pts = bundle.model.xyz.detach() * torch.tensor([4.0, 1.0, 1.0])
    cfg = EditConfig(correspondence="deform-gradient", f_fill_budget=1.0)
    for mode in ("keep", "tangent"):
        c = dataclasses.replace(cfg, f_correspondence_compression=mode)
        st, own = EditState(bundle, points=pts, cfg=c), EditState(bundle, points=pts, cfg=c)
        own._f_source = None  # every row computed on its own
        m = st.points.shape[0] - st.filled_points
        assert st.filled_points > 0 and torch.equal(st._f_source[:m], torch.arange(m))
        computed = []
        rule = st._rule_inverse
        st._rule_inverse = lambda cap, rows=None, mode=None: (computed.append(rows.numel()),
                                                              rule(cap, rows, mode=mode))[1]
        rows = torch.arange(st.points.shape[0])
        assert torch.equal(st.inv_f_correspondence_at(rows), own.inv_f_correspondence_at(rows))
        assert sum(computed) <= m  # the added rows were copied
        added = rows[m:]  # the added rows asked for first: their sources are filled with them
        assert torch.equal(st.inv_f_at(added)[added], own.inv_f_at(added)[added])
        assert torch.equal(st.inv_f_at(rows), own.inv_f_at(rows))
        a = render_edited(st, test.c2w[0], test.height, test.width, test.focal)
        b = render_edited(own, test.c2w[0], test.height, test.width, test.focal)
        assert torch.equal(a["x_can"].nan_to_num(7.0), b["x_can"].nan_to_num(7.0))

def _assert_keys_undo_up_to(state, cap):
    """The keys' inverse gradients of a 4× stretch undo at most cap [M] (> 2 somewhere) of each point's stretch, and
    most of it where cap > 2."""
    assert float(cap.max()) > 2.0
    low = torch.linalg.svdvals(state.inv_f_attention.double()).min(-1).values
    assert bool((low >= 1 / cap - 1e-4).all())
    assert float(low[cap > 2.0].median()) < 0.6


def test_key_stretch_gap_undoes_only_the_stretch_the_fill_left_open(tiny):
    """f_key_stretch gap: the attention keys take F with each point's stretch capped at the largest growth the fill
    left between consecutive points on its pairs. A 4× stretch the fill closes (a generous budget) leaves the keys
    undoing at most the fill ratio; one the budget leaves sparse undoes up to that growth; the correspondence's
    local maps are not capped; at rest (forced through the moved path) the frame is today's; extreme poses stay
    finite."""
    bundle, _, test = tiny
    xyz = bundle.model.xyz.detach()
    _forced_rest(bundle, test, EditConfig(f_key_stretch="gap"))
    s = torch.tensor([4.0, 1.0, 1.0])
    closed = EditState(bundle, points=xyz * s, cfg=EditConfig(f_key_stretch="gap", f_fill_budget=8.0))
    full = EditState(bundle, points=xyz * s, cfg=EditConfig(f_key_stretch="full", f_fill_budget=8.0))
    ratio = closed.cfg.f_fill_ratio
    assert closed.filled_points > 0 and float(closed._gap.max()) <= ratio + 1e-5
    low_closed = torch.linalg.svdvals(closed.inv_f_attention.double()).min(-1).values
    low_full = torch.linalg.svdvals(full.inv_f_attention.double()).min(-1).values
    assert float(low_closed.min()) >= 1 / ratio - 1e-4  # no key shrinks an offset by more than the ratio
    assert float(low_full.median()) < 0.4                # the full F⁻¹ undoes the 4× stretch
    assert torch.equal(closed.inv_f_keys, full.inv_f_keys)  # the correspondence keeps the whole local map
    sparse = EditState(bundle, points=xyz * s, cfg=EditConfig(f_key_stretch="gap", f_fill_budget=0.1))
    _assert_keys_undo_up_to(sparse, sparse._gap.double())  # where the budget left gaps, more stretch is undone
    c2w = test.c2w[0].clone()
    c2w[:3, 3] *= 2.5
    for pts in _extreme_poses(xyz):
        for mode in ("tangent", "undo", "keep"):
            st = EditState(bundle, points=pts, cfg=EditConfig(f_key_stretch="gap", f_compression=mode,
                                                              f_fill_budget=0.5))
            out = render_edited(st, c2w, test.height, test.width, test.focal)
            assert torch.isfinite(out["rgb"]).all() and torch.isfinite(out["alpha"]).all()


def test_key_stretch_sparse_undoes_stretch_only_where_the_budget_left_pairs_sparse(tiny):
    """f_key_stretch sparse: the keys' stretch cap is the growth left on the pairs the fill budget kept sparser than
    the fill ratio, 1 elsewhere. A 4× stretch the fill closes leaves the keys undoing no stretch (their inverse
    shrinks no offset); one the budget leaves sparse undoes up to that growth, as gap does there; the
    correspondence keeps the whole local map; at rest (forced through the moved path) the frame is today's;
    extreme poses stay finite."""
    bundle, _, test = tiny
    xyz = bundle.model.xyz.detach()
    _forced_rest(bundle, test, EditConfig(f_key_stretch="sparse"), views=[0])
    s = torch.tensor([4.0, 1.0, 1.0])
    closed = EditState(bundle, points=xyz * s, cfg=EditConfig(f_key_stretch="sparse", f_fill_budget=8.0))
    gap = EditState(bundle, points=xyz * s, cfg=EditConfig(f_key_stretch="gap", f_fill_budget=8.0))
    assert closed.filled_points > 0 and float(closed._sparse.max()) == 1.0
    low = torch.linalg.svdvals(closed.inv_f_attention.double()).min(-1).values
    assert float(low.min()) >= 1 - 1e-4                      # no key shrinks an offset: no stretch undone
    assert float(torch.linalg.svdvals(gap.inv_f_attention.double()).min(-1).values.min()) < 0.9
    assert torch.equal(closed.inv_f_keys, gap.inv_f_keys)    # the correspondence keeps the whole local map
    open_ = EditState(bundle, points=xyz * s, cfg=EditConfig(f_key_stretch="sparse", f_fill_budget=0.1))
    _assert_keys_undo_up_to(open_, open_._sparse.double())  # where the budget left pairs sparse, stretch is undone
    for pts in _extreme_poses(xyz):
        st = EditState(bundle, points=pts, cfg=EditConfig(f_key_stretch="sparse", f_fill_budget=0.5))
        out = render_edited(st, test.c2w[0], test.height, test.width, test.focal)
        assert torch.isfinite(out["rgb"]).all() and torch.isfinite(out["alpha"]).all()


def test_key_stretch_auto_is_sparse_on_a_sheet_and_gap_on_a_thick_shell(tiny):
    """f_key_stretch auto resolves by the model's thickness as f_compression auto does: with f_thick_spread above
    every spread the model is a sheet (sparse), at 0 a thick shell (gap); the keys then equal the explicit rule's."""
    bundle, _, _ = tiny
    pts = bundle.model.xyz.detach() * torch.tensor([4.0, 1.0, 1.0])
    for spread, rule in ((1.01, "sparse"), (0.0, "gap")):
        cfg = dict(f_fill_budget=0.1, f_thick_spread=spread, f_compression="tangent")
        auto = EditState(bundle, points=pts, cfg=EditConfig(f_key_stretch="auto", **cfg))
        same = EditState(bundle, points=pts, cfg=EditConfig(f_key_stretch=rule, **cfg))
        assert auto.key_stretch == rule
        assert torch.equal(auto.inv_f_attention, same.inv_f_attention)


@pytest.mark.parametrize("rule", ["gap", "sparse"])
def test_keys_computed_for_the_held_points_only_equal_the_whole_computation(tiny, rule):
    """A frame computes the keys' inverse gradients only at the points its rays hold (the Trace's `held`, the same
    `held_rows` the trace reads again without recomputing): those rows equal
    the whole computation's exactly, the frame equals one traced with the whole tensor, and a later full request
    completes the rest with the same values."""
    from core.frames.edited import _trace
    from core.points.render import trace_frame
    from core.points.trace import held_rows

    bundle, _, test = tiny
    pts = bundle.model.xyz.detach() * torch.tensor([4.0, 1.0, 1.0])
    cfg = EditConfig(f_key_stretch=rule, f_fill_budget=0.3, f_occlusion=True)
    whole = EditState(bundle, points=pts, cfg=cfg).inv_f_attention
    lazy = EditState(bundle, points=pts, cfg=cfg)
    c2w = test.c2w[0]
    tr = _trace(lazy, c2w, test.height, test.width, test.focal, False, 1.0)
    table, done = lazy._row_tables["inv_f_attention"]
    held = held_rows(tr.idx, lazy.points.shape[0])
    assert "held" in tr.__dict__ and torch.equal(tr.held, held)  # kept from the keys' request
    assert bool(done[held].all()) and int(done.sum()) < done.numel()  # some rows not needed by this view
    assert torch.equal(table[done], whole[done])
    for inv_f in (lazy.inv_f_attention_at, whole):
        t = trace_frame(bundle.model, c2w, test.height, test.width, test.focal, points=lazy.points,
                        influence=lazy.influence, inv_f=inv_f, rebase_depth=lazy.rebase_depth)
        if inv_f is whole:
            assert torch.equal(t.weights, ref.weights) and torch.equal(t.x, ref.x)
        ref = t
    assert torch.equal(lazy.inv_f_attention, whole) and bool(done.all())


def test_held_rows_are_the_points_some_ray_holds(monkeypatch):
    """held_rows (compiled and torch) and a Trace's `held` (once per trace; a replaced trace, whose idx may have been
    redone in place, computes its own)."""
    import dataclasses

    import core.points.trace as trace

    gen = torch.Generator().manual_seed(0)
    idx = torch.randint(-1, 50, (300, 7), generator=gen)
    idx[:40] = -1
    want = torch.unique(idx[idx >= 0])
    assert torch.equal(trace.held_rows(idx, 80), want)
    z = torch.zeros(300)
    tr = trace.Trace(origins=torch.zeros(300, 3), dirs=torch.zeros(300, 3), idx=idx.clone(), weights=z[:, None],
                     fg_weights=z[:, None], bg=z, x=torch.zeros(300, 3), active=z > 0, shape=(15, 20))
    assert torch.equal(tr.held, want) and tr.held is tr.held
    tr.idx[tr.idx == int(want[0])] = -1  # as the occlusion redo rewrites rows
    assert torch.equal(dataclasses.replace(tr).held, want[1:])
    monkeypatch.setattr(trace, "_held_compiled", trace._held_loop)  # the torch path
    assert torch.equal(trace.held_rows(idx, 80), want)
    assert trace.held_rows(torch.full((5, 3), -1), 10).numel() == 0
    empty = dataclasses.replace(tr, idx=torch.full((300, 7), -1))
    assert empty.held.numel() == 0


def test_reach_perspective_keeps_rest_frames_and_is_the_screen_index(tiny):
    """f_reach_perspective: rest frames are today's; nothing moved, no factor; a card stretched 4× along x seen
    from a near camera is traced exactly as the screen index with that factor answers, and at least as many rays
    get neighbours as without it; extreme poses stay finite."""
    bundle, _, test = tiny
    xyz = bundle.model.xyz.detach()
    cfg = dict(f_radius=True, f_radius_rule="gap", f_reach_gate=1.5, f_reach_between=True, render_mode="pixels",
               f_reach_perspective=4.0)
    _forced_rest(bundle, test, EditConfig(**cfg))
    assert EditState(bundle, cfg=EditConfig(**cfg)).reach_perspective == 0.0
    c2w = test.c2w[0].clone()
    c2w[:3, 3] *= 0.8  # nearer: the stretched card's near end spreads on the screen
    pts = xyz * torch.tensor([4.0, 1.0, 1.0])
    model = bundle.model
    active = {}
    for persp in (0.0, 4.0):
        st = EditState(bundle, points=pts, cfg=EditConfig(f_fill_budget=0.1, **{**cfg, "f_reach_perspective": persp}))
        assert st.reach_perspective == persp
        got = render_edited(st, c2w, test.height, test.width, test.focal)["trace"].active
        index = screen_index(st.points, model.cfg.neighbors, model.cfg.k, c2w, test.height, test.width, test.focal,
                             model.cfg.neighbor_radius_px, reach=st.reach, reach_gate=1.5, reach_between=True,
                             reach_perspective=persp)
        assert torch.equal(got, (index.query(pixel_grid(test.height, test.width, "cpu"), model.cfg.k).idx >= 0).any(1))
        active[persp] = int(got.sum())
    assert active[4.0] >= active[0.0]
    for p in _extreme_poses(xyz):
        out = render_edited(EditState(bundle, points=p, cfg=EditConfig(f_fill_budget=0.1, **cfg)), test.c2w[0],
                            test.height, test.width, test.focal)
        assert torch.isfinite(out["rgb"]).all() and torch.isfinite(out["alpha"]).all()
