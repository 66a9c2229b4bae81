"""Canonical correspondence against a per-ray loop reference, and its geometric invariants."""
import torch

from core.edits.correspondence import canonical_points, ray_canonical_points
from core.images.rays import project_on_ray
from core.points.trace import Trace


def _reference(w, idx, x_hat, o, d, p_def, p_can, mode):
    """Plain per-ray loop, straight from the paper's equations."""
    out = []
    for i in range(w.shape[0]):
        acc_can = torch.zeros(3)
        acc_disp = torch.zeros(3)
        for j in range(w.shape[1]):
            if idx[i, j] < 0:
                continue
            acc_can += w[i, j] * p_can[idx[i, j]]
            acc_disp += w[i, j] * (p_can[idx[i, j]] - p_def[idx[i, j]])
        if mode == "naive":
            out.append(acc_can)
        else:
            t = max(float(torch.dot(x_hat[i] - o[i], d[i])), 0.0)
            out.append(o[i] + t * d[i] + acc_disp)
    return torch.stack(out)


def _case(seed=0, r=16, k=5, m=40):
    g = torch.Generator().manual_seed(seed)
    p_can = torch.randn(m, 3, generator=g)
    p_def = p_can + 0.3 * torch.randn(m, 3, generator=g)
    idx = torch.randint(0, m, (r, k), generator=g)
    idx[0, 2:] = -1
    w = torch.softmax(torch.randn(r, k, generator=g), 1) * (idx >= 0)
    w = w / w.sum(1, keepdim=True)
    o = torch.randn(r, 3, generator=g) + torch.tensor([0.0, 0.0, 5.0])
    d = torch.nn.functional.normalize(-o + 0.2 * torch.randn(r, 3, generator=g), dim=1)
    x_hat = (w[..., None] * p_def[idx.clamp_min(0)]).sum(1)
    return w, idx, x_hat, o, d, p_def, p_can


def test_matches_reference_both_modes():
    for seed in range(3):
        case = _case(seed)
        for mode in ("deform-aware", "naive"):
            fast = canonical_points(*case, mode=mode)
            ref = _reference(*case, mode)
            assert torch.allclose(fast, ref, atol=1e-5), (seed, mode)


def test_rigid_translation_is_undone_exactly():
    w, idx, x_hat, o, d, p_def, p_can = _case(1)
    shift = torch.tensor([0.5, -2.0, 0.25])
    p_def = p_can + shift
    x_hat = (w[..., None] * p_def[idx.clamp_min(0)]).sum(1)
    x_can = canonical_points(w, idx, x_hat, o, d, p_def, p_can, "deform-aware")
    assert torch.allclose(x_can, project_on_ray(x_hat, o, d) - shift, atol=1e-5)


def test_identity_deformation_deform_aware_is_ray_projection():
    w, idx, x_hat, o, d, _, p_can = _case(2)
    x_hat = (w[..., None] * p_can[idx.clamp_min(0)]).sum(1)
    x_can = canonical_points(w, idx, x_hat, o, d, p_can, p_can, "deform-aware")
    assert torch.allclose(x_can, project_on_ray(x_hat, o, d), atol=1e-6)
    naive = canonical_points(w, idx, x_hat, o, d, p_can, p_can, "naive")
    assert torch.allclose(naive, x_hat, atol=1e-6)


def test_deform_gradient_matches_loop_and_reduces_to_deform_aware_at_identity():
    w, idx, x_hat, o, d, p_def, p_can = _case(4)
    g = torch.Generator().manual_seed(9)
    inv_f = torch.eye(3) + 0.3 * torch.randn(p_def.shape[0], 3, 3, generator=g)
    fast = canonical_points(w, idx, x_hat, o, d, p_def, p_can, "deform-gradient", inv_f=inv_f)
    x_def = project_on_ray(x_hat, o, d)
    ref = torch.stack([sum(w[i, j] * (p_can[idx[i, j]] + inv_f[idx[i, j]] @ (x_def[i] - p_def[idx[i, j]]))
                           for j in range(w.shape[1]) if idx[i, j] >= 0) for i in range(w.shape[0])])
    assert torch.allclose(fast, ref, atol=1e-5)
    eye = torch.eye(3).expand(p_def.shape[0], 3, 3)
    same = canonical_points(w, idx, x_hat, o, d, p_def, p_can, "deform-gradient", inv_f=eye)
    assert torch.allclose(same, canonical_points(w, idx, x_hat, o, d, p_def, p_can, "deform-aware"), atol=1e-5)


