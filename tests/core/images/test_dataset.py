import json
import math
import time

import numpy as np
import pytest
import torch
from PIL import Image

from core.images.cameras import look_at
from core.images.dataset import load_dataset, load_split
from core.util.errors import DataError, InputError

FOV = 0.69


def _c2w(i: int) -> list:
    a = 2 * math.pi * i / 7
    return look_at((4 * math.cos(a), 4 * math.sin(a), 1.0 + 0.1 * i)).tolist()


def _rgba(i: int, h: int, w: int) -> np.ndarray:
    rng = np.random.default_rng(i)
    img = rng.integers(0, 256, size=(h, w, 4), dtype=np.uint8)
    img[0, 0, 3], img[0, 1, 3] = 0, 255  # fully transparent and fully opaque pixels are present
    return img


def make_dataset(root, splits=(("train", 3), ("test", 2)), h=8, w=12, ext=False, channels=4):
    """A tiny NeRF-synthetic folder; returns {split: list of uint8 images [H, W, C]}."""
    out = {}
    for split, n in splits:
        (root / split).mkdir(parents=True, exist_ok=True)
        frames, imgs = [], []
        for i in range(n):
            img = _rgba(hash((split, i)) % 1000, h, w)[..., :channels]
            Image.fromarray(img).save(root / split / f"r_{i}.png")
            frames.append({"file_path": f"./{split}/r_{i}" + (".png" if ext else ""), "rotation": 0.1,
                           "transform_matrix": _c2w(i)})
            imgs.append(img)
        (root / f"transforms_{split}.json").write_text(json.dumps({"camera_angle_x": FOV, "frames": frames}))
        out[split] = imgs
    return out


def _edit_json(root, split, fn):
    p = root / f"transforms_{split}.json"
    doc = json.loads(p.read_text())
    fn(doc)
    p.write_text(json.dumps(doc))


@pytest.mark.parametrize("ext", [False, True])
def test_loads_images_alpha_cameras_and_focal(tmp_path, ext):
    imgs = make_dataset(tmp_path, ext=ext)
    d = load_split(tmp_path, "train", background=(0.2, 0.4, 0.6))
    assert d.images.shape == (3, 8, 12, 3) and d.alphas.shape == (3, 8, 12) and d.c2w.shape == (3, 4, 4)
    assert d.images.dtype == d.alphas.dtype == d.c2w.dtype == torch.float32
    assert (d.height, d.width, d.split, len(d)) == (8, 12, "train", 3)
    assert d.focal == pytest.approx(0.5 * 12 / math.tan(0.5 * FOV))
    assert [f.name for f in d.files] == ["r_0.png", "r_1.png", "r_2.png"]
    raw = torch.tensor(np.stack(imgs["train"]), dtype=torch.float64) / 255.0
    a = raw[..., 3]
    expect = raw[..., :3] * a[..., None] + torch.tensor([0.2, 0.4, 0.6], dtype=torch.float64) * (1 - a[..., None])
    torch.testing.assert_close(d.images.double(), expect, atol=1e-6, rtol=0)
    torch.testing.assert_close(d.alphas.double(), a, atol=1e-7, rtol=0)
    torch.testing.assert_close(d.c2w, torch.tensor([_c2w(i) for i in range(3)], dtype=torch.float32))


def test_rgb_images_without_masks_are_refused_never_silently_opaque(tmp_path):
    make_dataset(tmp_path, channels=3)
    with pytest.raises(DataError, match=r"r_0\.png: the image has no alpha channel.*'mask_path'.*--background-colour"):
        load_split(tmp_path, "test")


def test_background_colour_keys_out_a_studio_backdrop(tmp_path):
    imgs = make_dataset(tmp_path, channels=3)
    key = imgs["test"][0][2, 3] / 255.0  # one pixel's colour is the "backdrop"
    d = load_split(tmp_path, "test", background=(0.0, 0.0, 0.0), background_colour=tuple(key))
    for v, img in enumerate(imgs["test"]):
        raw = torch.tensor(img, dtype=torch.float64) / 255.0
        near = (raw - torch.tensor(key)).abs().max(dim=-1).values <= 0.04  # brute force, pixel by pixel
        assert torch.equal(d.alphas[v] == 0, near) and torch.all((d.alphas[v] == 0) | (d.alphas[v] == 1))
        assert torch.all(d.images[v][near] == 0)  # keyed pixels take the composite background
    assert float(d.alphas[0, 2, 3]) == 0.0


