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
