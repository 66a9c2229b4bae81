"""One scene in all four layouts (tools/scenes/formats.py writes nerfstudio, instant-ngp and BlenderNeRF from the
NeRF-synthetic one) loads to the same cameras, rays and pixels."""
import json
import math

import numpy as np
import pytest
import torch
from PIL import Image

from core.images.cameras import intrinsics, look_at, pixel_rays
from core.images.dataset import load_cameras, load_dataset
from tools.scenes.formats import FORMATS, write_layout

H, W = 10, 14  # non-square
ANGLE = 0.6911112070083618
VIEWS = {"train": 5, "val": 2, "test": 3}


def make_scene(root):
    """A NeRF-synthetic folder like `pointgt make-scene` writes: RGBA PNGs, file_path without extension."""
    for split, n in VIEWS.items():
        (root / split).mkdir(parents=True)
        frames = []
        for i in range(n):
            rng = np.random.default_rng(hash((split, i)) % 10_000)
            img = rng.integers(0, 256, size=(H, W, 4), dtype=np.uint8)
            img[0, 0, 3], img[0, 1, 3] = 0, 255
            Image.fromarray(img).save(root / split / f"r_{i}.png")
            a = 2 * math.pi * (i + 0.3 * len(frames)) / n + len(split)
            frames.append({"file_path": f"./{split}/r_{i}",
                           "transform_matrix": look_at((4 * math.cos(a), 4 * math.sin(a), 0.5 + 0.2 * i)).tolist()})
        (root / f"transforms_{split}.json").write_text(json.dumps({"camera_angle_x": ANGLE, "frames": frames}))
    return root


@pytest.fixture(scope="module")
def layouts(tmp_path_factory):
    root = tmp_path_factory.mktemp("scene")
    src = make_scene(root / "nerf-synthetic")
    out = {"nerf-synthetic": src}
    for fmt in FORMATS:
        write_layout(src, root / fmt, fmt, log=lambda m: None)
        out[fmt] = root / fmt
    return out


@pytest.mark.parametrize("downscale", [1, 2])
def test_every_layout_loads_to_the_same_cameras_rays_and_pixels(layouts, downscale):
    loaded = {fmt: load_dataset(path, splits=("train", "val", "test"), required=("train", "val", "test"),
                                downscale=downscale) for fmt, path in layouts.items()}
    ref = loaded["nerf-synthetic"]
    assert {d.layout for s in loaded.values() for d in s.values()} == {"nerf-synthetic", *FORMATS}
    for fmt, splits in loaded.items():
        for split, d in splits.items():
            r = ref[split]
            assert len(d) == VIEWS[split] and (d.height, d.width) == (r.height, r.width) == (H // downscale,
                                                                                           W // downscale)
            assert [f.stem.removeprefix(f"{split}_") for f in d.files] == [f.stem for f in r.files]
            assert torch.equal(d.c2w, r.c2w)
            ki, kr = d.intrinsics, r.intrinsics
            assert max(abs(a - b) for a, b in zip(ki.as_list(), kr.as_list())) < 1e-6, (fmt, ki, kr)
            assert type(d.focal) is type(r.focal) is float  # a centred camera takes the single-focal path
            for i in range(len(d)):
                for a, b in zip(pixel_rays(d.c2w[i], d.height, d.width, d.focal),
                                pixel_rays(r.c2w[i], r.height, r.width, r.focal)):
                    torch.testing.assert_close(a, b, atol=1e-6, rtol=0)
            # pixels: identical at full size; nerfstudio's 8-bit images_2/ copies are within a rounding step
            atol = 1.01 / 255 if (downscale > 1 and fmt == "nerfstudio") else 1e-6
            torch.testing.assert_close(d.alphas, r.alphas, atol=atol, rtol=0)
            torch.testing.assert_close(d.images, r.images, atol=2 * atol, rtol=0)
            if downscale == 1:  # bit-identical inputs: the fit (deterministic for a seed) is the same too
                assert d.focal == r.focal and torch.equal(d.images, r.images) and torch.equal(d.alphas, r.alphas)
    assert loaded["nerfstudio"]["train"].meta["downscaled_copies"] is (downscale > 1)


def test_render_cameras_agree_across_layouts(layouts):
    ref = load_cameras(layouts["nerf-synthetic"] / "transforms_test.json")
    for fmt in FORMATS:
        name = "transforms_test.json" if fmt == "blendernerf" else "transforms.json"
        cams = load_cameras(layouts[fmt] / name)
        if name == "transforms.json":  # all frames of the single file: pick the test ones
            idx = [i for i, n in enumerate(cams.names) if n.startswith("test_") or
                   (fmt == "nerfstudio" and i >= VIEWS["train"] + VIEWS["val"])]
            cams.c2w = cams.c2w[idx]
        assert torch.equal(cams.c2w, ref.c2w) and (cams.height, cams.width) == (H, W)
        k, kr = intrinsics(cams.focal, H, W), intrinsics(ref.focal, H, W)
        assert max(abs(a - b) for a, b in zip(k.as_list(), kr.as_list())) < 1e-6


def test_make_scene_format_writes_the_layout_from_an_existing_render(tmp_path):
    """`pointgt make-scene NAME --format F --out DIR` reuses the NeRF-synthetic render in DIR (no Blender render)
    and writes DIR/F/; the scene name must match."""
    from tools.cli import main
    from core.images.dataset import load_split

    make_scene(tmp_path)
    (tmp_path / "scene.json").write_text(json.dumps({"format": "pointgt-scene", "name": "crate"}))
    assert main(["make-scene", "crate", "--out", str(tmp_path), "--format", "nerfstudio"]) == 0
    d = load_split(tmp_path / "nerfstudio", "test")
    assert d.layout == "nerfstudio" and torch.equal(d.images, load_split(tmp_path, "test").images)
    assert main(["make-scene", "suzanne", "--out", str(tmp_path), "--format", "blendernerf"]) != 0
    assert not (tmp_path / "blendernerf").exists()
