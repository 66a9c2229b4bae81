"""Island layout: local-linear texel points, building and packing islands, placement, images, storage, outlines."""
import numpy as np
import pytest
import torch

from core.atlas.atlas import Atlas
from core.atlas.islands import IslandLayout, build_islands, occupancy
from core.atlas.outlines import CELL_KEYS, cells_from_arrays, cells_to_arrays, island_mask, outline_overlay
from core.atlas.texture import local_linear_points
from core.util.errors import ModelFileError


def test_local_linear_points_invert_an_affine_map_where_the_kernel_mean_does_not():
    g = torch.Generator().manual_seed(0)
    pix = torch.rand(20000, 2, generator=g) ** 2 * 50 + 7  # uneven density: the kernel mean drifts to dense side
    M, o = torch.tensor([[0.02, 0.005], [-0.003, 0.03], [0.01, 0.01]]), torch.tensor([1.0, 2.0, 3.0])
    xyz = pix @ M.T + o
    pts, cov = local_linear_points(pix, xyz, 64, 1.0)
    rows, cols = torch.nonzero(cov, as_tuple=True)
    centre = torch.stack([cols + 0.5, rows + 0.5], -1)
    back = (pts[rows, cols] - o) @ torch.linalg.pinv(M).T
    inner = ((centre > 10) & (centre < 54)).all(-1)
    err = (back - centre)[inner].norm(dim=-1)
    assert float(err.max()) < 0.15 and float(err.median()) < 0.01
    from core.atlas.texture import kernel_texture
    mean, _, _ = kernel_texture(torch.ones(len(pix), 1), (pix / 64)[:, None], xyz, 64, 1.0)
    back_mean = (mean[0].permute(1, 2, 0)[rows, cols] - o) @ torch.linalg.pinv(M).T
    assert float((back_mean - centre)[inner].norm(dim=-1).median()) > 0.05  # what the island map replaces
    assert not torch.isfinite(pts[~cov]).any()


def _two_chart_samples(S=6000):
    g = torch.Generator().manual_seed(1)
    chart = (torch.arange(S) % 2)
    uv = torch.rand(S, 2, 2, generator=g) * 0.3 + 0.35  # both charts' coordinates near the square's middle
    ring = (uv[:, 0] - 0.5).norm(dim=-1) > 0.08  # chart 0 holds a ring, chart 1 a full square patch
    keep = ring | (chart == 1)
    probs = torch.nn.functional.one_hot(chart, 2).float()
    return probs[keep], uv[keep]


def test_islands_do_not_overlap_and_samples_land_in_their_own_chart_islands():
    probs, uv = _two_chart_samples()
    lay = build_islands(probs, uv, np.array([60.0, 40.0]), pad=2, size=0, fill=1.5, min_cells=4)
    assert lay is not None and lay.islands >= 2
    pix = (lay.place(uv) * lay.size)  # [S, 2, 2]
    for c in range(2):
        p = pix[probs[:, c] > 0, c].floor().long()
        assert bool(lay.island_pixels[p[:, 1], p[:, 0]].all())
        assert bool((lay.owner[p[:, 1], p[:, 0]] == c).all())
    # islands of different charts at least 2 * pad pixels apart (centre to centre)
    from scipy.ndimage import distance_transform_edt
    for c in range(2):
        mine = lay.island_pixels.numpy() & (lay.owner.numpy() == c)
        other = lay.island_pixels.numpy() & ~mine
        assert distance_transform_edt(~mine)[other].min() >= 2 * lay.pad


def test_samples_a_map_lays_outside_the_unit_square_keep_their_own_texels():
    # one chart whose map lays a strip of its samples at u in (1, 1.5): they must not be clipped onto the square's
    # border (distant places in one column of texels), but keep their place, as inside the square
    g = torch.Generator().manual_seed(3)
    uv = torch.rand(8000, 1, 2, generator=g) * torch.tensor([1.5, 1.0])
    probs = torch.ones(8000, 1)
    lay = build_islands(probs, uv, np.array([40.0]), pad=2, size=0, fill=1.5, min_cells=4)
    pix = lay.place(uv)[:, 0] * lay.size
    # texel distances between samples equal their uv distances x 40 everywhere (one rigid placement per island)
    i, j = torch.randint(0, 8000, (2, 4000), generator=g)
    d_uv, d_pix = (uv[i, 0] - uv[j, 0]).norm(dim=-1) * 40, (pix[i] - pix[j]).norm(dim=-1)
    out = (uv[i, 0, 0] > 1.02) | (uv[j, 0, 0] > 1.02)
    assert float((d_uv - d_pix)[out].abs().max()) < 1e-3
    # and each of them in its own island cell
    p = pix.floor().long()
    assert bool(lay.island_pixels[p[:, 1], p[:, 0]].all())


