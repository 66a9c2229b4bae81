"""Lookups through the stored surface samples and the bake that fits the texels they read
(core/atlas/sample_lookup.py, EditConfig lookup)."""
import copy

import pytest
import torch

from core.atlas.sample_lookup import chart_texel_matrix, fit_texels, lookup_texel_rows, sample_lookup
from core.edits.bake import bake
from core.frames.edited import EditConfig, EditState, render_edited
from core.util.errors import InputError
from tests.helpers.tiny import tiny_bundle


def _stripes(lo, hi, bands=6):
    """Hard-edged bands along x: what a blurred bake loses."""
    def fn(p):
        t = ((p[:, 0] - lo[0]) / (hi[0] - lo[0]) * bands).floor() % 2
        return torch.stack([t, 1 - t, 0.5 * torch.ones_like(t)], 1), None
    return fn


@pytest.fixture(scope="module")
def card():
    return tiny_bundle("card")


def test_a_point_on_a_sample_reads_that_sample_and_halfway_reads_both(card):
    bundle = card[0]
    lk = sample_lookup(bundle.atlas)
    assert sample_lookup(bundle.atlas) is lk  # built once per atlas
    tex = torch.rand(1, 3, *bundle.atlas.layout.shape, generator=torch.Generator().manual_seed(0))
    tex = tex.expand(bundle.atlas.n, -1, -1, -1) if bundle.atlas.islands else \
        torch.rand(bundle.atlas.n, 3, bundle.atlas.layout.R, bundle.atlas.layout.R)
    reads = lk.read(tex)
    S = lk.samples
    assert reads.shape == (S.shape[0], 3) and torch.isfinite(reads).all()
    got = lk.lookup(reads, S[:50], k=4)
    assert torch.allclose(got, reads[:50], atol=1e-6)
    j, _ = lk.neighbours(S[:1], 2)
    a, b = int(j[0, 0]), int(j[0, 1])
    mid = 0.5 * (S[a] + S[b])
    _, w = lk.neighbours(mid[None], 2)
    assert torch.allclose(w, torch.full_like(w, 0.5), atol=1e-4)
    bad = torch.tensor([[float("nan"), 0.0, 0.0]])
    out = lk.lookup(reads, torch.cat([bad, S[:2]]), k=4)
    assert torch.isnan(out[0]).all() and torch.isfinite(out[1:]).all()


def test_neighbour_queries_on_several_threads_match_one_thread(card):
    lk = sample_lookup(card[0].atlas)
    x = lk.samples[::3] + 0.01 * torch.randn(len(lk.samples[::3]), 3, generator=torch.Generator().manual_seed(1))
    before = torch.get_num_threads()
    try:
        torch.set_num_threads(1)
        j1, w1 = lk.neighbours(x, 4)
        torch.set_num_threads(2)
        j2, w2 = lk.neighbours(x, 4)
    finally:
        torch.set_num_threads(before)
    assert torch.equal(j1, j2) and torch.equal(w1, w2)


def test_gathered_texel_rows_equal_the_sparse_product(card):
    """lookup_texel_rows (the refit's rows, gathered) against the plain product of the points' blend weights over
    the samples and the per-sample rows: bit for bit with one or two samples per point (each texel sums at most two
    terms), to rounding with more."""
    import numpy as np
    import scipy.sparse as sp

    def lookup_matrix(lk, x, k):  # the blend weights [Q, S]: row q holds its k nearest samples' weights
        j, w = lk.neighbours(x, k)
        Q, kk = j.shape
        return sp.csr_matrix((w.reshape(-1).numpy(), (np.repeat(np.arange(Q), kk), j.reshape(-1).numpy())),
                             shape=(Q, len(lk.samples)))

    atlas = card[0].atlas
    lk = sample_lookup(atlas)
    per_sample = chart_texel_matrix(atlas, lk)
    g = torch.Generator().manual_seed(3)
    x = torch.cat([lk.samples[::2] + 0.02 * torch.randn(len(lk.samples[::2]), 3, generator=g), lk.samples[:5]])
    for k in (1, 2, 4):
        want = lookup_matrix(lk, x, k) @ per_sample
        want.sort_indices()
        got = lookup_texel_rows(lk, x, k, per_sample)
        assert got.shape == want.shape and np.array_equal(got.indptr, want.indptr)
        assert np.array_equal(got.indices, want.indices)
        assert np.array_equal(got.data, want.data) if k <= 2 else np.allclose(got.data, want.data, rtol=1e-12)
    empty = lookup_texel_rows(lk, x[:0], 2, per_sample)
    assert empty.shape == (0, per_sample.shape[1]) and empty.nnz == 0


