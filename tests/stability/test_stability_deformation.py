"""Deformation gradients F on extreme inputs: finite, bounded, identity at rest, exact for affine maps."""
import math

import pytest
import torch

from core.edits.deformation import DeformationConfig, DeformationField, bound, inverse, polar, stretch

MAX = DeformationConfig().max_stretch


def _volume(n=600, seed=0):
    g = torch.Generator().manual_seed(seed)
    return torch.rand(n, 3, generator=g) * 2 - 1


def _sheet(n=24, noise=0.0, seed=0):
    """A flat square sheet in the plane z = 0 (optionally with a little thickness)."""
    u, v = torch.meshgrid(torch.linspace(-1, 1, n), torch.linspace(-1, 1, n), indexing="ij")
    p = torch.stack([u.reshape(-1), v.reshape(-1), torch.zeros(n * n)], 1)
    if noise:
        g = torch.Generator().manual_seed(seed)
        p = p + noise * torch.randn(p.shape, generator=g)
    return p


def _rot(angle, axis=2):
    c, s = math.cos(angle), math.sin(angle)
    r = torch.eye(3)
    i, j = [a for a in range(3) if a != axis]
    r[i, i], r[i, j], r[j, i], r[j, j] = c, -s, s, c
    return r


def _check(f, max_stretch=MAX):
    assert torch.isfinite(f).all()
    sv = torch.linalg.svdvals(f.double())
    assert float(sv.max()) <= max_stretch * (1 + 1e-4)
    assert float(sv.min()) >= (1 / max_stretch) * (1 - 1e-4)


@pytest.mark.parametrize("make", [_volume, _sheet, lambda: _sheet(noise=0.01)])
def test_identity_at_rest(make):
    p = make()
    f = DeformationField(p).gradients(p)
    assert torch.allclose(f, torch.eye(3).expand_as(f), atol=1e-5)


def test_exact_for_affine_volume():
    p = _volume()
    a = torch.tensor([[1.3, 0.2, -0.1], [0.1, 0.8, 0.4], [-0.3, 0.2, 2.0]]) @ _rot(0.7, 0)
    q = p @ a.T + torch.tensor([3.0, -1.0, 2.0])
    f = DeformationField(p).gradients(q)
    assert torch.allclose(f, a.expand_as(f), atol=1e-4)
    # a mirror is kept as a mirror
    m = torch.diag(torch.tensor([1.0, -1.0, 1.0]))
    fm = DeformationField(p).gradients(p @ m.T)
    assert torch.allclose(fm, m.expand_as(fm), atol=1e-4)


def test_sheet_stretch_exact_in_plane_and_normal_completed():
    p = _sheet()
    a = torch.diag(torch.tensor([5.0, 0.5, 1.0]))
    r = _rot(0.9, 0)
    q = p @ (r @ a).T
    f = DeformationField(p).gradients(q)
    _check(f)
    tang = f[:, :, :2]
    assert torch.allclose(tang, (r @ a)[:, :2].expand_as(tang), atol=1e-4)
    # normal column: unit, along the deformed sheet's normal (r's third column)
    assert torch.allclose(f[:, :, 2], r[:, 2].expand(f.shape[0], 3), atol=1e-4)


def test_sheet_in_plane_mirror_is_a_flip_and_noisy_sheet_stays_near_identity():
    p = _sheet()
    f = DeformationField(p).gradients(p * torch.tensor([1.0, -1.0, 1.0]))
    assert (torch.linalg.det(f) > 0).all()  # a mirrored sheet is the same sheet turned over
    pn = _sheet(noise=0.003)
    fn = DeformationField(pn).gradients(pn @ _rot(0.5).T)
    assert torch.allclose(fn, _rot(0.5).expand_as(fn), atol=1e-3)


@pytest.mark.parametrize("scale", [5.0, 1e-3, 0.0, 1e6, 1e-9])
@pytest.mark.parametrize("make", [_volume, _sheet])
def test_squash_and_stretch_are_bounded(make, scale):
    p = make()
    q = p.clone()
    q[:, 0] *= scale
    f = DeformationField(p).gradients(q)
    _check(f)
    if scale == 5.0:
        assert torch.allclose(stretch(f), torch.full((len(p),), 5.0), atol=1e-3)
    if scale == 0.0:
        assert torch.allclose(f[:, 0, 0], torch.full((len(p),), 1 / MAX), atol=1e-4)