def test_points_off_the_islands_clamp_next_to_them_and_extreme_inputs_stay_finite():
    probs, uv = _two_chart_samples()
    lay = build_islands(probs, uv, np.array([60.0, 40.0]), pad=2)
    far = torch.tensor([[[0.0, 0.0], [1.0, 1.0]], [[float("nan"), 1e30], [-1e30, float("inf")]]])
    out = lay.place(far) * lay.size
    assert torch.isfinite(out).all()
    from scipy.ndimage import distance_transform_edt
    d = distance_transform_edt(~lay.island_pixels.numpy())
    for p in out.reshape(-1, 2):
        assert d[int(p[1].clamp(0, lay.size - 1)), int(p[0].clamp(0, lay.size - 1))] <= 1.5


def test_pack_takes_each_pixel_from_its_owner_and_unpack_is_a_view():
    probs, uv = _two_chart_samples()
    lay = build_islands(probs, uv, np.array([60.0, 40.0]), pad=2)
    tex = torch.stack([torch.zeros(3, lay.size, lay.size), torch.ones(3, lay.size, lay.size)])
    img = lay.pack(tex)
    assert torch.equal(img[..., 0][lay.region], lay.owner[lay.region].float())
    assert float(img[~lay.region].abs().max()) == 0.0  # no dilation outside the padding
    views = lay.unpack(img)
    assert views.shape == (2, 3, lay.size, lay.size) and torch.equal(lay.pack(views), img)
    # lookups past the padding read the nearest padding pixel's colour, not the background
    from scipy.ndimage import distance_transform_edt
    _, (ri, ci) = distance_transform_edt(~lay.region.numpy(), return_indices=True)
    assert torch.equal(views[0, 0], img[..., 0][torch.from_numpy(ri), torch.from_numpy(ci)])


def test_island_atlas_round_trips_through_its_arrays_and_grid_files_still_load():
    torch.manual_seed(0)
    a = Atlas(2, 16, 2, torch.zeros(3), 1.0, width_chart=8, depth_chart=1, width_map=8, depth_map=1)
    x = torch.rand(3000, 3) * 2 - 1
    probs, uv = a.chart_uv(x)
    grid_arrays, grid_meta = a.to_arrays(), a.meta()
    a.set_layout(build_islands(probs, uv, np.array([50.0, 50.0]), pad=2))
    with torch.no_grad():
        a.textures.uniform_(0, 1)
    b = Atlas.from_arrays(a.to_arrays(), a.meta())
    assert a.meta()["layout"] == "islands" and b.islands
    assert torch.allclose(a.lookup(x), b.lookup(x), atol=1e-5)
    # the charts read one image, held once: n views of it without a copy, before and after loading
    for at in (a, b):
        size = at.layout.size
        assert tuple(at.textures.shape) == (1, 3, size, size)
        assert at.chart_textures.shape[0] == at.n and at.chart_textures.stride(0) == 0
        assert at.chart_textures.data_ptr() == at.textures.data_ptr()
    assert torch.equal(b.packed_image(), a.packed_image().clamp(0, 1))
    p, _ = b.chart_uv(x)
    assert torch.equal(p.sum(-1), torch.ones(len(x))) and set(p.unique().tolist()) <= {0.0, 1.0}
    g = Atlas.from_arrays(grid_arrays, grid_meta)  # a version-1 (grid) file: soft charts as before
    assert not g.islands and grid_meta["version"] == 1