def test_deform_gradient_undoes_an_affine_deformation_exactly():
    """p_def = A p_can + b: every neighbour maps the ray's surface point back to A⁻¹ (x_def − b), whatever the
    weights; the translation-only deform-aware correspondence misses by the local stretch/rotation."""
    w, idx, x_hat, o, d, _, p_can = _case(5)
    a = torch.tensor([[5.0, 0.0, 0.0], [0.0, 0.8, -0.6], [0.0, 0.6, 0.8]])
    b = torch.tensor([0.3, -1.0, 0.5])
    p_def = p_can @ a.T + b
    x_hat = (w[..., None] * p_def[idx.clamp_min(0)]).sum(1)
    inv_f = torch.linalg.inv(a).expand(p_def.shape[0], 3, 3)
    x_def = project_on_ray(x_hat, o, d)
    want = (x_def - b) @ torch.linalg.inv(a).T
    got = canonical_points(w, idx, x_hat, o, d, p_def, p_can, "deform-gradient", inv_f=inv_f)
    assert torch.allclose(got, want, atol=1e-4)
    aware = canonical_points(w, idx, x_hat, o, d, p_def, p_can, "deform-aware")
    assert float((aware - want).norm(dim=1).mean()) > 0.1
    try:
        canonical_points(w, idx, x_hat, o, d, p_def, p_can, "deform-gradient")
    except ValueError as exc:
        assert "inv_f" in str(exc)
    else:
        raise AssertionError("deform-gradient without inv_f must raise")


def _trace(w, idx, x_hat, o, d):
    """A Trace holding the case's rays (every ray active, all attention on the neighbours)."""
    r = w.shape[0]
    return Trace(origins=o, dirs=d, idx=idx, weights=w, fg_weights=w, bg=torch.zeros(r), x=x_hat,
                 active=torch.ones(r, dtype=torch.bool), shape=(1, r))


def test_ray_canonical_points_matches_the_loop_on_selected_rays():
    """The per-ray function every caller uses: selected rays of a trace, by index or mask, against the loop;
    a non-finite deformed point (a broken rig) enters as the origin; nothing moved = the projection on the ray."""
    w, idx, x_hat, o, d, p_def, p_can = _case(6)
    p_def = p_def.clone()
    p_def[int(idx[3, 0])] = float("nan")
    clean = torch.nan_to_num(p_def, nan=0.0)
    x_hat = (w[..., None] * clean[idx.clamp_min(0)]).sum(1)
    tr = _trace(w, idx, x_hat, o, d)
    sel = torch.tensor([0, 3, 7, 11])
    mask = torch.zeros(w.shape[0], dtype=torch.bool)
    mask[sel] = True
    for mode in ("deform-aware", "naive"):
        ref = _reference(w, idx, x_hat, o, d, clean, p_can, mode)[sel]
        for s in (sel, mask):
            got = ray_canonical_points(tr, s, p_def, p_can, mode)
            assert torch.isfinite(got).all() and torch.allclose(got, ref, atol=1e-5), mode
    rest = ray_canonical_points(tr, sel)
    want = torch.stack([o[i] + max(float(torch.dot(x_hat[i] - o[i], d[i])), 0.0) * d[i] for i in sel.tolist()])
    assert torch.allclose(rest, want, atol=1e-6)
    assert torch.equal(ray_canonical_points(tr)[sel], rest)  # sel None: every ray
    inv_f = torch.eye(3).expand(p_def.shape[0], 3, 3)
    grad = ray_canonical_points(tr, sel, p_def, p_can, "deform-gradient", inv_f=inv_f)
    assert torch.allclose(grad, ray_canonical_points(tr, sel, p_def, p_can, "deform-aware"), atol=1e-5)


def _two_layers(seed=0, r=12, k=6):
    """Rays whose neighbours come from two parts: a front part near canonical (0, 0, 0) and a part the pose swung
    behind it, whose canonical points lie far away (around (10, 0, 0)) and which moved by (−10, 0, 1)."""
    g = torch.Generator().manual_seed(seed)
    front = 0.05 * torch.randn(r * k, 3, generator=g)
    back_can = torch.tensor([10.0, 0.0, 0.0]) + 0.05 * torch.randn(r * k, 3, generator=g)
    p_can = torch.cat([front, back_can])
    p_def = torch.cat([front, back_can + torch.tensor([-10.0, 0.0, 1.0])])
    n = r * k
    idx = torch.cat([torch.arange(n).view(r, k)[:, : k - 2], n + torch.arange(2 * r).view(r, 2)], 1)  # 2 behind
    w = torch.cat([torch.full((r, k - 2), 0.9 / (k - 2)), torch.full((r, 2), 0.05)], 1)
    o = torch.tensor([0.0, 0.0, -5.0]).expand(r, 3).clone()
    d = torch.tensor([0.0, 0.0, 1.0]).expand(r, 3).clone()
    x_hat = (w[..., None] * p_def[idx]).sum(1)
    return w, idx, x_hat, o, d, p_def, p_can