def test_fold_collapse_nan_and_random_inputs():
    p = _sheet()
    fold = p.clone()
    fold[:, 0] = fold[:, 0].abs()  # the sheet folded onto itself along x = 0
    _check(DeformationField(p).gradients(fold))
    fld = DeformationField(p)
    _check(fld.gradients(torch.zeros_like(p)))  # everything collapsed to one point
    q = p.clone()
    q[::3] = float("nan")
    q[1::7] = float("inf")
    q[2::11] = 1e30
    f = fld.gradients(q)
    _check(f)
    g = torch.Generator().manual_seed(1)
    _check(fld.gradients(torch.randn(p.shape, generator=g) * 100))  # neighbourhoods scrambled
    q = p.clone()
    q[:5] = float("nan")
    bad = fld.gradients(q)[:5]
    assert torch.equal(bad, torch.eye(3).expand_as(bad))  # absent points: identity


def test_ids_removed_and_duplicated_neighbours():
    p = _sheet(16)
    n = len(p)
    fld = DeformationField(p)
    a = _rot(0.4) @ torch.diag(torch.tensor([2.0, 1.0, 1.0]))
    # every other point removed, the first 40 duplicated and moved far away by a translation
    keep = torch.arange(0, n, 2)
    dup = torch.arange(40)
    ids = torch.cat([keep, dup])
    q = torch.cat([p[keep] @ a.T, p[dup] @ a.T + torch.tensor([50.0, 0.0, 0.0])])
    f = fld.gradients(q, ids)
    _check(f)
    close = ((f[:, :2, :2] - a[:2, :2]).abs().amax((1, 2)) < 1e-3)
    assert bool(close[:len(keep)].all())  # the original copy: exact
    assert bool(close[len(keep):].all())  # the moved copy too: its neighbours found only in the other copy are dropped
    # duplicated canonical points at the same place (a neighbour listed twice) and a single point
    p2 = torch.cat([p, p[:10]])
    _check(DeformationField(p2).gradients(p2 * 2))
    one = torch.zeros(1, 3)
    assert torch.equal(DeformationField(one).gradients(one + 1), torch.eye(3)[None])


def test_polar_parts_and_inverse():
    g = torch.Generator().manual_seed(3)
    f = bound(torch.randn(200, 3, 3, generator=g) * 3, MAX)
    _check(f)
    r, s = polar(f)
    assert torch.allclose(r @ s, f, atol=1e-4)
    assert torch.allclose(torch.linalg.det(r), torch.ones(200), atol=1e-4)
    assert torch.allclose(r @ r.transpose(1, 2), torch.eye(3).expand(200, 3, 3), atol=1e-4)
    assert torch.allclose(s, s.transpose(1, 2), atol=1e-5)
    fi = inverse(f)
    assert torch.isfinite(fi).all()
    assert torch.allclose(fi @ f, torch.eye(3).expand(200, 3, 3), atol=1e-3)
    assert torch.equal(bound(torch.eye(3)[None], MAX), torch.eye(3)[None])


def test_inverse_and_det3_match_torch_linalg():
    """inverse (the compiled adjugate on the CPU) equals torch.linalg.inv in float64 to float32 rounding, and det3
    (the cofactor expansion) torch.linalg.det, over bounded gradients from a squash to 1/20 to a 20× stretch and
    mirrors; the torch path (other devices) is torch.linalg.inv itself."""
    from core.edits.deformation import det3

    g = torch.Generator().manual_seed(7)
    f = bound(torch.randn(2000, 3, 3, generator=g) * torch.rand(2000, 1, 1, generator=g) * 30, MAX)
    f = torch.cat([f, torch.eye(3)[None], torch.diag(torch.tensor([MAX, 1.0 / MAX, -1.0]))[None]])
    ref = torch.linalg.inv(f.double())
    fi = inverse(f)
    assert fi.dtype == f.dtype and torch.isfinite(fi).all()
    assert torch.allclose(fi.double(), ref, rtol=1e-6, atol=1e-6 * float(ref.abs().max()))
    fd = f.double()
    assert torch.allclose(det3(fd), torch.linalg.det(fd), rtol=1e-12, atol=1e-15)
    assert torch.equal(det3(torch.eye(3)[None]), torch.ones(1))