def test_cell_grids_are_stored_cropped_and_the_whole_grids_of_older_files_still_load():
    """Atlas version 7 keeps each layout chart's occupied bounding box only; the whole [n, G, G] grids of versions
    2-6 give the same layout, and damaged boxes, crops or grid sizes are refused before any large allocation."""
    cells = np.full((3, 40, 40), -1, np.int32)
    cells[0, 2:30, 5:9] = 0
    cells[0, 10, 20] = 1          # a second island of chart 0: its box spans both
    cells[2, 35:40, 0:3] = 2      # chart 1 has no cells
    stored = cells_to_arrays(cells)
    assert stored["atlas/islands/grid"].tolist() == [40]
    assert stored["atlas/islands/cell_boxes"].tolist() == [[2, 5, 28, 16], [0, 0, 0, 0], [35, 0, 5, 3]]
    assert stored["atlas/islands/cell_crops"].size == 28 * 16 + 5 * 3 < cells.size // 10
    np.testing.assert_array_equal(cells_from_arrays(stored), cells)
    np.testing.assert_array_equal(cells_from_arrays({"atlas/islands/cells": cells}), cells)
    assert cells_from_arrays({}) is None
    damaged = [("atlas/islands/cell_boxes", np.array([[2, 5, 28, 36], [0, 0, 0, 0], [35, 0, 5, 3]], np.int32)),
               ("atlas/islands/cell_boxes", np.array([[-1, 5, 28, 16], [0, 0, 0, 0], [35, 0, 5, 3]], np.int32)),
               ("atlas/islands/cell_boxes", np.zeros((3, 3), np.int32)),
               ("atlas/islands/cell_crops", stored["atlas/islands/cell_crops"][:-1]),
               ("atlas/islands/grid", np.array([1 << 20], np.int32)),
               ("atlas/islands/grid", np.array([0], np.int32))]
    for key, value in damaged:
        with pytest.raises(ModelFileError):
            cells_from_arrays(dict(stored, **{key: value}))
    # a fitted island layout: the stored form reloads it exactly, and so does the whole grid of older files
    torch.manual_seed(0)
    a = Atlas(2, 16, 2, torch.zeros(3), 1.0, width_chart=8, depth_chart=1, width_map=8, depth_map=1)
    x = torch.rand(3000, 3) * 2 - 1
    probs, uv = a.chart_uv(x)
    a.set_layout(build_islands(probs, uv, np.array([50.0, 50.0]), pad=2))
    arrays = a.to_arrays()
    assert "atlas/islands/cells" not in arrays and a.meta()["version"] == 7
    old = {k: v for k, v in arrays.items() if k not in CELL_KEYS}
    old["atlas/islands/cells"] = a.layout.cells.numpy()
    for form in (arrays, old):
        b = Atlas.from_arrays(form, dict(a.meta(), version=6 if form is old else 7))
        assert torch.equal(b.layout.cells, a.layout.cells) and torch.equal(b.layout.nearest, a.layout.nearest)
    with pytest.raises(ModelFileError, match="island cell arrays"):
        Atlas.from_arrays({k: v for k, v in arrays.items() if k != "atlas/islands/cell_crops"}, a.meta())


def test_occupancy_closes_gaps_between_sparse_samples():
    t = torch.stack(torch.meshgrid(torch.arange(5, 25, 2.0), torch.arange(5, 25, 2.0), indexing="ij"), -1)
    occ = occupancy(t.reshape(-1, 2).numpy() + 0.5, 32, fill=1.5)
    assert occ[6:24, 6:24].all() and not occ[0, 0] and not occ[30, 30]


def test_outline_overlay_marks_the_island_edges_only():
    cells = -np.ones((1, 8, 8), np.int32)
    cells[0, 2:6, 2:6] = 0
    mask = island_mask({"atlas/islands/cells": cells, "atlas/islands/offset": np.array([[3, 1]], np.int32)}, (10, 12))
    assert mask.sum() == 16 and mask[3, 5] and mask[6, 8]
    ov = outline_overlay(mask)
    assert ov.shape == (10, 12, 4) and int((ov[..., 3] > 0).sum()) == 12  # the 4x4 square's border
    assert ov[..., 3][~mask].max() == 0.0
    tp = np.full((4, 4, 3), np.nan, np.float32)
    tp[1:3, 1:3] = 0.0
    assert island_mask({"atlas/texel_points": tp}, (4, 4)).sum() == 4  # grid atlases: the texel map


def _reoriented(lay: IslandLayout, q: int) -> IslandLayout:
    """The same islands with every one placed under symmetry q of the texel grid (ORIENT[q]) and shifted back into
    the image: the whole image transformed, so nothing overlaps."""
    from core.atlas.outlines import ORIENT_NP
    M = ORIENT_NP[q]
    corner = (np.array([[0, 0], [lay.size, 0], [0, lay.size], [lay.size, lay.size]]) @ M.T).min(0)
    off = lay.offset.numpy() @ M.T - corner
    return IslandLayout(lay.n, lay.size, lay.pad, lay.affine, lay.cells, torch.from_numpy(off),
                        torch.full((lay.islands,), q))


