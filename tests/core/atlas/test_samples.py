import numpy as np
import pytest
import torch

from core.atlas.samples import extract_surface_samples, remove_outliers
from core.images.cameras import look_at
from core.util.errors import InputError

RADIUS = 0.5


def _sphere_render(origins, dirs):
    """Analytic ray/sphere hit at the origin; fg = 1 on hits. Adds a small off-ray offset to test projection."""
    b = (origins * dirs).sum(-1)
    c = (origins * origins).sum(-1) - RADIUS ** 2
    disc = b * b - c
    hit = disc > 0
    t = -b - torch.sqrt(disc.clamp_min(0))
    x = origins + t[:, None] * dirs
    off = torch.linalg.cross(dirs, torch.tensor([0.0, 0.0, 1.0]).expand_as(dirs)) * 0.01  # perpendicular to the ray
    return {"x": x + off, "fg": hit.float()}


def _views(n=3, size=24):
    out = []
    for k in range(n):
        ang = 2 * np.pi * k / n
        c2w = look_at((2.0 * np.cos(ang), 2.0 * np.sin(ang), 0.5))
        c2w = c2w.float()
        img = torch.rand(size, size, 3, generator=torch.Generator().manual_seed(k))
        alpha = torch.ones(size, size)
        alpha[:, : size // 4] = 0  # left quarter masked out by ground truth
        out.append((c2w, size, size, 30.0, img, alpha))
    return out


def test_samples_lie_on_the_surface_and_carry_pixel_colours():
    views = _views()
    xyz, rgb = extract_surface_samples(_sphere_render, views, outlier_std=10.0)
    assert xyz.shape == rgb.shape and xyz.shape[1] == 3
    assert (xyz.norm(dim=-1) - RADIUS).abs().max() < 2e-3  # projected back onto the ray -> on the sphere
    # every colour is one of the source pixels, and masked pixels (alpha 0) never contribute
    allowed = torch.cat([v[4][:, v[2] // 4:].reshape(-1, 3) for v in views])
    assert (rgb[:, None] == allowed[None]).all(-1).any(1).all()  # exact matches


def test_max_samples_subsamples_deterministically():
    a, _ = extract_surface_samples(_sphere_render, _views(), max_samples=100, seed=3)
    b, _ = extract_surface_samples(_sphere_render, _views(), max_samples=100, seed=3)
    assert a.shape == (100, 3) and torch.equal(a, b)


def test_outlier_removal_matches_brute_force():
    g = np.random.default_rng(0)
    pts = g.normal(size=(400, 3))
    pts /= np.linalg.norm(pts, axis=1, keepdims=True)
    pts = np.concatenate([pts, [[5.0, 5.0, 5.0], [-4.0, 6.0, 0.0]]])
    keep = remove_outliers(pts, k=8, std_ratio=2.0)
    d = torch.cdist(torch.from_numpy(pts), torch.from_numpy(pts))
    knn = d.topk(9, largest=False).values[:, 1:].mean(1)  # brute-force reference
    ref = (knn <= knn.mean() + 2.0 * knn.std(unbiased=False)).numpy()
    assert np.array_equal(keep, ref)
    assert not keep[-1] and not keep[-2]


def test_no_foreground_is_a_clear_error():
    def miss(o, d):
        return {"x": o, "fg": torch.zeros(len(o))}
    with pytest.raises(InputError, match="no surface samples"):
        extract_surface_samples(miss, _views())


def test_bad_view_shapes_are_reported():
    c2w, h, w, f, img, alpha = _views(1)[0]
    with pytest.raises(InputError, match="view 0"):
        extract_surface_samples(_sphere_render, [(c2w, h, w, f, img[:, :5], alpha)])


def _coloured_render(origins, dirs, bg=(0.2, 0.9, 0.4)):
    """The sphere render plus a display colour fg * c + (1 - fg) * bg with a known object colour c(x)."""
    out = _sphere_render(origins, dirs)
    fg = out["fg"] * 0.6  # partial coverage on hits (above the 0.5 threshold), to test the un-compositing
    c = (out["x"] * 0.8 + 0.5).clamp(0, 1)
    return {"x": out["x"], "fg": fg, "rgb": fg[:, None] * c + (1 - fg[:, None]) * torch.tensor(bg)}


def test_render_colour_is_the_uncomposited_object_colour():
    xyz, rgb = extract_surface_samples(_coloured_render, _views(), outlier_std=10.0, colour="render",
                                       background=(0.2, 0.9, 0.4))
    # c was computed at the unprojected x (1 cm off the ray); projection moves x by <= 1 cm (0.8 cm in colour).
    assert (rgb - (xyz * 0.8 + 0.5).clamp(0, 1)).abs().max() < 0.02
    xyz_i, rgb_i = extract_surface_samples(_coloured_render, _views(), outlier_std=10.0)  # image colours differ
    assert torch.equal(xyz_i, xyz) and not torch.allclose(rgb_i, rgb)


def test_render_colour_needs_rgb_and_a_known_mode():
    with pytest.raises(InputError, match="needs the render function to return 'rgb'"):
        extract_surface_samples(_sphere_render, _views(1), colour="render")
    with pytest.raises(InputError, match="colour must be"):
        extract_surface_samples(_sphere_render, _views(1), colour="paint")