def _reference_downscale(rgba: torch.Tensor, k: int, bg) -> tuple[torch.Tensor, torch.Tensor]:
    """Brute force, one output pixel at a time: mean of premultiplied colour and of alpha over k x k blocks."""
    v, h, w, _ = rgba.shape
    out = torch.zeros(v, h // k, w // k, 3, dtype=torch.float64)
    alpha = torch.zeros(v, h // k, w // k, dtype=torch.float64)
    for n in range(v):
        for r in range(h // k):
            for c in range(w // k):
                block = rgba[n, r * k:(r + 1) * k, c * k:(c + 1) * k].reshape(-1, 4)
                a = block[:, 3].mean()
                out[n, r, c] = (block[:, :3] * block[:, 3:]).mean(0) + torch.tensor(bg) * (1 - a)
                alpha[n, r, c] = a
    return out, alpha


@pytest.mark.parametrize("k", [2, 4])
def test_downscale_matches_brute_force_area_average(tmp_path, k):
    imgs = make_dataset(tmp_path, h=8, w=12)
    d = load_split(tmp_path, "train", downscale=k, background=(1.0, 0.5, 0.0))
    ref, ref_a = _reference_downscale(torch.tensor(np.stack(imgs["train"]), dtype=torch.float64) / 255, k,
                                      (1.0, 0.5, 0.0))
    assert (d.height, d.width) == (8 // k, 12 // k)
    assert d.focal == pytest.approx(0.5 * (12 // k) / math.tan(0.5 * FOV))
    torch.testing.assert_close(d.images.double(), ref, atol=1e-6, rtol=0)
    torch.testing.assert_close(d.alphas.double(), ref_a, atol=1e-6, rtol=0)


def test_downscale_has_no_dark_fringe(tmp_path):
    # Opaque red next to transparent black: on white the edge pixel must be (1, .5, .5), not a darker red.
    (tmp_path / "train").mkdir()
    img = np.zeros((2, 2, 4), np.uint8)
    img[:, 0] = (255, 0, 0, 255)
    Image.fromarray(img).save(tmp_path / "train" / "r_0.png")
    (tmp_path / "transforms_train.json").write_text(json.dumps(
        {"camera_angle_x": FOV, "frames": [{"file_path": "./train/r_0", "transform_matrix": _c2w(0)}]}))
    d = load_split(tmp_path, downscale=2)
    torch.testing.assert_close(d.images[0, 0, 0], torch.tensor([1.0, 0.5, 0.5]))
    assert float(d.alphas[0, 0, 0]) == pytest.approx(0.5)


def test_load_dataset_skips_absent_optional_splits(tmp_path):
    make_dataset(tmp_path)
    data = load_dataset(tmp_path)
    assert sorted(data) == ["test", "train"] and len(data["test"]) == 2
    with pytest.raises(DataError, match=r"transforms_val\.json.*not found.*transforms_test\.json"):
        load_dataset(tmp_path, required=("train", "val"))
    with pytest.raises(InputError, match="required"):
        load_dataset(tmp_path, splits=("test",))


def test_auxiliary_depth_and_normal_images_are_ignored(tmp_path):
    make_dataset(tmp_path)
    for name in ("r_0_depth_0000.png", "r_0_normal_0000.png"):
        Image.new("L", (3, 3)).save(tmp_path / "test" / name)
    assert len(load_split(tmp_path, "test")) == 2


def test_images_shared_between_splits_are_not_extra(tmp_path):
    make_dataset(tmp_path, splits=(("train", 3),))
    (tmp_path / "transforms_val.json").write_text(json.dumps(
        {"camera_angle_x": FOV, "frames": [{"file_path": "./train/r_2", "transform_matrix": _c2w(2)}]}))
    _edit_json(tmp_path, "train", lambda doc: doc["frames"].pop())
    assert len(load_split(tmp_path, "train")) == 2 and len(load_split(tmp_path, "val")) == 1


def _scaled(doc):
    doc["frames"][1]["transform_matrix"] = (np.array(_c2w(1)) @ np.diag([2.0, 2.0, 2.0, 1.0])).tolist()


def _reflected(doc):
    doc["frames"][2]["transform_matrix"] = (np.array(_c2w(2)) @ np.diag([1.0, 1.0, -1.0, 1.0])).tolist()


def _sheared(doc):
    m = np.array(_c2w(1))
    m[:3, 0] += 0.1 * m[:3, 1]
    doc["frames"][1]["transform_matrix"] = m.tolist()


def _last_row(doc):
    doc["frames"][0]["transform_matrix"][3] = [0, 0, 1, 1]


def _nan_matrix(doc):
    doc["frames"][0]["transform_matrix"][0][1] = float("nan")


BAD_JSON = [
    ("no angle", lambda d: d.pop("camera_angle_x"), r"missing 'camera_angle_x'"),
    ("nan angle", lambda d: d.update(camera_angle_x=float("nan")), "camera_angle_x"),
    ("zero angle", lambda d: d.update(camera_angle_x=0), "camera_angle_x"),
    ("negative angle", lambda d: d.update(camera_angle_x=-0.5), "camera_angle_x"),
    ("degrees", lambda d: d.update(camera_angle_x=40.0), "degrees"),
    ("pi", lambda d: d.update(camera_angle_x=math.pi), "camera_angle_x"),
    ("string angle", lambda d: d.update(camera_angle_x="0.6"), "camera_angle_x"),
    ("no frames", lambda d: d.pop("frames"), "missing 'frames'"),
    ("empty frames", lambda d: d.update(frames=[]), "'frames' is empty"),
    ("frame not object", lambda d: d["frames"].append([1, 2]), "frame 3 is a list"),
    ("no file_path", lambda d: d["frames"][1].pop("file_path"), "frame 1 has no 'file_path'"),
    ("no matrix", lambda d: d["frames"][2].pop("transform_matrix"), "frame 2 has no 'transform_matrix'"),
    ("file_path not str", lambda d: d["frames"][0].update(file_path=3), "'file_path' must be a non-empty string"),
    ("image missing", lambda d: d["frames"][1].update(file_path="./train/r_9"), r"frame 1: image not found.*r_9\.png"),
    ("duplicate", lambda d: d["frames"][2].update(file_path="./train/r_0.png"), "same image as frame 0"),
    ("3x4", lambda d: d["frames"][0]["transform_matrix"].pop(), r"must be 4x4, got shape \(3, 4\)"),
    ("ragged", lambda d: d["frames"][0]["transform_matrix"][1].pop(), "4x4 list of numbers"),
    ("strings", lambda d: d["frames"][0]["transform_matrix"][1].__setitem__(0, "x"), "4x4 list of numbers"),
    ("nan matrix", _nan_matrix, "NaN/inf"),
    # finite in float64 but inf in the float32 cameras (found by mutating a scene's transforms file)
    ("far camera", lambda d: d["frames"][1]["transform_matrix"][0].__setitem__(3, 1e300),
     r"frame 1 \(r_1\.png\).*farther than 1e\+15 units"),
    ("scaled", _scaled, r"frame 1 \(r_1\.png\).*not orthonormal"),
    ("sheared", _sheared, r"frame 1 .*not orthonormal"),
    ("reflection", _reflected, r"frame 2 .*reflection"),
    ("last row", _last_row, r"frame 0 .*last row"),
]


@pytest.mark.parametrize("edit,pattern", [b[1:] for b in BAD_JSON], ids=[b[0] for b in BAD_JSON])
def test_bad_transforms_are_rejected_with_file_and_problem(tmp_path, edit, pattern):
    make_dataset(tmp_path)
    _edit_json(tmp_path, "train", edit)
    with pytest.raises(DataError, match=pattern) as err:
        load_split(tmp_path, "train")
    assert "transforms_train.json" in str(err.value) or "r_" in str(err.value)


def test_missing_and_unparseable_json(tmp_path):
    with pytest.raises(DataError, match="dataset folder not found"):
        load_split(tmp_path / "nowhere")
    with pytest.raises(DataError, match=r"transforms_train\.json: split file not found.*no transforms"):
        load_split(tmp_path)
    (tmp_path / "transforms_train.json").write_text('{"camera_angle_x": 0.6, "frames": [}')
    with pytest.raises(DataError, match=r"transforms_train\.json: invalid JSON at line 1, column"):
        load_split(tmp_path)
    (tmp_path / "transforms_train.json").write_text("[1, 2]")
    with pytest.raises(DataError, match="expected a JSON object"):
        load_split(tmp_path)
    (tmp_path / "transforms_train.json").write_bytes(b"\xff\xfe\x00garbage")
    with pytest.raises(DataError, match="not UTF-8"):
        load_split(tmp_path)


def test_extra_png_in_split_folder_is_rejected_unless_allowed(tmp_path):
    make_dataset(tmp_path)
    Image.new("RGBA", (12, 8)).save(tmp_path / "train" / "stray.png")
    with pytest.raises(DataError, match=r"1 PNG\(s\) in .*train are not referenced by any frame: stray\.png"):
        load_split(tmp_path, "train")
    assert len(load_split(tmp_path, "train", check_extra_files=False)) == 3


def test_mixed_sizes_corrupt_images_and_bad_downscale(tmp_path):
    make_dataset(tmp_path)
    with pytest.raises(DataError, match=r"12x8, which downscale=5 does not divide; use one of \[2, 4\]"):
        load_split(tmp_path, downscale=5)
    for bad in (0, -2, 1.5, True):
        with pytest.raises(InputError, match="downscale"):
            load_split(tmp_path, downscale=bad)
    with pytest.raises(InputError, match="background"):
        load_split(tmp_path, background=(1.0, 2.0, 0.0))
    Image.new("RGBA", (12, 10)).save(tmp_path / "train" / "r_1.png")
    with pytest.raises(DataError, match=r"r_1\.png: image is 12x10 but r_0\.png is 12x8"):
        load_split(tmp_path)
    (tmp_path / "train" / "r_1.png").write_bytes((tmp_path / "train" / "r_0.png").read_bytes()[:60])
    with pytest.raises(DataError, match=r"r_1\.png.*truncated or corrupt"):
        load_split(tmp_path)


def test_eighty_128px_images_load_well_under_a_second(tmp_path):
    make_dataset(tmp_path, splits=(("train", 80),), h=128, w=128)
    times = []
    for _ in range(3):  # best of three: the machine may be shared
        t0 = time.perf_counter()
        d = load_split(tmp_path, "train")
        times.append(time.perf_counter() - t0)
    elapsed = min(times)
    print(f"\nload_split: 80 RGBA PNGs of 128x128 in {elapsed:.3f} s (best of 3)")
    assert d.images.shape == (80, 128, 128, 3)
    assert elapsed < 1.0