def test_transposed_and_turned_islands_place_lookups_texels_and_outlines_consistently():
    from core.atlas.outlines import ORIENT_NP, cell_pixels
    probs, uv = _two_chart_samples()
    lay = build_islands(probs, uv, np.array([60.0, 40.0]), pad=2, transpose=False)
    assert int(lay.orient.abs().sum()) == 0
    base = lay.place(uv) * lay.size
    for q in range(8):
        other = _reoriented(lay, q)
        M = torch.from_numpy(ORIENT_NP[q]).float()
        shift = (torch.tensor([[0, 0], [lay.size, 0], [0, lay.size], [lay.size, lay.size]]).float() @ M.T).min(0).values
        # every lookup goes where the whole image's transform sends it, the pixels (and outlines) follow
        assert torch.allclose(other.place(uv) * other.size, base @ M.T - shift, atol=1e-4)
        k = torch.nonzero(lay.island_pixels)
        moved = (torch.stack([k[:, 1] + 0.5, k[:, 0] + 0.5], -1) @ M.T - shift).floor().long()
        assert bool(other.island_pixels[moved[:, 1], moved[:, 0]].all())
        assert int(other.island_pixels.sum()) == int(lay.island_pixels.sum())
        arrays = other.to_arrays()
        assert np.array_equal(island_mask(arrays, other.shape), other.island_pixels.numpy())
        back = IslandLayout.from_arrays(arrays, lay.n, lay.size, lay.pad)
        assert torch.equal(back.orient, other.orient) and torch.equal(back.place(uv), other.place(uv))
        # placing each point in one chart only gives that chart's column of the full placement
        chart = torch.arange(len(uv)) % lay.n
        assert torch.equal(other.place_one(uv[torch.arange(len(uv)), chart], chart),
                           other.place(uv)[torch.arange(len(uv)), chart])
        n, rr, kk = np.nonzero(lay.cells.numpy() >= 0)  # cell centres land in the pixel cell_pixels names
        isl = lay.cells.numpy()[n, rr, kk]
        c, r = cell_pixels(kk, rr, other.offset.numpy()[isl], other.orient.numpy()[isl])
        assert other.island_pixels.numpy()[r, c].all()
    # files without orientations read as all-upright islands
    arrays = {k: v for k, v in lay.to_arrays().items() if k != "atlas/islands/orient"}
    assert torch.equal(IslandLayout.from_arrays(arrays, lay.n, lay.size, lay.pad).place(uv), lay.place(uv))


class _SideChart(torch.nn.Module):
    """Chart logits [M, 2]: chart 0 for x < 0, chart 1 for x > 0."""
    def forward(self, xn):
        return torch.stack([-20 * xn[:, 0], 20 * xn[:, 0]], -1)


class _BentMap(torch.nn.Module):
    """t_c [M, 2, 2]: a smooth map that is not affine (so the texel map needs its Gauss-Newton steps)."""
    def forward(self, xn):
        u = 0.5 + 0.3 * xn[:, :2] + 0.15 * xn[:, :1] * xn[:, 1:2] + 0.1 * xn[:, :2] ** 2
        return torch.stack([u, u.flip(-1)], 1)


def test_texel_map_round_trips_on_reoriented_islands():
    """The island texel map's Gauss-Newton steps turn the miss back into chart texels: under any orientation of the
    islands the texels map back to themselves as well as upright ones do."""
    a = Atlas(2, 16, 2, torch.zeros(3), 1.0, width_chart=8, depth_chart=1, width_map=8, depth_map=1)
    a.chart, a.tex = _SideChart(), _BentMap()
    g = torch.Generator().manual_seed(2)
    u = torch.rand(8000, 2, generator=g) * 1.6 - 0.8
    x = torch.stack([u[:, 0], u[:, 1], 0.2 * torch.sin(2 * u[:, 0])], -1)  # a gently curved sheet
    probs, uv = a.chart_uv(x)
    spacing = 1.6 / 8000 ** 0.5
    lay = build_islands(probs, uv, np.array([80.0, 80.0]), pad=2, transpose=False)
    shares = []
    for q in (0, 1, 6):
        a.set_layout(_reoriented(lay, q))
        a.compute_texel_points(x, 3 * spacing, 2.0, "splat", 1.0)
        shares.append(a.texel_stats["round_trip_1"])
        assert a.meta()["version"] == 7  # island atlases store their cell grids cropped
        back = IslandLayout.from_arrays(a.to_arrays(), 2, a.layout.size, a.layout.pad)
        assert torch.equal(back.orient, a.layout.orient)
    assert min(shares) > 0.93 and max(shares) - min(shares) < 0.01, shares  # without turning back: 0.83-0.91