def test_fold_rule_drops_the_part_behind():
    """10 % of the attention on a part that moved 10 units drags the paper's lookup ≈ 1 unit across the texture;
    the fold rule keeps the front part only and lands on it."""
    case = _two_layers()
    front_can = (case[0][:, :-2, None] * case[6][case[1][:, :-2]]).sum(1) / 0.9
    for mode in ("naive", "deform-aware"):
        plain = canonical_points(*case, mode=mode)
        folded = canonical_points(*case, mode=mode, fold_radius=1.0)
        assert float((plain - front_can)[:, 0].abs().min()) > 0.5
        assert float((folded[:, :2] - front_can[:, :2]).abs().max()) < 0.2
    inv_f = torch.eye(3).expand(case[5].shape[0], 3, 3)
    got = canonical_points(*case, mode="deform-gradient", inv_f=inv_f, fold_radius=1.0)
    assert float((got[:, :2] - front_can[:, :2]).abs().max()) < 0.2


def test_fold_rule_changes_nothing_on_one_smooth_layer():
    """All neighbours within the radius (or no radius): bit-identical to the paper's correspondence."""
    for seed in range(3):
        case = _case(seed)
        for mode in ("naive", "deform-aware"):
            ref = canonical_points(*case, mode=mode)
            assert torch.equal(canonical_points(*case, mode=mode, fold_radius=1e6), ref)
            assert torch.equal(canonical_points(*case, mode=mode, fold_radius=float("inf")), ref)
            assert torch.equal(canonical_points(*case, mode=mode, fold_radius=None), ref)


def test_fold_rule_changes_nothing_under_a_rigid_translation():
    """Every point moved by the same vector: one displacement (up to rounding), nothing dropped at any radius."""
    w, idx, _, o, d, _, p_can = _case(6)
    p_def = p_can + torch.tensor([0.4, -1.0, 2.0])
    x_hat = (w[..., None] * p_def[idx.clamp_min(0)]).sum(1)
    for mode in ("naive", "deform-aware"):
        ref = canonical_points(w, idx, x_hat, o, d, p_def, p_can, mode=mode)
        assert torch.equal(canonical_points(w, idx, x_hat, o, d, p_def, p_can, mode=mode, fold_radius=1e-5), ref)


def test_fold_rule_is_finite_on_hostile_rows():
    """Rays without neighbours, all weight underflowed, radius 0 (the anchor alone): finite, and a row whose
    weight is all on one neighbour is that neighbour's lookup."""
    w, idx, x_hat, o, d, p_def, p_can = _case(3)
    idx[1] = -1
    w[1] = 0.0
    w[2] = 0.0
    for mode in ("naive", "deform-aware"):
        out = canonical_points(w, idx, x_hat, o, d, p_def, p_can, mode=mode, fold_radius=0.0)
        assert torch.isfinite(out).all()
    naive = canonical_points(w, idx, x_hat, o, d, p_def, p_can, mode="naive", fold_radius=0.0)
    top = idx[3, w[3].argmax()]
    assert torch.allclose(naive[3], p_can[top] * w[3].sum(), atol=1e-6)