def test_inverse_at_writes_the_rows_inverse_gives_and_nothing_else():
    """inverse_at (the occlusion rule's inverses at the points a frame holds) writes inverse's rows to float32
    rounding at the rows asked for (a singular row gets I, as the compiled inverse gives), and leaves the other rows
    of its output as they were; the torch fallback (a float64 output) agrees too."""
    from core.edits.deformation import inverse_at

    g = torch.Generator().manual_seed(11)
    f = bound(torch.randn(500, 3, 3, generator=g) * torch.rand(500, 1, 1, generator=g) * 30, MAX)
    f = torch.cat([f, torch.zeros(1, 3, 3), torch.diag(torch.tensor([MAX, 1.0 / MAX, -1.0]))[None]]).contiguous()
    rows = torch.tensor([0, 3, 499, 500, 501, 7])
    out = torch.full_like(f, 5.0)
    inverse_at(f, rows, out)
    full = inverse(f)
    scale = float(full[rows].abs().max())
    assert torch.allclose(out[rows], full[rows], rtol=1e-6, atol=1e-6 * scale)
    assert torch.equal(out[500], torch.eye(3))
    others = torch.ones(f.shape[0], dtype=torch.bool)
    others[rows] = False
    assert bool((out[others] == 5.0).all())
    out64 = torch.zeros(f.shape, dtype=torch.float64)
    inverse_at(f.double(), rows, out64)
    assert torch.allclose(out64[rows], full[rows].double(), rtol=1e-5, atol=1e-5)
    inverse_at(f, rows[:0], out)  # no rows: nothing to do


def test_expansion_inverse_undoes_stretch_only():
    from core.edits.deformation import expansion_inverse

    r = _rot(0.6, 1)
    f = (r @ torch.diag(torch.tensor([5.0, 0.2, 1.0])))[None]
    g = expansion_inverse(f)
    assert torch.allclose(g, (torch.diag(torch.tensor([0.2, 1.0, 1.0])) @ r.T)[None], atol=1e-5)
    m = torch.diag(torch.tensor([1.0, 1.0, -1.0]))[None]  # a mirror: undone (it is its own inverse)
    assert torch.allclose(expansion_inverse(m), m, atol=1e-6)
    assert torch.isfinite(expansion_inverse(torch.zeros(1, 3, 3))).all()


def test_expansion_inverse_compiled_matches_torch():
    from core.edits.deformation import _expansion_inverse_torch, expansion_inverse

    g = torch.Generator().manual_seed(4)
    f = bound(torch.randn(500, 3, 3, generator=g) * torch.rand(500, 1, 1, generator=g) * 4, MAX)
    f = torch.cat([f, torch.eye(3)[None], torch.diag(torch.tensor([2.0, 2.0, 0.5]))[None],
                   torch.diag(torch.tensor([1.0, 1.0, -1.0]))[None]])  # repeated singular values, a mirror
    # (the torch path leaves singular values within 1e-3 below 1 as they are: the paths differ by that much)
    assert torch.allclose(expansion_inverse(f), _expansion_inverse_torch(f), atol=1e-3)


def test_spread_ratios_tell_a_sheet_from_a_thick_shell_and_stay_finite():
    """A flat sheet's neighbourhoods are near 0 thick, a sheet with noise of a fifth of its spacing thin, a volume's
    cloud thick (the median spread `f_compression auto` compares); degenerate inputs (one point, coincident points,
    non-finite ones) give finite ratios in [0, 1]."""
    flat = DeformationField(_sheet())
    noisy = DeformationField(_sheet(noise=0.2 * 2 / 23))
    cloud = DeformationField(_volume())
    assert flat.median_spread < 1e-6
    assert noisy.median_spread < 0.15 <= cloud.median_spread
    for pts in (torch.zeros(1, 3), torch.zeros(30, 3), torch.cat([_volume(50), torch.full((5, 3), float("nan"))])):
        fld = DeformationField(pts)
        r = fld.spread_ratios()
        assert r.shape == (pts.shape[0],) and torch.isfinite(r).all() and float(r.min()) >= 0 and float(r.max()) <= 1
        assert math.isfinite(fld.median_spread)
    assert torch.equal(cloud.spread_ratios(torch.tensor([3, 3, 0])), cloud.spread_ratios()[[3, 3, 0]])