def test_split_island_cuts_long_and_hollow_islands_at_their_narrowest_and_keeps_every_cell():
    from core.atlas.islands import split_island
    bell = np.zeros((20, 100), bool)  # two 20 x 40 blocks joined by a 4-cell-high bridge
    bell[:, :40] = bell[:, 60:] = True
    bell[8:12, 40:60] = True
    pieces = split_island(bell, 70)
    assert len(pieces) == 2 and all(max(m.shape) <= 70 for m, _ in pieces)
    back = np.zeros_like(bell, np.int64)
    for m, (k0, r0) in pieces:
        back[r0:r0 + m.shape[0], k0:k0 + m.shape[1]] += m
    assert np.array_equal(back, bell.astype(np.int64))  # every cell in exactly one piece
    assert 40 <= max(k0 for _, (k0, _) in pieces) <= 60  # the cut goes through the bridge
    u = np.zeros((60, 60), bool)  # a U: short enough, but fills 44 % of its box
    u[:, :10] = u[:, 50:] = u[50:] = True
    assert len(split_island(u, 100)) == 1
    cut = split_island(u, 100, min_box_fill=0.55, min_length=16)
    assert len(cut) > 1 and sum(int(m.sum()) for m, _ in cut) == int(u.sum())
    assert all(m.sum() >= 0.55 * m.size or max(m.shape) < 16 for m, _ in cut)


def _long_and_hollow_samples(S=20000):
    """Chart 0: a long strip (160 x 24 texels at scale 160), chart 1: a ring (hollow, 80 texels across)."""
    g = torch.Generator().manual_seed(3)
    uv = torch.rand(S, 2, 2, generator=g)
    chart = torch.arange(S) % 2
    uv[:, 0, 1] = 0.45 + 0.15 * uv[:, 0, 1]
    ang, rad = uv[:, 1, 0] * 2 * np.pi, 0.34 + 0.16 * uv[:, 1, 1]
    uv[:, 1] = torch.stack([0.5 + rad * torch.cos(ang), 0.5 + rad * torch.sin(ang)], -1) * 0.5 + 0.25
    return torch.nn.functional.one_hot(chart, 2).float(), uv


@pytest.mark.parametrize("packer", ["xatlas", "bitmap"])
def test_cut_islands_fill_the_square_and_keep_their_padding_for_bilinear_lookups(packer):
    from scipy.ndimage import distance_transform_edt

    from core.atlas.packing import sample_charts
    probs, uv = _long_and_hollow_samples()
    whole = build_islands(probs, uv, np.array([160.0, 160.0]), pad=2, fill=1.0, min_cells=4, packer=packer)
    lay = build_islands(probs, uv, np.array([160.0, 160.0]), pad=2, fill=1.0, min_cells=4, split=0.6, min_fill=0.55,
                        packer=packer)
    share = lambda L: float(L.island_pixels.float().mean())  # noqa: E731
    assert share(whole) < 0.35 and share(lay) > 0.6 and lay.islands > whole.islands, (share(whole), share(lay))
    ids = lay.label.numpy()
    isl = lay.island_pixels.numpy()
    for i in range(lay.islands):  # every island, pieces of one chart too, 2 * pad - 1 from every other (xatlas)
        mine = isl & (ids == i)
        assert distance_transform_edt(~mine)[isl & ~mine].min() >= 2 * lay.pad - 1
    # an image holding each pixel's island id (-100 outside the padding): a bilinear lookup anywhere, on or off
    # the islands, mixes no two islands and never reads outside the padding
    img = torch.from_numpy(np.where(ids >= 0, ids, -100).astype(np.float32))
    tex = img[None, None].expand(2, 3, -1, -1)
    g = torch.Generator().manual_seed(4)
    probe = torch.cat([uv + torch.randn(uv.shape, generator=g) * 0.01, torch.rand(4000, 2, 2, generator=g) * 1.4 - 0.2])
    got = sample_charts(tex, lay.place(probe))[..., 0]
    assert float(got.min()) >= 0 and float((got - got.round()).abs().max()) < 1e-4


def test_packing_finds_a_square_near_the_islands_area():
    from core.atlas.islands import pack_islands, start_side
    rng = np.random.default_rng(0)
    masks = [np.ones((h, w), bool) for h, w in rng.integers(8, 40, (24, 2))]  # rectangles
    offsets, orient, side = pack_islands(masks, 2, 0, transpose=True)
    assert side >= start_side(masks, 2, 1.0) and sum(int(m.sum()) for m in masks) / side ** 2 > 0.6
    pix = np.zeros((side, side), np.int64)
    from core.atlas.outlines import cell_pixels
    for i, m in enumerate(masks):
        rr, kk = np.nonzero(m)
        pc, pr = cell_pixels(kk, rr, np.broadcast_to(offsets[i], (len(rr), 2)), np.full(len(rr), orient[i]))
        pix[pr, pc] += 1
    assert pix.max() == 1 and pix.sum() == sum(int(m.sum()) for m in masks)  # inside the image, no overlap


