"""The camera convention everything rests on: c2w camera-to-world looking down −Z with +Y up, pixel (r, c) centred
at (c + 0.5, r + 0.5), row 0 at the top — checked against brute-force references written out here."""
import math

import pytest
import torch

from core.images.cameras import focal_from_fov, look_at, pixel_rays, project_points, rays_for_pixels
from core.images.rays import distance_to_ray, project_on_ray
from core.points.render import pixel_grid


def _camera(seed=0):
    """A generic camera: random rotation (det +1) and position, float64."""
    g = torch.Generator().manual_seed(seed)
    q, _ = torch.linalg.qr(torch.randn(3, 3, generator=g, dtype=torch.float64))
    if torch.det(q) < 0:
        q[:, 0] = -q[:, 0]
    m = torch.eye(4, dtype=torch.float64)
    m[:3, :3], m[:3, 3] = q, torch.randn(3, generator=g, dtype=torch.float64) * 2
    return m


def _reference_pixel(p, c2w, h, w, focal):
    """Pinhole projection written from the convention alone: camera axes are the columns of c2w (x right, y up,
    z back), image x grows to the right from the left edge, image y grows downwards from the top edge."""
    rel = p - c2w[:3, 3]
    x, y, z = (float(rel @ c2w[:3, i]) for i in range(3))
    return focal * x / -z + w / 2, focal * -y / -z + h / 2


@pytest.mark.parametrize("h,w", [(5, 7), (6, 4)])
def test_each_pixel_ray_passes_through_its_pixel_centre(h, w):
    c2w, focal = _camera(1), 6.0
    o, d = pixel_rays(c2w, h, w, focal)
    assert o.shape == d.shape == (h, w, 3)
    assert torch.allclose(d.norm(dim=-1), torch.ones(h, w, dtype=torch.float64))
    for r in range(h):
        for c in range(w):
            p = o[r, c] + 2.5 * d[r, c]  # any point on the ray
            col, row = _reference_pixel(p, c2w, h, w, focal)
            assert col == pytest.approx(c + 0.5, abs=1e-9) and row == pytest.approx(r + 0.5, abs=1e-9)


def test_project_points_matches_the_reference_and_depth_is_along_minus_z():
    c2w, h, w, focal = _camera(2), 9, 11, 8.0
    g = torch.Generator().manual_seed(3)
    cam = torch.stack([torch.rand(50, generator=g, dtype=torch.float64) * 2 - 1,
                       torch.rand(50, generator=g, dtype=torch.float64) * 2 - 1,
                       -(torch.rand(50, generator=g, dtype=torch.float64) * 3 + 0.5)], 1)
    pts = cam @ c2w[:3, :3].T + c2w[:3, 3]
    px, depth = project_points(pts, c2w, h, w, focal)
    assert torch.allclose(depth, -cam[:, 2])
    for i in range(len(pts)):
        col, row = _reference_pixel(pts[i], c2w, h, w, focal)
        assert px[i, 0].item() == pytest.approx(col, abs=1e-9) and px[i, 1].item() == pytest.approx(row, abs=1e-9)