def test_bound_above_caps_the_stretch_only_and_matches_torch():
    """bound_above clamps each row's singular values to at most its cap: a stretch beyond the cap is cut to it,
    compression, directions and a mirror's orientation stay, rows within their cap are unchanged; the compiled
    path equals the torch reference, and degenerate rows (a singular F, a cap below every singular value) stay
    finite."""
    from core.edits.deformation import _bound_above_torch, bound_above

    r = _rot(0.6, 1)
    f = torch.stack([r @ torch.diag(torch.tensor([5.0, 0.2, 1.0])), torch.diag(torch.tensor([3.0, 1.0, -1.0])),
                     _rot(0.3, 0), torch.zeros(3, 3)])
    cap = torch.tensor([2.0, 2.0, 1.5, 1.0])
    for fn in (bound_above, _bound_above_torch):
        g = fn(f, cap)
        assert torch.allclose(g[0], r @ torch.diag(torch.tensor([2.0, 0.2, 1.0])), atol=1e-5)
        assert torch.allclose(g[1], torch.diag(torch.tensor([2.0, 1.0, -1.0])), atol=1e-5)
        assert torch.equal(g[2], f[2]) and torch.equal(g[3], f[3])
    gen = torch.Generator().manual_seed(5)
    f = bound(torch.randn(400, 3, 3, generator=gen) * 3, MAX)
    cap = 0.5 + 4 * torch.rand(400, generator=gen)
    a, b = bound_above(f, cap), _bound_above_torch(f, cap)
    assert torch.allclose(a, b, atol=1e-5)
    sv, sv0 = torch.linalg.svdvals(a.double()), torch.linalg.svdvals(f.double())
    assert bool((sv[:, 0] <= cap.double() * (1 + 1e-5)).all())
    assert torch.allclose(sv, torch.minimum(sv0, cap.double()[:, None]), atol=1e-4)
    assert torch.equal(torch.sign(torch.linalg.det(a)), torch.sign(torch.linalg.det(f)))
    tiny = bound_above(f, torch.full((400,), 1e-3))
    assert torch.isfinite(tiny).all() and float(torch.linalg.svdvals(tiny.double()).max()) <= 1e-3 * (1 + 1e-5)


def test_key_inverse_is_the_capped_tangent_rule_and_matches_torch():
    """key_inverse: F⁻¹ without cap or normals; with a cap the inverse of bound_above(F, cap); with normals the
    tangent rule's inverse (a compression across the surface not undone, one along it undone); the compiled path
    equals the torch reference on random bounded F, and stays finite for a singular F."""
    from core.edits.deformation import _key_inverse_torch, bound_above, key_inverse

    gen = torch.Generator().manual_seed(6)
    f = bound(torch.randn(400, 3, 3, generator=gen) * 3, MAX)
    n = torch.randn(400, 3, generator=gen, dtype=torch.float64)
    n = n / n.norm(dim=1, keepdim=True)
    cap = 0.5 + 4 * torch.rand(400, generator=gen)
    assert torch.allclose(key_inverse(f), inverse(f), atol=1e-4)
    assert torch.allclose(key_inverse(f, cap), inverse(bound_above(f, cap)), atol=1e-4)
    inf = torch.full((400,), math.inf, dtype=torch.float64)
    for c in (cap.double(), inf):
        for nn in (None, n):
            assert torch.allclose(key_inverse(f, c, nn), _key_inverse_torch(f, c, nn), atol=1e-4, rtol=1e-5)
    z = torch.tensor([0.0, 0.0, 1.0], dtype=torch.float64)[None]
    squash = torch.diag(torch.tensor([1.0, 1.0, 0.2]))[None]      # across the sheet (normal z): not undone
    thin = torch.diag(torch.tensor([0.2, 1.0, 1.0]))[None]        # along it: undone
    assert torch.allclose(key_inverse(squash, None, z), torch.eye(3)[None], atol=1e-6)
    assert torch.allclose(key_inverse(thin, None, z), torch.diag(torch.tensor([5.0, 1.0, 1.0]))[None], atol=1e-5)
    assert torch.isfinite(key_inverse(torch.zeros(2, 3, 3), torch.ones(2), z.expand(2, 3))).all()