class _WobblyMap(torch.nn.Module):
    """t_c [M, 2, 2]: the bent map with a fine wobble of ~1/3 texel at scale 80, whose slope folds the map locally
    (where the texel map's Gauss-Newton steps miss)."""
    def forward(self, xn):
        u = _BentMap()(xn)[:, 0] + 0.004 * torch.sin(300 * xn[:, 1:2]) * torch.cos(310 * xn[:, :1])
        return torch.stack([u, u.flip(-1)], 1)


def _wobbly_island_atlas():
    """An island atlas of the wobbly map over 20 000 samples of a bent sheet: (atlas, samples x [S, 3], probs)."""
    a = Atlas(2, 16, 2, torch.zeros(3), 1.0, width_chart=8, depth_chart=1, width_map=8, depth_map=1)
    a.chart, a.tex = _SideChart(), _WobblyMap()
    g = torch.Generator().manual_seed(5)
    u = torch.rand(20000, 2, generator=g) * 1.6 - 0.8
    x = torch.stack([u[:, 0], u[:, 1], 0.2 * torch.sin(2 * u[:, 0])], -1)
    probs, uv = a.chart_uv(x)
    a.set_layout(build_islands(probs, uv, np.array([80.0, 80.0]), pad=2))
    return a, x, probs


def test_texels_newton_misses_take_the_nearest_sample_and_still_map_back():
    a, x, _ = _wobbly_island_atlas()
    tp = a.compute_texel_points(x, 3 * 1.6 / 20000 ** 0.5, 1.0, "splat", 1.0)
    st = a.texel_stats
    ok = torch.isfinite(tp).all(-1)
    assert st["nearest_sample"] > 0 and st["kept"] == int(ok.sum())
    assert st["kept"] / st["island_texels"] > st["round_trip_1_of_island"] + 0.01, st  # the fallback adds texels
    _, pix = a.atlas_pixel_coords(tp[ok])
    rows, cols = torch.nonzero(ok, as_tuple=True)
    assert float((pix - torch.stack([cols + 0.5, rows + 0.5], -1)).norm(dim=-1).max()) <= 1.0 + 1e-4


class _FlatMap(torch.nn.Module):
    """t_c [M, 2, 2]: both charts map the plane affinely, u = 0.5 + 0.45 x, v = 0.5 + 0.06 y (a long strip)."""
    def forward(self, xn):
        u = torch.stack([0.5 + 0.45 * xn[:, 0], 0.5 + 0.06 * xn[:, 1]], -1)
        return torch.stack([u, u], 1)


def test_subpixel_lookups_across_a_cut_land_on_an_island():
    """Where a chart was cut into two islands, neighbouring pixels sit in different islands: the sub-pixels between
    them interpolate the chart's raw coordinates and are placed after, so they land on an island (the placed
    coordinates interpolated would land in the gap between the two)."""
    from scipy.ndimage import distance_transform_edt

    from core.atlas.subpixel import subpixel_chart_uv
    a = Atlas(2, 16, 2, torch.zeros(3), 1.0, width_chart=8, depth_chart=1, width_map=8, depth_map=1)
    a.chart = torch.nn.Module()
    a.chart.forward = lambda xn: torch.stack([torch.full_like(xn[:, 0], 5.0), torch.zeros_like(xn[:, 0])], -1)
    a.tex = _FlatMap()
    g = torch.Generator().manual_seed(6)
    x = torch.cat([torch.rand(20000, 2, generator=g) * 2 - 1, torch.zeros(20000, 1)], -1)
    probs, uv = a.chart_uv(x, placed=False)
    a.set_layout(build_islands(probs, uv, np.array([200.0, 200.0]), pad=2, split=0.6, rotate=False))
    assert a.layout.islands >= 2  # the 180 x 24 strip was cut
    H, W = 6, 80
    r, c = torch.meshgrid(torch.arange(H) + 0.5, torch.arange(W) + 0.5, indexing="ij")
    pts = torch.stack([c / W * 1.8 - 0.9, r / H * 0.5 - 0.25, torch.zeros(H, W)], -1)
    valid = torch.ones(H, W, dtype=torch.bool)
    p, uv_sub, on = subpixel_chart_uv(a, pts, valid, torch.ones(H, W), 4, 10.0)
    pix = uv_sub[:, 0] * a.layout.size
    d = distance_transform_edt(~a.layout.island_pixels.numpy())
    k = pix.floor().long().clamp(0, a.layout.size - 1)
    assert bool((p[:, 0] == 1).all()) and float(d[k[:, 1], k[:, 0]].max()) <= 1.0
    # placing each sub-pixel in its own chart only (what the frames do) reads the same texels as placing all charts
    from core.atlas.packing import blend_charts
    from core.images.filter import subpixel_points as raw  # the sub-pixels' raw outputs, placed both ways
    feat = torch.cat([q.reshape(H, W, -1) for q in a.chart_uv(pts.reshape(-1, 3), placed=False)], -1)
    v = raw(feat, valid, torch.ones(H, W), 4, 10.0)[on]
    hp, all_uv = a.place(v[:, :2], v[:, 2:].reshape(-1, 2, 2))
    hp1, own_uv = a.place(v[:, :2], v[:, 2:].reshape(-1, 2, 2), own_chart_only=True)
    tex = torch.rand(2, 3, a.layout.size, a.layout.size, generator=g)
    assert torch.equal(hp1, hp) and torch.equal(own_uv, uv_sub)
    assert torch.equal(blend_charts(tex, own_uv, hp1), blend_charts(tex, all_uv, hp))
    # chart_uv's own-chart placement (the texel map and the bake read only those) gives each point's own chart's
    # coordinates in every slot, as placing every chart does in the own slot
    from core.atlas.packing import chart_coords
    p_all, uv_all = a.chart_uv(pts.reshape(-1, 3))
    p_own, uv_own = a.chart_uv(pts.reshape(-1, 3), own_chart_only=True)
    own = chart_coords(uv_all, p_all.argmax(-1))
    assert torch.equal(p_own, p_all)
    assert torch.allclose(uv_own, own[:, None].expand_as(uv_own), atol=1e-6)


