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
    (tmp_path / "scene.json").write_text(json.dumps({  # the parts of a scene description every reader checks
        "format": "pointgt-scene", "name": "crate", "bbox": {"center": [0, 0, 0], "half_size": [1, 1, 1]},
        "texture": {"params": {}}, "poses": {"rest": {"type": "rest"}}}))
    assert main(["make-scene", "crate", "--out", str(tmp_path), "--format", "nerfstudio"]) == 0
    d = load_split(tmp_path / "nerfstudio", "test")
    assert d.layout == "nerfstudio" and torch.equal(d.images, load_split(tmp_path, "test").images)
    assert main(["make-scene", "suzanne", "--out", str(tmp_path), "--format", "blendernerf"]) != 0
    assert not (tmp_path / "blendernerf").exists()


def test_the_same_scene_fits_the_same_from_nerf_synthetic_and_nerfstudio(tmp_path):
    """Identical cameras and pixels give the identical (seeded) fit: the trained points match bit for bit."""
    from core.bundle import load_bundle
    from tests.helpers.synthetic import fibonacci_cameras, render_split, write_split
    from tools.cli import main

    src = tmp_path / "nerf-synthetic"
    write_split(src, render_split("card", fibonacci_cameras(5, seed=0), 20))
    write_split(src, render_split("card", fibonacci_cameras(2, seed=5), 20, split="test"))
    write_layout(src, tmp_path / "nerfstudio", "nerfstudio", log=lambda m: None)
    models = []
    for fmt in ("nerf-synthetic", "nerfstudio"):
        out = tmp_path / f"{fmt}.pgt"
        assert main(["fit", str(tmp_path / fmt), "--out", str(out), "--stage", "papr", "--steps", "8",
                     "--points", "200", "--eval-views", "1", "--no-profile", "--no-progress", "--device", "cpu",
                     "--threads", "1"]) == 0
        models.append(load_bundle(out, "cpu").model)
    assert torch.equal(models[0].xyz, models[1].xyz)


def test_fit_and_eval_on_an_off_centre_non_square_capture(tmp_path, capsys):
    """A nerfstudio capture whose camera has fx != fy and an off-centre principal point trains and evaluates
    with those intrinsics (stored in the model), and its hull points project onto the object in every view."""
    from core.bundle import load_bundle
    from core.images.cameras import Intrinsics, project_points
    from core.images.dataset import load_split
    from core.points.init import visual_hull_points
    from tests.helpers.synthetic import fibonacci_cameras, render_split, write_split
    from tools.cli import main

    k = Intrinsics(30.0, 28.0, 15.5, 9.2)  # 28 x 20 image: principal point 1.5 px right, 0.8 px up of centre
    root = tmp_path / "capture"
    splits = {s: render_split("sphere", fibonacci_cameras(n, seed=seed), 28, height=20, intrinsics=k, split=s)
              for s, n, seed in (("train", 6, 0), ("test", 2, 5))}
    frames, names = [], {}
    for s, d in splits.items():
        write_split(root, d)
        doc = json.loads((root / f"transforms_{s}.json").read_text())
        (root / f"transforms_{s}.json").unlink()
        names[f"{s}_filenames"] = [f["file_path"] + ".png" for f in doc["frames"]]
        frames += [{**f, "file_path": f["file_path"] + ".png"} for f in doc["frames"]]
    (root / "transforms.json").write_text(json.dumps({"camera_model": "PINHOLE", "fl_x": k.fx, "fl_y": k.fy,
                                                      "cx": k.cx, "cy": k.cy, "w": 28, "h": 20,
                                                      "frames": frames, **names}))
    train = load_split(root, "train")
    assert train.focal == k and (train.height, train.width) == (20, 28)
    torch.testing.assert_close(train.alphas, splits["train"].alphas, atol=1 / 255, rtol=0)
    pts = visual_hull_points(train.alphas, train.c2w, train.focal, 300)
    near = pts[pts.norm(dim=1) < 0.75]  # the hull points on the object (radius 0.7) ...
    assert near.shape[0] > 40

    def on_silhouette(cam) -> float:
        hits = []
        for i in range(len(train)):
            px, _ = project_points(near, train.c2w[i], 20, 28, cam)
            cols, rows = px[:, 0].floor().long().clamp(0, 27), px[:, 1].floor().long().clamp(0, 19)
            hits.append((train.alphas[i][rows, cols] > 0).float())
        return float(torch.cat(hits).mean())
    print(f"on the silhouette: {on_silhouette(k):.3f} loaded intrinsics, {on_silhouette(k.fx):.3f} centred")
    # ... fall on its silhouette in every view under the loaded intrinsics, not under a centred camera
    assert on_silhouette(k) > 0.97 and on_silhouette(k.fx) < on_silhouette(k) - 0.02
    out = tmp_path / "m.pgt"
    assert main(["fit", str(root), "--out", str(out), "--stage", "papr", "--steps", "8", "--points", "200",
                 "--eval-views", "1", "--no-profile", "--no-progress", "--device", "cpu", "--threads", "1"]) == 0
    assert load_bundle(out, "cpu").meta["scene"]["intrinsics"] == {"fx": 30.0, "fy": 28.0, "cx": 15.5, "cy": 9.2}
    assert main(["eval", str(out), str(root), "--device", "cpu", "--json", str(tmp_path / "e.json")]) == 0
    report = json.loads((tmp_path / "e.json").read_text())
    assert report["views"] == 2 and (report["width"], report["height"]) == (28, 20)
    assert all(math.isfinite(v["psnr"]) for v in report["per_view"])


def test_fit_names_the_way_out_for_photos_without_masks_and_checks_the_flags_first(tmp_path, capsys):
    """RGB photos without mask_path stop `pointgt fit` with the three ways out; a bad --background-colour or
    --test-every is refused before anything is read."""
    from tools.cli import main

    src = make_scene(tmp_path / "nerf-synthetic")
    write_layout(src, tmp_path / "ns", "nerfstudio", log=lambda m: None)
    doc = json.loads((tmp_path / "ns" / "transforms.json").read_text())
    for f in doc["frames"]:
        f.pop("mask_path")
    (tmp_path / "ns" / "transforms.json").write_text(json.dumps(doc))
    base = ["fit", str(tmp_path / "ns"), "--out", str(tmp_path / "m.pgt"), "--steps", "2", "--no-progress"]
    assert main(base) == 2
    err = capsys.readouterr().err
    assert "has no alpha channel" in err and "'mask_path'" in err and "--background-colour R,G,B" in err
    assert main(base + ["--background-colour", "1,2"]) == 2
    assert "--background-colour must be three" in capsys.readouterr().err
    assert main(base + ["--test-every", "1"]) == 2
    assert "--test-every must be at least 2" in capsys.readouterr().err
    assert not (tmp_path / "m.pgt").exists()