def test_key_loop_closed_form_cases_match_torch():
    """The compiled cap's closed-form paths (one or two singular values beyond the cap) and their fall-back to
    Jacobi rotations (σ's too close to tell apart, all three beyond the cap) equal the torch reference to 1e-8 in
    float64, mirrored F included; σ1 = σ2, σ2 = σ3, a σ just at the cap, near rotations at a cap of 1 and extreme
    scales stay finite and capped."""
    from core.edits.deformation import _bound_above_torch, _key_inverse_torch, bound_above, key_inverse

    gen = torch.Generator().manual_seed(7)
    q1, _ = torch.linalg.qr(torch.randn(3, 3, generator=gen, dtype=torch.float64))
    q2, _ = torch.linalg.qr(torch.randn(3, 3, generator=gen, dtype=torch.float64))
    cases = [  # (singular values, cap)
        ((3.0, 1.0, 0.5), 2.0), ((3.0, 2.5, 0.5), 2.0), ((3.0, 3.0, 0.5), 2.0), ((3.0, 3.0 * (1 + 1e-7), 0.5), 2.0),
        ((3.0, 2.999, 2.998), 2.0), ((3.0, 1.0, 1.0), 2.0), ((2.0 * (1 + 1e-12), 1.0, 1.0), 2.0),
        ((2.001, 2.0005, 0.5), 2.0), ((2.5, 2.0 * (1 + 1e-12), 1.0), 2.0), ((1e6, 1.0, 1e-6), 1.0),
        ((1e-3, 5e-4, 1e-4), 1e-4), ((1.2, 1.0, 0.9), 1.0), ((4.0, 3.0, 2.0), 1.0),
        # near rotations at a cap of 1 (most points of a posed model): σ's apart by 1e-4 … 1e-9
        ((1 + 2e-4, 1 + 1e-4, 1 - 1e-4), 1.0), ((1 + 1e-6, 1 - 1e-6, 1 - 2e-6), 1.0), ((1 + 2e-9, 1 + 1e-9, 1.0), 1.0),
        ((1 + 1e-5, 1 + 1e-5, 1 - 1e-5), 1.0), ((1 + 3e-7, 1 + 2e-7, 1 - 1e-7), 1.0)]
    rows, caps = [], []
    for sv, c in cases:
        for sign in (1.0, -1.0):  # a mirrored neighbourhood too
            rows.append(q1 @ torch.diag(torch.tensor(sv, dtype=torch.float64) * torch.tensor([1.0, 1.0, sign],
                                                                                               dtype=torch.float64)) @ q2)
            caps.append(c)
    f, cap = torch.stack(rows), torch.tensor(caps, dtype=torch.float64)
    a, b = bound_above(f, cap), _bound_above_torch(f, cap)
    assert torch.isfinite(a).all()
    scale = f.flatten(1).abs().amax(1)[:, None, None]
    assert bool(((a - b).abs() <= 1e-8 * scale).all())  # σ1 = σ2: the closed form loses ~√eps in σ1 − σ2
    sv, sv0 = torch.linalg.svdvals(a), torch.linalg.svdvals(f)
    assert bool(((sv - torch.minimum(sv0, cap[:, None])).abs() <= 1e-8 * sv0[:, :1]).all())
    assert torch.equal(torch.sign(torch.linalg.det(a)), torch.sign(torch.linalg.det(f)))
    # random F whose stretch mostly exceeds a cap near 1, as at a posed sheet's joint, with and without normals
    f = bound(torch.randn(2000, 3, 3, generator=gen, dtype=torch.float64) * 0.3 + torch.eye(3, dtype=torch.float64)
              * 1.2, MAX)
    cap = 1.0 + 0.5 * torch.rand(2000, generator=gen, dtype=torch.float64)
    n = torch.randn(2000, 3, generator=gen, dtype=torch.float64)
    n = n / n.norm(dim=1, keepdim=True)
    assert torch.allclose(bound_above(f, cap), _bound_above_torch(f, cap), rtol=1e-9, atol=1e-9)
    for nn in (None, n):
        assert torch.allclose(key_inverse(f, cap, nn), _key_inverse_torch(f, cap, nn), rtol=1e-8, atol=1e-8)
    # near rotations (σ within 1e-3 … 1e-7 of 1) at a cap of 1
    for eps in (1e-3, 1e-5, 1e-7):
        r, _ = torch.linalg.qr(torch.randn(500, 3, 3, generator=gen, dtype=torch.float64))
        f = r @ (torch.eye(3, dtype=torch.float64) + eps * torch.randn(500, 3, 3, generator=gen, dtype=torch.float64))
        one = torch.ones(500, dtype=torch.float64)
        assert torch.allclose(bound_above(f, one), _bound_above_torch(f, one), rtol=1e-9, atol=1e-9)
        assert torch.allclose(key_inverse(f, one, n[:500]), _key_inverse_torch(f, one, n[:500]), rtol=1e-8,
                              atol=1e-8)