def test_texel_map_newton_keeps_its_best_step_where_the_map_folds():
    """Where the map folds (the wobbly map's fine wobble) a Gauss-Newton step can land farther from the texel than
    where it started; the texel map keeps each point's best iterate, so no point ends farther from its texel than
    its local-linear start."""
    a, x, probs = _wobbly_island_atlas()
    A = a.layout.size
    # start from the samples themselves, aimed at a texel 1.5 texels off where they land, along the surface
    chart = probs.argmax(-1)[:4000]
    start = x[:4000]
    pix0 = a.layout.place_one(a.tex(a.normalise(start))[torch.arange(4000), chart], chart) * A
    target = pix0 + torch.tensor([1.5, -1.0])
    slope = torch.zeros(4000, 2, 3)
    slope[:, 0, 0], slope[:, 1, 1] = 1.6 / A, 1.6 / A   # about one texel per unit step, in the sheet's plane
    out = a._newton_to_texels(start, slope, chart, target)

    def miss(p):
        return (a.layout.place_one(a.tex(a.normalise(p))[torch.arange(len(p)), chart], chart) * A - target).norm(dim=-1)

    before, after = miss(start), miss(out)
    assert torch.isfinite(out).all()
    assert bool((after <= before + 1e-5).all()), float((after - before).max())
    assert float(after.median()) < 0.5 * float(before.median())   # and the steps still converge where they can


def test_texel_map_newton_reaches_as_far_as_each_points_own_texels():
    """The Gauss-Newton steps may move a point up to max_move of its own texel sizes: where the map squeezes the
    surface a texel is many sample spacings long, and the local-linear point lies that far from the texel's
    preimage. Points whose slope is 50 times shorter (most of them, so the typical texel is short) do not hold the
    others back."""
    a, x, probs = _wobbly_island_atlas()
    A, n = a.layout.size, 4000
    chart = probs.argmax(-1)[:n]
    start = x[:n]
    pix0 = a.layout.place_one(a.tex(a.normalise(start))[torch.arange(n), chart], chart) * A
    target = pix0 + torch.tensor([1.5, -1.0])    # 1.8 texels along the surface
    slope = torch.zeros(n, 2, 3)
    slope[:, 0, 0], slope[:, 1, 1] = 1.6 / A, 1.6 / A   # about one texel per unit step
    short = torch.arange(n) >= n // 4
    slope[short] *= 0.02                          # three quarters of the points: texels 50 times shorter
    out = a._newton_to_texels(start, slope, chart, target)
    miss = (a.layout.place_one(a.tex(a.normalise(out))[torch.arange(n), chart], chart) * A - target).norm(dim=-1)
    assert torch.isfinite(out).all()
    assert float(miss[~short].median()) < 0.5, float(miss[~short].median())   # converged where the map allows
    moved = (out - start).norm(dim=-1)
    assert float(moved[short].max()) <= 8 * 0.02 * 1.6 / A + 1e-6    # the short ones stay within their own reach


