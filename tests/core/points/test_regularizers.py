"""Geometry regularizers: values, zeros where they must be zero, gradient routing, finiteness."""
import torch

from core.images.rays import distance_to_ray
from core.points.regularizers import close_to_ray, close_to_surface


def _att_on_ray(r=8, k=4):
    o = torch.zeros(r, 3)
    d = torch.tensor([0.0, 0.0, 1.0]).expand(r, 3).clone()
    t = torch.linspace(1, 2, k)
    p = (o[:, None, :] + t[None, :, None] * d[:, None, :]).clone().requires_grad_(True)  # all points on the ray
    w = torch.full((r, k), 1.0 / k, requires_grad=True)
    x = (w[..., None] * p).sum(1)
    return {"fg_weights": w, "p": p, "x": x, "valid": torch.ones(r, k, dtype=torch.bool)}, o, d


def test_close_to_ray_zero_when_points_on_ray_and_positive_off_ray():
    att, o, d = _att_on_ray()
    fg = torch.ones(8, dtype=torch.bool)
    assert float(close_to_ray(att, o, d, fg).detach()) < 1e-6
    att["p"] = att["p"] + torch.tensor([0.3, 0.0, 0.0])
    assert abs(float(close_to_ray(att, o, d, fg).detach()) - 0.3) < 1e-5


def test_close_to_ray_moves_attention_not_points():
    att, o, d = _att_on_ray()
    p = att["p"].detach().clone()
    p[:, 0, 0] += 1.0  # one neighbour off the ray
    p.requires_grad_(True)
    att["p"] = p
    close_to_ray(att, o, d, torch.ones(8, dtype=torch.bool)).backward()
    assert p.grad is None  # points detached
    assert att["fg_weights"].grad is not None and float(att["fg_weights"].grad.abs().sum()) > 0


def test_close_to_surface_zero_when_neighbours_at_x_and_only_moves_points():
    att, o, d = _att_on_ray(k=1)
    fg = torch.ones(8, dtype=torch.bool)
    assert float(close_to_surface(att, fg).detach()) < 1e-6
    att, o, d = _att_on_ray(k=4)
    loss = close_to_surface(att, fg)
    assert float(loss.detach()) > 0
    loss.backward()
    assert att["p"].grad is not None and torch.isfinite(att["p"].grad).all()
    assert att["fg_weights"].grad is None  # x detached: no gradient into attention


def test_background_rays_ignored_and_empty_mask_is_zero():
    att, o, d = _att_on_ray()
    none = torch.zeros(8, dtype=torch.bool)
    assert float(close_to_ray(att, o, d, none).detach()) == 0.0
    assert float(close_to_surface(att, none).detach()) == 0.0


def test_distance_to_ray_far_points_finite():
    o = torch.zeros(2, 3)
    d = torch.tensor([[0.0, 0.0, 1.0], [1.0, 0.0, 0.0]])
    x = torch.tensor([[1e18, 0.0, 1e18], [3.0, 4.0, 0.0]])
    dist = distance_to_ray(x, o, d)
    assert torch.isfinite(dist).all() and abs(float(dist[1]) - 4.0) < 1e-6
