"""Invariants every rendered frame must satisfy, shared by the stability tests."""
import torch


def check_frame(out, h, w):
    """The invariants of every frame: shapes, finite rgb/alpha in [0, 1], x_can finite or NaN (off the object)."""
    rgb, alpha, x = out["rgb"], out["alpha"], out["x_can"]
    assert rgb.shape == (h, w, 3) and alpha.shape == (h, w) and x.shape == (h, w, 3)
    assert bool(torch.isfinite(rgb).all()) and float(rgb.min()) >= 0.0 and float(rgb.max()) <= 1.0
    assert bool(torch.isfinite(alpha).all()) and float(alpha.min()) >= 0.0 and float(alpha.max()) <= 1.0 + 1e-6
    assert not bool(torch.isinf(x).any())
    for key in ("weights", "fg_weights", "bg", "x"):
        assert bool(torch.isfinite(getattr(out["trace"], key)).all()), key