def test_occupancy_on_the_points_bounding_box_equals_the_whole_grid():
    from core.atlas.islands import _occupancy_full

    g = np.random.default_rng(0)
    for trial in range(60):
        G, fill, n = int(g.integers(8, 160)), float(g.choice([0.5, 1.0, 1.5, 2.3, 3.0])), int(g.integers(1, 300))
        t = g.uniform(-5, G + 5, 2) + g.normal(0, g.uniform(1, G / 3), (n, 2))
        if trial % 3 == 0:  # a ring: its hole is filled or kept the same way on both
            a = g.uniform(0, 2 * np.pi, n)
            t = np.c_[G / 2 + G / 4 * np.cos(a), G / 2 + G / 4 * np.sin(a)]
        whole = _occupancy_full(np.clip(np.floor(t).astype(np.int64), 0, G - 1), (G, G), fill)
        assert np.array_equal(occupancy(t, G, fill), whole), trial
    assert not occupancy(np.zeros((0, 2)), 16).any()


def test_nearest_cells_are_occupied_and_as_near_as_any_occupied_cell():
    torch.manual_seed(1)
    a = Atlas(2, 16, 2, torch.zeros(3), 1.0, width_chart=8, depth_chart=1, width_map=8, depth_map=1)
    probs, uv = a.chart_uv(torch.rand(3000, 3) * 2 - 1)
    layout = build_islands(probs, uv, np.array([50.0, 50.0]), pad=2)
    G = layout.cells.shape[1]
    assert layout.nearest.dtype == torch.int32 and layout.nearest.shape == (layout.n, G, G)
    rows, cols = (g.reshape(-1) for g in torch.meshgrid(torch.arange(G), torch.arange(G), indexing="ij"))
    for c in range(layout.n):
        occ = torch.nonzero(layout.cells[c] >= 0)  # [K, 2]
        if len(occ) == 0:
            continue
        nb = layout.nearest_cells(c, rows, cols)
        assert bool((layout.cells[c][nb[:, 0], nb[:, 1]] >= 0).all())
        here = torch.stack([rows, cols], -1).float()
        best = torch.cdist(here, occ.float()).amin(1)
        assert torch.allclose((nb.float() - here).norm(dim=-1), best)
        per_cell = layout.nearest_cells(torch.full_like(rows, c), rows, cols)  # a chart per cell: the same
        assert torch.equal(per_cell, nb)


def test_the_smallest_island_kept_is_the_same_surface_at_any_texel_density():
    from core.atlas.config import AtlasConfig
    from core.atlas.fit import island_layout, min_island_cells, sample_spacing

    def grid(x0, n, d=0.0025):
        g = x0 + np.arange(n) * d
        X, Y = np.meshgrid(g, g)
        return np.stack([X.ravel(), Y.ravel(), np.zeros(X.size)], -1)

    def islands(stray: int, tpp: float, min_pixels: float) -> int:
        xyz = np.concatenate([grid(0.0, 100), grid(0.5, stray)])  # a 0.25 square and a stray patch, pixels 0.02
        spacing, area, *elements = sample_spacing(xyz, per_sample=True)
        probs, uv = torch.ones(len(xyz), 1), torch.from_numpy(xyz[:, None, :2]).float() - 0.4
        cfg = AtlasConfig(layout="islands", island_sides=False, island_split=0.0, texels_per_pixel=tpp,
                          island_min_pixels=min_pixels)
        return island_layout(probs, uv, tuple(elements), area, 1.0, 16, cfg, 0.02)[1]["islands"]

    for tpp in (4.0, 8.0):
        assert islands(3, tpp, 1.0) == 1  # a quarter of a pixel across: dropped at either density
        assert islands(8, tpp, 1.0) == 2  # most of a pixel across: kept at either density
        assert islands(3, tpp, 0.0) == 2  # nothing is dropped with 0
    assert islands(3, 8.0, 16 / 64) == 2  # a fixed 16 texels would keep it at 8 texels per pixel
    cfg = AtlasConfig(texels_per_pixel=5.0, island_min_pixels=1.0)
    assert min_island_cells(0.02 / 5, cfg, 0.02) == 25 and min_island_cells(0.02 / 2.5, cfg, 0.02) == 6
    assert min_island_cells(1.0, cfg, None) == 25
    assert min_island_cells(1.0, AtlasConfig(island_min_pixels=0.0), 1.0) == 1