def test_fitted_bake_returns_a_hard_edged_texture_at_the_samples_better_than_the_splat(card):
    atlas = card[0].atlas
    lk = sample_lookup(atlas)
    S = lk.samples
    fn = _stripes(S.min(0).values, S.max(0).values)
    want = fn(S)[0]
    err = {}
    for source in ("fit", "samples"):
        img = bake(atlas, fn, source=source)
        assert torch.isfinite(img).all() and img.min() >= 0 and img.max() <= 1
        read = lk.read(img.permute(2, 0, 1)[None].expand(atlas.n, -1, -1, -1)) if atlas.islands else None
        if read is None:
            from core.atlas.packing import unpack
            read = lk.read(unpack(img, atlas.layout))
        err[source] = float(((read - want) ** 2).mean())
    assert err["fit"] < 0.5 * err["samples"], err
    assert bake(atlas, fn).equal(bake(atlas, fn, source="fit"))  # "auto" fits when the atlas keeps samples
    fallback = copy.deepcopy(atlas)
    fallback.bake_samples = None
    with pytest.raises(InputError, match="no surface samples"):
        bake(fallback, fn, source="fit")


def test_fitted_decal_leaves_the_rest_of_the_atlas_as_it_was(card):
    atlas = card[0].atlas
    lk = sample_lookup(atlas)
    S = lk.samples
    centre = S.mean(0)
    radius = 0.25 * float((S.max(0).values - S.min(0).values).norm())
    red = torch.tensor([1.0, 0.0, 0.0])
    inside_of = lambda p: ((p - centre).norm(dim=-1) < radius)  # noqa: E731
    base = atlas.packed_image()
    img = bake(atlas, lambda p: (red.expand(p.shape[0], 3), inside_of(p).float()), source="fit")
    from core.atlas.packing import unpack
    read, before = lk.read(unpack(img, atlas.layout)), lk.read(unpack(base, atlas.layout))
    d = (S - centre).norm(dim=-1)
    deep, far = d < 0.5 * radius, d > 1.5 * radius
    assert deep.sum() > 10 and far.sum() > 10
    # the tiny atlas lays a few samples into the same texels: judge the bulk, and bound every sample
    inner, outer = (read[deep] - red).abs().amax(-1), (read[far] - before[far]).abs().amax(-1)
    assert inner.median() < 0.05 and inner.quantile(0.95) < 0.1 and inner.max() < 0.3
    assert outer.median() < 0.005 and outer.quantile(0.95) < 0.03 and outer.max() < 0.3
    with pytest.raises(InputError, match="targets"):
        fit_texels(atlas, base, torch.zeros(3, 3))


def test_frames_through_the_samples(card):
    """Rest and a moved pose render finite frames through the samples; an unedited model is the same frame
    with either lookup; a model without samples falls back to the charts; the island stack is one image."""
    bundle, _, test = card
    atlas = bundle.atlas
    S = sample_lookup(atlas).samples
    fn = _stripes(S.min(0).values, S.max(0).values)
    img = bake(atlas, fn)
    view = (test.c2w[0], test.height, test.width, test.focal)
    frames = {}
    for lookup in ("samples", "charts"):
        st = EditState(bundle, atlas=img, cfg=EditConfig(lookup=lookup))
        assert (st.sample_lookup is not None) == (lookup == "samples")
        frames[lookup] = render_edited(st, *view)["rgb"]
        assert torch.isfinite(frames[lookup]).all()
    assert not torch.equal(frames["samples"], frames["charts"])
    plain = [render_edited(EditState(bundle, cfg=EditConfig(lookup=lk)), *view)["rgb"] for lk in ("samples", "charts")]
    assert torch.equal(plain[0], plain[1])
    xyz = bundle.model.xyz.detach()
    moved = render_edited(EditState(bundle, points=xyz + 0.05 * torch.sin(3 * xyz.flip(1)), atlas=img), *view)
    assert torch.isfinite(moved["rgb"]).all()
    one = EditState(bundle, atlas=img, cfg=EditConfig(antialias=1))
    assert torch.isfinite(render_edited(one, *view)["rgb"]).all()
    old = copy.deepcopy(bundle)
    old.atlas.bake_samples = None
    st = EditState(old, atlas=img)
    assert st.sample_lookup is None
    assert torch.equal(render_edited(st, *view)["rgb"], frames["charts"])
    if atlas.islands:
        tex = EditState(bundle, atlas=img).edit_textures
        assert tex.shape[0] == atlas.n and (atlas.n == 1 or tex.stride(0) == 0)
