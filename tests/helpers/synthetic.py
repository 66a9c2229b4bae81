"""Analytic ray-traced scenes for fast tests (no Blender): a textured sphere and a thin textured card.

Colours are emission-like (no lighting) functions of the surface point, images are 2×2 supersampled so that
alpha is anti-aliased like a Cycles render, cameras sit on a sphere looking at the origin.
"""
from __future__ import annotations

import math
from pathlib import Path

import torch

from core.images.cameras import Intrinsics, focal_from_fov, look_at, pixel_rays
from core.images.dataset import SplitData


def stripes(x: torch.Tensor) -> torch.Tensor:
    """A smooth colour field of 3-D position: x [N, 3] -> rgb [N, 3] in [0, 1]."""
    r = 0.5 + 0.4 * torch.sin(4.0 * x[:, 0] + 1.0)
    g = 0.5 + 0.4 * torch.sin(5.0 * x[:, 1] + 2.0)
    b = 0.5 + 0.4 * torch.cos(3.0 * x[:, 2] + 0.5 * x[:, 0])
    return torch.stack([r, g, b], dim=-1)


def fibonacci_cameras(n: int, radius: float = 4.0, seed: int = 0) -> torch.Tensor:
    """n camera-to-world matrices [n, 4, 4] spread over a sphere, looking at the origin."""
    g = torch.Generator().manual_seed(seed)
    off = float(torch.rand(1, generator=g))
    mats = []
    for i in range(n):
        z = 1 - 2 * (i + 0.5) / n
        z = max(min(z, 0.98), -0.98)
        phi = math.pi * (3 - math.sqrt(5)) * i + 2 * math.pi * off
        r = math.sqrt(1 - z * z)
        eye = (radius * r * math.cos(phi), radius * r * math.sin(phi), radius * z)
        mats.append(look_at(eye).float())
    return torch.stack(mats)


def _hit(shape: str, o: torch.Tensor, d: torch.Tensor):
    """Ray hits: returns t [R] (inf = miss) for the analytic shapes."""
    if shape == "sphere":
        rad = 0.7
        b = (o * d).sum(-1)
        c = (o * o).sum(-1) - rad * rad
        disc = b * b - c
        t = -b - torch.sqrt(disc.clamp_min(0))
        return torch.where((disc > 0) & (t > 0), t, torch.full_like(t, float("inf")))
    if shape == "card":  # plane z = 0.05 * sin(2x), thin double-sided card |x| < 0.9, |y| < 0.5 (approximately bent)
        t = -o[:, 2] / torch.where(d[:, 2].abs() > 1e-9, d[:, 2], torch.full_like(d[:, 2], 1e-9))
        p = o + t[:, None] * d
        ok = (t > 0) & (p[:, 0].abs() < 0.9) & (p[:, 1].abs() < 0.5)
        return torch.where(ok, t, torch.full_like(t, float("inf")))
    raise ValueError(shape)


def undistort_normalised(lens, xd: torch.Tensor, yd: torch.Tensor, iters: int = 200):
    """Brute-force inverse of OpenCV's radial-tangential model (lens = (k1, k2, k3, p1, p2)) by fixed-point
    iteration: distorted normalised coordinates -> the undistorted ones that distort onto them (float64)."""
    k1, k2, k3, p1, p2 = lens
    xd, yd = xd.double(), yd.double()
    x, y = xd.clone(), yd.clone()
    for _ in range(iters):
        r2 = x * x + y * y
        radial = 1 + r2 * (k1 + r2 * (k2 + r2 * k3))
        x, y = ((xd - 2 * p1 * x * y - p2 * (r2 + 2 * x * x)) / radial,
                (yd - p1 * (r2 + 2 * y * y) - 2 * p2 * x * y) / radial)
    return x, y