def test_local_map_fold_test_drops_nothing_under_an_affine_map_and_still_drops_the_part_behind():
    """fold_inv_f: neighbours are compared by their own local-map estimates of the ray's canonical point. Under a
    5× stretch with a rotation (F exact) the displacements differ by 4× the neighbours' canonical offsets and the
    displacement test drops most of them, but every local estimate agrees: nothing is dropped, even at a tight
    radius. Two parts (one swung behind, F = I on both): the local-map test drops the part behind as the
    displacement test does."""
    w, idx, _, o, d, _, p_can = _case(7)
    a = torch.tensor([[5.0, 0.0, 0.0], [0.0, 0.8, -0.6], [0.0, 0.6, 0.8]])
    b = torch.tensor([0.3, -1.0, 0.5])
    p_def = p_can @ a.T + b
    x_hat = (w[..., None] * p_def[idx.clamp_min(0)]).sum(1)
    inv_f = torch.linalg.inv(a).expand(p_def.shape[0], 3, 3).contiguous()
    for mode, kw in (("deform-aware", {}), ("deform-gradient", {"inv_f": inv_f})):
        ref = canonical_points(w, idx, x_hat, o, d, p_def, p_can, mode, **kw)
        local = canonical_points(w, idx, x_hat, o, d, p_def, p_can, mode, fold_radius=0.05, fold_inv_f=inv_f, **kw)
        assert torch.equal(local, ref)
        disp = canonical_points(w, idx, x_hat, o, d, p_def, p_can, mode, fold_radius=0.05, **kw)
        assert float((disp - ref).norm(dim=1).max()) > 0.1  # the displacement test dropped neighbours
    case = _two_layers()
    front_can = (case[0][:, :-2, None] * case[6][case[1][:, :-2]]).sum(1) / 0.9
    eye = torch.eye(3).expand(case[5].shape[0], 3, 3)
    for mode in ("naive", "deform-aware"):
        got = canonical_points(*case, mode=mode, fold_radius=1.0, fold_inv_f=eye)
        assert torch.isfinite(got).all()
        assert float((got[:, :2] - front_can[:, :2]).abs().max()) < 0.2
    # hostile rows: no neighbours, underflowed weights, a singular local map
    w, idx, x_hat, o, d, p_def, p_can = _case(3)
    idx[1] = -1
    w[1] = 0.0
    w[2] = 0.0
    bad = torch.eye(3).repeat(p_def.shape[0], 1, 1)
    bad[::3] = 0.0
    out = canonical_points(w, idx, x_hat, o, d, p_def, p_can, "deform-aware", fold_radius=0.0, fold_inv_f=bad)
    assert torch.isfinite(out).all()


def test_compiled_backend_matches_torch():
    """The compiled pass (fold rule + naive / deform-aware sum, one loop per ray) equals the torch path to float
    rounding: every radius (none, 0, dropping some, dropping none), rays without neighbours, zero-weight rows, the
    two-layer fold; and rows the rule leaves whole are the same numbers with and without it."""
    import pytest

    from core.edits import correspondence as corr

    if corr.numba is None:
        pytest.skip("numba is not installed")
    for seed in range(6):
        case = list(_case(seed, r=64, k=12, m=120))
        case[0][5] = 0.0
        case[1][6] = -1
        g = torch.Generator().manual_seed(seed)
        inv_f = torch.eye(3) + 0.4 * torch.randn(120, 3, 3, generator=g)  # turned, stretched, mirrored maps
        inv_f[::7] = 0.0  # degenerate ones
        for mode in ("naive", "deform-aware", "deform-gradient"):
            maps = inv_f if mode == "deform-gradient" else None
            for radius in (None, 0.0, 0.3, 1.0, 1e6, float("inf")):
                ref = canonical_points(*case, mode=mode, inv_f=maps, fold_radius=radius, backend="torch")
                got = canonical_points(*case, mode=mode, inv_f=maps, fold_radius=radius, backend="compiled")
                assert torch.isfinite(got).all()
                assert torch.allclose(got, ref, atol=1e-5, rtol=0), (seed, mode, radius)
            whole = canonical_points(*case, mode=mode, inv_f=maps, fold_radius=1e6, backend="compiled")
            assert torch.equal(whole, canonical_points(*case, mode=mode, inv_f=maps, backend="compiled"))
        eye = torch.eye(3).expand(120, 3, 3)  # F = I: deform-gradient is deform-aware
        assert torch.allclose(canonical_points(*case, mode="deform-gradient", inv_f=eye, backend="compiled"),
                              canonical_points(*case, mode="deform-aware", backend="compiled"), atol=1e-5, rtol=0)
    case = _two_layers()
    eye = torch.eye(3).expand(case[5].shape[0], 3, 3)
    for mode in ("naive", "deform-aware", "deform-gradient"):
        maps = eye if mode == "deform-gradient" else None
        ref = canonical_points(*case, mode=mode, inv_f=maps, fold_radius=1.0, backend="torch")
        got = canonical_points(*case, mode=mode, inv_f=maps, fold_radius=1.0, backend="compiled")
        assert torch.allclose(got, ref, atol=1e-5)
        # the local-map fold rule in torch, the sum compiled
        ref = canonical_points(*case, mode=mode, inv_f=maps, fold_radius=1.0, fold_inv_f=eye, backend="torch")
        got = canonical_points(*case, mode=mode, inv_f=maps, fold_radius=1.0, fold_inv_f=eye, backend="compiled")
        assert torch.allclose(got, ref, atol=1e-5)
    with pytest.raises(ValueError):
        canonical_points(*case, mode="deform-gradient", backend="compiled")  # no maps