def test_brute_force_nearest_ray_is_the_pixel_that_contains_the_projection():
    """For points in front of the camera, the pixel whose centre ray passes closest (searched over every pixel)
    is (floor(row), floor(col)) of the projection: centres at +0.5, row 0 at the top."""
    c2w, h, w, focal = _camera(4), 8, 10, 9.0
    o, d = pixel_rays(c2w, h, w, focal)
    o, d = o.reshape(-1, 3), d.reshape(-1, 3)
    g = torch.Generator().manual_seed(5)
    checked = 0
    for _ in range(40):
        col, row = float(torch.rand(1, generator=g)) * w, float(torch.rand(1, generator=g)) * h
        fc, fr = col - math.floor(col), row - math.floor(row)
        if min(fc, 1 - fc, fr, 1 - fr) < 0.1:  # near a pixel edge two rays are nearly as close
            continue
        depth = 1.0 + 3.0 * float(torch.rand(1, generator=g))
        cam = torch.tensor([(col - w / 2) / focal * depth, -(row - h / 2) / focal * depth, -depth],
                           dtype=torch.float64)
        p = c2w[:3, :3] @ cam + c2w[:3, 3]
        # angular distance to each pixel's ray (distance / depth along it), smallest wins
        dist = distance_to_ray(p.expand(h * w, 3), o, d) / ((p - o) * d).sum(-1)
        best = int(dist.argmin())
        assert (best // w, best % w) == (math.floor(row), math.floor(col))
        checked += 1
    assert checked >= 15


def test_look_at_keeps_world_up_at_the_top_of_the_image():
    c2w = look_at((0.0, -4.0, 0.0))  # on −Y looking at the origin, world Z up
    h = w = 16
    focal = focal_from_fov(w, 0.69)
    px, depth = project_points(torch.tensor([[0.0, 0.0, 0.0], [0.0, 0.0, 0.5], [0.5, 0.0, 0.0]],
                                            dtype=torch.float64), c2w, h, w, focal)
    assert torch.allclose(px[0], torch.tensor([w / 2, h / 2], dtype=torch.float64))
    assert px[1, 1] < h / 2 and px[1, 0] == pytest.approx(w / 2)  # above the target: a smaller row
    assert px[2, 0] > w / 2  # world +X is to the right when looking along +Y
    assert torch.allclose(depth, torch.full((3,), 4.0, dtype=torch.float64))


def test_field_of_view_edges_land_on_the_image_borders():
    w, h, fov = 20, 12, 0.8
    focal = focal_from_fov(w, fov)
    c2w = torch.eye(4, dtype=torch.float64)
    z = 3.0
    x = z * math.tan(fov / 2)
    px, _ = project_points(torch.tensor([[-x, 0.0, -z], [x, 0.0, -z]], dtype=torch.float64), c2w, h, w, focal)
    assert px[0, 0].item() == pytest.approx(0.0, abs=1e-9) and px[1, 0].item() == pytest.approx(w, abs=1e-9)


def test_rays_for_pixel_grid_equal_pixel_rays():
    c2w, h, w, focal = _camera(6).float(), 5, 7, 6.0
    o, d = pixel_rays(c2w, h, w, focal)
    o2, d2 = rays_for_pixels(c2w, pixel_grid(h, w, "cpu"), h, w, focal)
    assert torch.allclose(o.reshape(-1, 3), o2) and torch.allclose(d.reshape(-1, 3), d2, atol=1e-6)


def test_projection_on_a_ray_and_distance_agree():
    g = torch.Generator().manual_seed(7)
    o = torch.randn(30, 3, generator=g, dtype=torch.float64)
    d = torch.nn.functional.normalize(torch.randn(30, 3, generator=g, dtype=torch.float64), dim=1)
    x = o + 2.0 * d + torch.randn(30, 3, generator=g, dtype=torch.float64) * 0.1
    proj = project_on_ray(x, o, d)
    assert torch.allclose(((x - proj) * d).sum(-1), torch.zeros(30, dtype=torch.float64), atol=1e-12)
    assert torch.allclose((x - proj).norm(dim=-1), distance_to_ray(x, o, d))
    behind = o - 3.0 * d  # t is clamped at the origin
    assert torch.allclose(project_on_ray(behind, o, d), o)


# ------------------------------------------------------------------ general intrinsics (fx, fy, cx, cy)
from core.images.cameras import Intrinsics, focal_scale, intrinsics, simplest  # noqa: E402
from core.util.errors import InputError  # noqa: E402


def _reference_pixel_k(p, c2w, k):
    """Brute force with separate focal lengths and a principal point measured from the top-left corner."""
    rel = p - c2w[:3, 3]
    x, y, z = (float(rel @ c2w[:3, i]) for i in range(3))
    return k.fx * x / -z + k.cx, k.fy * -y / -z + k.cy


@pytest.mark.parametrize("h,w,k", [(5, 9, Intrinsics(7.0, 4.5, 3.1, 2.9)), (8, 3, Intrinsics(5.0, 5.0, 0.4, 6.5))])
def test_pixel_rays_with_intrinsics_pass_through_their_pixel_centres(h, w, k):
    c2w = _camera(4)
    o, d = pixel_rays(c2w, h, w, k)
    assert o.shape == d.shape == (h, w, 3)
    for r in range(h):
        for c in range(w):
            col, row = _reference_pixel_k(o[r, c] + 1.7 * d[r, c], c2w, k)
            assert col == pytest.approx(c + 0.5, abs=1e-9) and row == pytest.approx(r + 0.5, abs=1e-9)
    px = torch.tensor([[0.25, 0.75], [w - 0.1, h - 2.3], [3.3, 1.1]], dtype=torch.float64)
    o2, d2 = rays_for_pixels(c2w, px, h, w, k)
    for i in range(len(px)):
        col, row = _reference_pixel_k(o2[i] + 2.0 * d2[i], c2w, k)
        assert (col, row) == (pytest.approx(float(px[i, 0]), abs=1e-9), pytest.approx(float(px[i, 1]), abs=1e-9))


def test_project_points_with_intrinsics_matches_brute_force_and_inverts_rays():
    c2w, h, w, k = _camera(5), 6, 10, Intrinsics(9.0, 6.0, 6.5, 2.0)
    g = torch.Generator().manual_seed(6)
    pts = torch.randn(40, 3, generator=g, dtype=torch.float64) + c2w[:3, 3] - 3 * c2w[:3, 2]
    px, depth = project_points(pts, c2w, h, w, k)
    for i in range(len(pts)):
        col, row = _reference_pixel_k(pts[i], c2w, k)
        assert px[i, 0].item() == pytest.approx(col, abs=1e-9) and px[i, 1].item() == pytest.approx(row, abs=1e-9)
    o, d = rays_for_pixels(c2w, px, h, w, k)  # the ray through each projection passes through the point
    assert torch.allclose(distance_to_ray(pts, o, d), torch.zeros(40, dtype=torch.float64), atol=1e-9)


def test_a_plain_focal_and_its_centred_intrinsics_agree_bit_for_bit():
    c2w, h, w, f = _camera(7), 7, 12, 9.25
    k = intrinsics(f, h, w)
    assert k == Intrinsics(f, f, 6.0, 3.5) and k.is_centred(h, w) and simplest(k, h, w) == f
    assert isinstance(simplest(Intrinsics(f, f, 6.0, 3.0), h, w), Intrinsics)
    for a, b in zip(pixel_rays(c2w, h, w, f), pixel_rays(c2w, h, w, k)):
        assert torch.equal(a, b)
    pts = torch.randn(20, 3, dtype=torch.float64) - 4 * c2w[:3, 2] + c2w[:3, 3]
    assert torch.equal(project_points(pts, c2w, h, w, f)[0], project_points(pts, c2w, h, w, k)[0])
    assert focal_scale(f) == f and focal_scale(Intrinsics(4.0, 9.0, 1, 1)) == pytest.approx(6.0)
    assert intrinsics(f, h, w).scaled(0.5) == Intrinsics(f / 2, f / 2, 3.0, 1.75)


@pytest.mark.parametrize("bad", [dict(fx=0.0), dict(fy=-1.0), dict(cx=math.nan), dict(cy=math.inf), dict(fx=True)])
def test_intrinsics_refuse_non_finite_or_non_positive_values(bad):
    args = dict(fx=5.0, fy=5.0, cx=2.0, cy=2.0) | bad
    with pytest.raises(InputError, match="camera intrinsics"):
        Intrinsics(**args)