def render_split(shape: str, c2w: torch.Tensor, size: int, fov: float = 0.69, colour=stripes,
                 background=(1.0, 1.0, 1.0), split: str = "train", height: int | None = None,
                 intrinsics: Intrinsics | None = None, lens: tuple | None = None) -> SplitData:
    """Render views of an analytic shape into a SplitData (images [V,H,W,3], alphas [V,H,W], ...): `size` wide,
    `height` (default `size`) high, through a centred camera of horizontal field of view `fov` or `intrinsics`,
    seen through the distorting lens (k1, k2, k3, p1, p2) when `lens` is given (the SplitData keeps the pinhole
    intrinsics)."""
    h, w = (height or size), size
    focal = focal_from_fov(size, fov) if intrinsics is None else intrinsics
    ss = 2
    cam = focal * ss if intrinsics is None else intrinsics.scaled(ss)
    bg = torch.tensor(background)
    ims, als = [], []
    for m in c2w:
        o, d = pixel_rays(m, h * ss, w * ss, cam)
        if lens is not None:  # each pixel sees the ray that the lens bends onto it
            k = Intrinsics(*[float(v) for v in (cam if isinstance(cam, Intrinsics) else
                                                Intrinsics(cam, cam, w * ss / 2, h * ss / 2)).as_list()])
            v, u = torch.meshgrid(torch.arange(h * ss) + 0.5, torch.arange(w * ss) + 0.5, indexing="ij")
            x, y = undistort_normalised(lens, (u - k.cx) / k.fx, (v - k.cy) / k.fy)
            dc = torch.stack([x, -y, -torch.ones_like(x)], -1)
            d = (dc / dc.norm(dim=-1, keepdim=True)) @ m[:3, :3].double().T
            d = d.to(o.dtype)
        o, d = o.reshape(-1, 3), d.reshape(-1, 3)
        t = _hit(shape, o, d)
        hit = torch.isfinite(t)
        rgb = torch.zeros_like(o)
        p = o[hit] + t[hit, None] * d[hit]
        rgb[hit] = colour(p)
        a = hit.float()
        rgb = rgb.reshape(h, ss, w, ss, 3).mean((1, 3))
        a = a.reshape(h, ss, w, ss).mean((1, 3))
        ims.append(rgb + (1 - a[..., None]) * bg)
        als.append(a)
    files = [Path(f"{split}/r_{i}.png") for i in range(len(c2w))]
    angle = fov if intrinsics is None else 2 * math.atan(0.5 * w / intrinsics.fx)
    return SplitData(split=split, images=torch.stack(ims).float(), alphas=torch.stack(als).float(),
                     c2w=c2w.float(), focal=focal, height=h, width=w, camera_angle_x=angle, files=files)


def write_split(root: str | Path, split: SplitData, background=(1.0, 1.0, 1.0)) -> Path:
    """Write a rendered split (composited over `background`, as render_split made it) as a NeRF-synthetic
    folder: `<split>/r_<i>.png` (RGBA, straight colour) and `transforms_<split>.json`. Returns root."""
    import json

    import numpy as np

    from core.images.png import write_png

    root = Path(root)
    (root / split.split).mkdir(parents=True, exist_ok=True)
    bg = torch.tensor(background, dtype=torch.float32)
    frames = []
    for i, name in enumerate(split.files):
        a = split.alphas[i][..., None]
        straight = torch.where(a > 0, (split.images[i] - (1 - a) * bg) / a.clamp_min(1e-6), torch.zeros_like(a))
        write_png(root / name, np.concatenate([straight.clamp(0, 1).numpy(), a.numpy()], -1), backup=False)
        frames.append({"file_path": f"./{split.split}/r_{i}", "transform_matrix": split.c2w[i].tolist()})
    (root / f"transforms_{split.split}.json").write_text(
        json.dumps({"camera_angle_x": split.camera_angle_x, "frames": frames}))
    return root


def write_capture(root: str | Path, splits: list[SplitData], frame_keys=None, top_keys: dict | None = None) -> Path:
    """Write rendered splits as one nerfstudio capture: `images/<split>_<i>.png` (RGB, straight colour),
    `masks/<split>_<i>.png` (the alpha), and `transforms.json` with the first split's intrinsics at the top
    (`camera_model` OPENCV, zero distortion), `<split>_filenames` lists. frame_keys(split, i) -> dict of keys
    added to (or overriding in) that frame; top_keys override the top-level keys. Returns root."""
    import json

    import numpy as np

    from core.images.png import write_png

    root = Path(root)
    (root / "images").mkdir(parents=True, exist_ok=True)
    (root / "masks").mkdir(exist_ok=True)
    first = splits[0]
    k = first.intrinsics
    doc = {"camera_model": "OPENCV", "fl_x": k.fx, "fl_y": k.fy, "cx": k.cx, "cy": k.cy, "w": first.width,
           "h": first.height, "k1": 0.0, "k2": 0.0, "k3": 0.0, "p1": 0.0, "p2": 0.0, "frames": []}
    for split in splits:
        bg = torch.ones(3)
        names = []
        for i in range(len(split.files)):
            a = split.alphas[i][..., None]
            straight = torch.where(a > 0, (split.images[i] - (1 - a) * bg) / a.clamp_min(1e-6), torch.zeros_like(a))
            name = f"images/{split.split}_{i}.png"
            write_png(root / name, straight.clamp(0, 1).numpy(), backup=False)
            write_png(root / f"masks/{split.split}_{i}.png", a.expand(-1, -1, 3).numpy(), backup=False)
            frame = {"file_path": name, "mask_path": f"masks/{split.split}_{i}.png",
                     "transform_matrix": split.c2w[i].tolist()}
            frame.update(frame_keys(split.split, i) if frame_keys else {})
            doc["frames"].append(frame)
            names.append(name)
        doc[f"{split.split}_filenames"] = names
    doc.update(top_keys or {})
    (root / "transforms.json").write_text(json.dumps(doc, indent=1))
    return root
