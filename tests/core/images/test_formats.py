"""The layouts real tools write (nerfstudio, instant-ngp, BlenderNeRF): intrinsics keys at the top or per frame,
distortion refused, masks, keyed backdrops, deterministic splits, downscaled copies — checked against references
written out here."""
import json
import math

import numpy as np
import pytest
import torch
from PIL import Image

from core.images.cameras import Intrinsics, look_at, pixel_rays
from core.images.dataset import load_cameras, load_dataset, load_split, parse_colour
from core.util.errors import DataError, InputError

H, W = 8, 12
K = dict(fl_x=11.0, fl_y=9.5, cx=6.75, cy=3.25)


def _c2w(i: int) -> list:
    a = 2 * math.pi * i / 9
    return look_at((4 * math.cos(a), 4 * math.sin(a), 1.0 + 0.1 * i)).tolist()


def _rgb(i: int, h=H, w=W) -> np.ndarray:
    img = np.random.default_rng(100 + i).integers(0, 256, size=(h, w, 3), dtype=np.uint8)
    img[1, 2] = 0  # one black pixel: the backdrop of the keying test
    return img


def _mask(i: int, h=H, w=W) -> np.ndarray:
    m = np.random.default_rng(200 + i).integers(0, 256, size=(h, w), dtype=np.uint8)
    m[0, 0], m[0, 1] = 0, 255
    return m


def make_nerfstudio(root, n=6, masks=True, per_frame=(), top=None, sub="cam0", ext="png"):
    """A nerfstudio folder: images/<sub>/frame_<i>.<ext> (RGB), masks/<sub>/frame_<i>.png, one transforms.json.
    per_frame: intrinsics keys written into every frame instead of the top."""
    doc = {"camera_model": "OPENCV", "w": W, "h": H, **K, "k1": 0.0, "k2": 0.0, "p1": 0.0, "p2": 0.0,
           "applied_transform": [[1, 0, 0, 0], [0, 0, 1, 0], [0, -1, 0, 0]], **(top or {})}
    for key in per_frame:
        doc.pop(key)
    frames = []
    for i in reversed(range(n)):  # JSON order differs from file order: the split must not depend on it
        (root / "images" / sub).mkdir(parents=True, exist_ok=True)
        Image.fromarray(_rgb(i)).save(root / "images" / sub / f"frame_{i:03d}.{ext}")
        fr = {"file_path": f"images/{sub}/frame_{i:03d}.{ext}", "transform_matrix": _c2w(i)}
        if masks:
            (root / "masks" / sub).mkdir(parents=True, exist_ok=True)
            Image.fromarray(_mask(i)).save(root / "masks" / sub / f"frame_{i:03d}.png")
            fr["mask_path"] = f"masks/{sub}/frame_{i:03d}.png"
        fr.update({key: (W if key == "w" else H if key == "h" else K[key]) for key in per_frame})
        frames.append(fr)
    doc["frames"] = frames
    (root / "transforms.json").write_text(json.dumps(doc))
    return doc


def _edit(root, fn, name="transforms.json"):
    p = root / name
    doc = json.loads(p.read_text())
    fn(doc)
    p.write_text(json.dumps(doc))


def test_nerfstudio_loads_intrinsics_masks_and_a_deterministic_split(tmp_path):
    make_nerfstudio(tmp_path, n=7)
    data = load_dataset(tmp_path, splits=("train", "val", "test"), required=("train", "test"), test_every=3)
    assert set(data) == {"train", "test"}  # no val in a single file without val_filenames
    # reference split: sorted by file_path, every 3rd (starting with the first) is a test view
    order = sorted(range(7), key=lambda i: f"frame_{i:03d}")
    test_ids = [order[j] for j in range(7) if j % 3 == 0]
    train_ids = [order[j] for j in range(7) if j % 3 != 0]
    for split, ids in (("train", train_ids), ("test", test_ids)):
        d = data[split]
        assert [f.name for f in d.files] == [f"frame_{i:03d}.png" for i in ids]
        assert d.layout == "nerfstudio" and (d.height, d.width) == (H, W)
        assert d.intrinsics == Intrinsics(11.0, 9.5, 6.75, 3.25) and d.focal == d.intrinsics
        torch.testing.assert_close(d.c2w, torch.tensor([_c2w(i) for i in ids], dtype=torch.float32))
        for v, i in enumerate(ids):
            a = torch.tensor(_mask(i), dtype=torch.float64) / 255
            rgb = torch.tensor(_rgb(i), dtype=torch.float64) / 255
            torch.testing.assert_close(d.alphas[v].double(), a, atol=1e-7, rtol=0)
            torch.testing.assert_close(d.images[v].double(), rgb * a[..., None] + (1 - a[..., None]),
                                       atol=1e-6, rtol=0)


def test_single_file_split_lists_are_used_when_present(tmp_path):
    make_nerfstudio(tmp_path, n=5)
    _edit(tmp_path, lambda d: d.update(train_filenames=[f"images/cam0/frame_00{i}.png" for i in (4, 1, 2)],
                                       test_filenames=["./images/cam0/frame_000.png"],
                                       val_filenames=["images/cam0/frame_003.png"]))
    data = load_dataset(tmp_path, splits=("train", "val", "test"))
    assert [f.name for f in data["train"].files] == ["frame_004.png", "frame_001.png", "frame_002.png"]
    assert [f.name for f in data["val"].files] == ["frame_003.png"]
    assert [f.name for f in data["test"].files] == ["frame_000.png"]
    _edit(tmp_path, lambda d: d["test_filenames"].append("images/cam0/nope.png"))
    with pytest.raises(DataError, match=r"transforms\.json: 'test_filenames' names 1 image.*nope\.png"):
        load_split(tmp_path, "test")


@pytest.mark.parametrize("keys", [("fl_x", "fl_y", "cx", "cy"), ("fl_x", "w", "h"), ("cy",)])
def test_intrinsics_per_frame_equal_the_same_keys_at_the_top(tmp_path, keys):
    top = tmp_path / "top"
    make_nerfstudio(top)
    per = tmp_path / "per"
    make_nerfstudio(per, per_frame=keys)
    a, b = load_split(top, "train"), load_split(per, "train")
    assert a.intrinsics == b.intrinsics and torch.equal(a.images, b.images)


def test_a_key_missing_at_the_top_must_be_in_every_frame(tmp_path):
    make_nerfstudio(tmp_path, per_frame=("fl_y",))
    _edit(tmp_path, lambda d: d["frames"][2].pop("fl_y"))
    with pytest.raises(DataError, match=r"transforms\.json: frame 2 has no 'fl_y'.*every frame or once at the top"):
        load_split(tmp_path, "train")


def test_missing_focal_names_the_file_and_keys(tmp_path):
    make_nerfstudio(tmp_path)
    _edit(tmp_path, lambda d: d.pop("fl_x"))
    with pytest.raises(DataError, match=r"transforms\.json: frame 0 \(frame_\d+\.png\) has no horizontal "
                                        r"intrinsics: missing 'camera_angle_x'.*'fl_x'"):
        load_split(tmp_path, "train")


def _per_frame_capture(root, extra):
    """A card capture: 5 train + 1 test views through K_REF at 32 x 24, plus one train view per (intrinsics,
    (h, w)) in `extra` with its own per-frame keys. Returns (root, reference train split rendered through K_REF
    for all train views)."""
    from tests.helpers.synthetic import fibonacci_cameras, render_split, write_capture

    cams = fibonacci_cameras(5 + len(extra), seed=2)
    train = render_split("card", cams[:5], 32, height=24, intrinsics=K_REF)
    test = render_split("card", fibonacci_cameras(1, seed=7), 32, height=24, intrinsics=K_REF, split="test")
    own = [render_split("card", cams[5 + j:6 + j], size[1], height=size[0], intrinsics=k, split=f"own{j}")
           for j, (k, size) in enumerate(extra)]
    keys = {f"own{j}": {"fl_x": k.fx, "fl_y": k.fy, "cx": k.cx, "cy": k.cy, "w": size[1], "h": size[0]}
            for j, (k, size) in enumerate(extra)}
    write_capture(root, [train, test, *own], frame_keys=lambda split, i: keys.get(split, {}),
                  top_keys={"train_filenames": [f"images/train_{i}.png" for i in range(5)]
                            + [f"images/own{j}_0.png" for j in range(len(extra))]})
    return root, render_split("card", cams, 32, height=24, intrinsics=K_REF)


K_REF = Intrinsics(30.0, 27.0, 17.5, 12.0)


def test_frames_with_their_own_intrinsics_are_resampled_onto_the_split_camera(tmp_path):
    """Per-frame fl_x/fl_y/cx/cy/w/h: each such frame is resampled onto the camera most frames share, so the
    split is exactly what that camera would have seen: a frame whose camera is the reference camera moved by
    whole pixels (a larger image) resamples to the very same pixels, a zoomed one to within interpolation."""
    shifted = (Intrinsics(30.0, 27.0, 17.5 + 3, 12.0 + 2), (30, 40))  # reference pixels = this image cropped
    zoomed = (Intrinsics(45.0, 40.5, 27.0, 19.0), (40, 52))  # 1.5 x the focal lengths, another centre
    root, ref = _per_frame_capture(tmp_path, [shifted, zoomed])
    d = load_split(root, "train")
    assert d.focal == K_REF and (d.height, d.width) == (24, 32) and len(d) == 7
    assert d.meta["resampled"] == {"frames": 2, "min_coverage": 1.0, "undistorted": 0}
    torch.testing.assert_close(d.images[:5], ref.images[:5], atol=1.5 / 255, rtol=0)  # 8-bit PNGs
    torch.testing.assert_close(d.images[5], ref.images[5], atol=1.5 / 255, rtol=0)
    torch.testing.assert_close(d.alphas[5], ref.alphas[5], atol=1.5 / 255, rtol=0)
    err = (d.images[6] - ref.images[6]).abs()
    assert float(err.mean()) < 0.01 and float((d.alphas[6] - ref.alphas[6]).abs().mean()) < 0.01, float(err.mean())
    # the test split and the camera-only reader get the same camera
    assert load_split(root, "test").focal == K_REF and load_cameras(root / "transforms.json").focal == K_REF
    # --downscale averages the resampled frames
    d2 = load_split(root, "train", downscale=2)
    assert d2.focal == K_REF.scaled(0.5)
    torch.testing.assert_close(d2.alphas, d.alphas.reshape(7, 12, 2, 16, 2).mean((2, 4)), atol=1e-6, rtol=0)


def test_a_frame_that_sees_too_little_of_the_split_camera_is_refused(tmp_path):
    far = (Intrinsics(30.0, 27.0, 40.0, 12.0), (24, 32))  # the principal point 22.5 px further right
    root, _ = _per_frame_capture(tmp_path, [far])
    with pytest.raises(DataError, match=r"transforms\.json: frame own0_0\.png sees only \d+% of the split's camera "
                                        r"view.*crop or remove the frame"):
        load_split(root, "train")


LENS = (-0.25, 0.05, 0.01, 0.003, -0.002)  # k1, k2, k3, p1, p2: barrel, as phone and DSLR wide angles


@pytest.mark.parametrize("where", ["top", "frame"])
def test_opencv_distortion_is_undone_as_the_images_are_read(tmp_path, where):
    """A card seen through a radial-tangential lens (rays bent by the brute-force inverse of the lens) loads as
    the pinhole camera would have seen it; keys at the top or in every frame (instant-ngp) alike."""
    from tests.helpers.synthetic import fibonacci_cameras, render_split, write_capture

    k = Intrinsics(60.0, 56.0, 33.0, 25.0)
    cams = fibonacci_cameras(4, radius=2.0, seed=3)
    seen = render_split("card", cams, 64, height=48, intrinsics=k, lens=LENS)
    pinhole = render_split("card", cams, 64, height=48, intrinsics=k)
    keys = dict(zip(("k1", "k2", "k3", "p1", "p2"), LENS))
    write_capture(tmp_path, [seen], top_keys=keys if where == "top" else {},
                  frame_keys=(lambda split, i: keys) if where == "frame" else None)
    d = load_split(tmp_path, "train")
    assert d.focal == k and d.meta["resampled"] == {"frames": 4, "min_coverage": 1.0, "undistorted": 4}
    # mean error: what is left is bilinear interpolation across the card's anti-aliased edges (the distorted
    # photos themselves are 2.5 x further off)
    err = float((d.images - pinhole.images).abs().mean())
    raw = float((seen.images - pinhole.images).abs().mean())
    assert err < 0.004 and raw > 2 * err, (err, raw)
    a_err = float((d.alphas - pinhole.alphas).abs().mean())
    assert a_err < 0.5 * float((seen.alphas - pinhole.alphas).abs().mean()), a_err
    assert load_cameras(tmp_path / "transforms.json").focal == k  # the undistorted (pinhole) camera


@pytest.mark.parametrize("where", ["top", "frame"])
def test_k4_and_folding_lenses_are_refused_naming_file_and_key(tmp_path, where):
    make_nerfstudio(tmp_path)
    if where == "top":
        _edit(tmp_path, lambda d: d.update(k4=0.01))
        pattern = r"transforms\.json: 'k4' = 0\.01: k4 belongs to the fisheye"
    else:
        _edit(tmp_path, lambda d: [f.update(k4=0.0 if i else -0.02) for i, f in enumerate(d["frames"])])
        pattern = r"transforms\.json: frame \d \(frame_005\.png\): 'k4' = -0\.02: k4 belongs to the fisheye"
    with pytest.raises(DataError, match=pattern):
        load_dataset(tmp_path, splits=("train", "test"), required=("train", "test"))
    make_nerfstudio(tmp_path / "fold")
    _edit(tmp_path / "fold", lambda d: d.update(k1=-2.0))
    with pytest.raises(DataError, match=r"transforms\.json: frame 0 \(frame_\d+\.png\): the distortion k1, k2, k3, "
                                        r"p1, p2 = \[-2\.0, 0\.0, 0\.0, 0\.0, 0\.0\] folds the image over"):
        load_split(tmp_path / "fold")


@pytest.mark.parametrize("model,ok", [("PINHOLE", True), ("SIMPLE_PINHOLE", True), ("OPENCV", True),
                                      ("OPENCV_FISHEYE", False), ("EQUIRECTANGULAR", False)])
def test_camera_models(tmp_path, model, ok):
    make_nerfstudio(tmp_path)
    _edit(tmp_path, lambda d: d.update(camera_model=model))
    if ok:
        assert load_split(tmp_path).intrinsics.fx == 11.0
    else:
        kind = "a fisheye lens" if "FISHEYE" in model else "not a model PointGT reads"
        with pytest.raises(DataError, match=rf"transforms\.json: 'camera_model' is '{model}', {kind}.*undistort"):
            load_split(tmp_path)


def test_masks_all_frames_or_none(tmp_path):
    make_nerfstudio(tmp_path)
    _edit(tmp_path, lambda d: d["frames"][4].pop("mask_path"))
    with pytest.raises(DataError, match=r"transforms\.json: frame \d has a 'mask_path' but frame \d has none"):
        load_dataset(tmp_path, splits=("train", "test"), required=("train", "test"))


def test_images_without_alpha_or_masks_need_a_key(tmp_path):
    make_nerfstudio(tmp_path, masks=False)
    with pytest.raises(DataError, match=r"frame_\d+\.png: the image has no alpha channel and transforms\.json "
                                        r"gives no 'mask_path'.*--background-colour R,G,B"):
        load_split(tmp_path)
    d = load_split(tmp_path, background_colour=parse_colour("0,0,0"))
    assert torch.all(d.alphas[:, 1, 2] == 0) and float(d.alphas.mean()) > 0.9  # the black pixel, not the rest


def test_parse_colour():
    assert parse_colour("1,0.5,0") == (1.0, 0.5, 0.0)
    assert parse_colour("255,0,51") == (1.0, 0.0, 0.2)
    for bad in ("1,2", "a,b,c", "-1,0,0", "300,0,0", "nan,0,0"):
        with pytest.raises(InputError, match="--background-colour"):
            parse_colour(bad)


def test_jpeg_images_with_their_extension(tmp_path):
    make_nerfstudio(tmp_path, ext="jpg")
    d = load_split(tmp_path)
    assert d.files[0].suffix == ".jpg" and d.images.shape[1:] == (H, W, 3)


def test_downscaled_copies_are_picked_and_intrinsics_scaled(tmp_path):
    make_nerfstudio(tmp_path, n=4)
    full = load_split(tmp_path, "train", downscale=2)  # no copies yet: area average
    assert full.meta["downscaled_copies"] is False and (full.height, full.width) == (H // 2, W // 2)
    assert full.intrinsics == Intrinsics(5.5, 4.75, 3.375, 1.625)
    for folder in ("images_2", "masks_2"):
        (tmp_path / folder / "cam0").mkdir(parents=True)
    for i in range(4):  # copies with recognisable content: a flat grey and a full mask
        Image.fromarray(np.full((H // 2, W // 2, 3), 77, np.uint8)).save(tmp_path / f"images_2/cam0/frame_{i:03d}.png")
        Image.fromarray(np.full((H // 2, W // 2), 255, np.uint8)).save(tmp_path / f"masks_2/cam0/frame_{i:03d}.png")
    d = load_split(tmp_path, "train", downscale=2)
    assert d.meta["downscaled_copies"] is True and d.intrinsics == full.intrinsics
    assert torch.all(d.alphas == 1) and torch.allclose(d.images, torch.full_like(d.images, 77 / 255))
    Image.fromarray(np.zeros((3, 3, 3), np.uint8)).save(tmp_path / "images_2/cam0/frame_001.png")
    with pytest.raises(DataError, match=r"frame_001\.png: downscaled copy is 3x3.*regenerate the cam0/ folder"):
        load_split(tmp_path, "train", downscale=2, test_every=4)


def test_off_centre_non_square_rays_go_through_the_pixels_they_came_from(tmp_path):
    """End to end: rays of the loaded camera hit their pixel centres under the brute-force pinhole formula."""
    make_nerfstudio(tmp_path)
    d = load_split(tmp_path)
    c2w = d.c2w[0].double()
    o, dirs = pixel_rays(c2w, d.height, d.width, d.focal)
    for r in range(d.height):
        for c in range(d.width):
            rel = o[r, c] + 3.0 * dirs[r, c] - c2w[:3, 3]
            x, y, z = (float(rel @ c2w[:3, i]) for i in range(3))
            assert K["fl_x"] * x / -z + K["cx"] == pytest.approx(c + 0.5, abs=1e-5)  # c2w is float32
            assert K["fl_y"] * -y / -z + K["cy"] == pytest.approx(r + 0.5, abs=1e-5)


def test_instant_ngp_aabb_scale_and_per_frame_intrinsics(tmp_path):
    make_nerfstudio(tmp_path, per_frame=("fl_x", "fl_y", "cx", "cy", "w", "h"),
                    top={"aabb_scale": 16})
    _edit(tmp_path, lambda d: [d.pop(k) for k in ("camera_model", "applied_transform")])
    d = load_split(tmp_path)
    assert d.layout == "instant-ngp" and d.meta["aabb_scale"] == 16 and d.intrinsics.fy == 9.5
    _edit(tmp_path, lambda d: d.update(aabb_scale=3))
    with pytest.raises(DataError, match=r"'aabb_scale' must be a power of two"):
        load_split(tmp_path)
    _edit(tmp_path, lambda d: d.update(aabb_scale=1, is_fisheye=True))
    with pytest.raises(DataError, match=r"'is_fisheye' is true"):
        load_split(tmp_path)


def test_fields_of_view_on_both_axes(tmp_path):
    make_nerfstudio(tmp_path)
    _edit(tmp_path, lambda d: [d.pop(k) for k in ("fl_x", "fl_y", "cx", "cy")] and
          d.update(camera_angle_x=0.9, camera_angle_y=0.7))
    k = load_split(tmp_path).intrinsics
    assert k.fx == pytest.approx(0.5 * W / math.tan(0.45)) and k.fy == pytest.approx(0.5 * H / math.tan(0.35))
    assert (k.cx, k.cy) == (W / 2, H / 2)


def test_w_h_must_match_the_images(tmp_path):
    make_nerfstudio(tmp_path)
    _edit(tmp_path, lambda d: d.update(w=W + 2))
    with pytest.raises(DataError, match=r"transforms\.json: 'w' is 14 but frame_\d+\.png is 12x8"):
        load_split(tmp_path)


def test_load_cameras_reads_intrinsics_and_scales_them_to_a_size(tmp_path):
    make_nerfstudio(tmp_path)
    cams = load_cameras(tmp_path / "transforms.json")
    assert (cams.height, cams.width) == (H, W) and cams.focal == Intrinsics(11.0, 9.5, 6.75, 3.25)
    cams = load_cameras(tmp_path / "transforms.json", size=24)
    assert (cams.height, cams.width) == (16, 24) and cams.focal == Intrinsics(22.0, 19.0, 13.5, 6.5)
    assert len(cams.names) == 6


def test_progress_prints_the_memory_estimate(tmp_path, capsys):
    make_nerfstudio(tmp_path)
    load_split(tmp_path, progress=True)
    err = capsys.readouterr().err
    assert "transforms.json: 5 images of 12x8, about" in err and "MiB" in err


@pytest.mark.parametrize("key,value,pattern", [("fl_x", 1e-6, "'fl_x' = 1e-06 pixels is implausible"),
                                               ("fl_y", 1e12, "'fl_y' = 1e\\+12 pixels is implausible"),
                                               ("cx", -1e6, "'cx' = -1e\\+06 pixels lies far outside"),
                                               ("cy", 1e9, "'cy' = 1e\\+09 pixels lies far outside")])
def test_implausible_intrinsics_are_refused(tmp_path, key, value, pattern):
    make_nerfstudio(tmp_path)
    _edit(tmp_path, lambda d: d.update({key: value}))
    with pytest.raises(DataError, match=r"transforms\.json: " + pattern):
        load_split(tmp_path)


@pytest.mark.parametrize("scale", [1e-3, 1e5])
def test_rays_stay_finite_at_the_accepted_extremes(tmp_path, scale):
    """The widest and narrowest accepted cameras, principal point at the far edge of the accepted range."""
    side = max(H, W)
    make_nerfstudio(tmp_path)
    _edit(tmp_path, lambda d: d.update(fl_x=scale * side, fl_y=scale * side, cx=-10.0 * W, cy=11.0 * H))
    d = load_split(tmp_path)
    for dtype in (torch.float32, torch.float64):
        o, dirs = pixel_rays(d.c2w[0].to(dtype), d.height, d.width, d.focal)
        assert torch.isfinite(dirs).all() and torch.allclose(dirs.norm(dim=-1), torch.ones((), dtype=dtype))


def test_memory_estimate_counts_the_downscaled_split(tmp_path, monkeypatch):
    """Each image is reduced as it is read: a split too large for memory at full size loads with --downscale."""
    import os

    from core.images import dataset

    make_nerfstudio(tmp_path, n=6)  # 5 train views of 12 x 8
    decode = H * W * 16 * min(4, os.cpu_count() or 1)  # full-size decode buffers, one per reader thread
    monkeypatch.setattr(dataset, "_memory_limit", lambda: 5 * (H // 2) * (W // 2) * 16 + decode)
    with pytest.raises(DataError, match=r"transforms\.json: 5 images of 12x8 need .* use fewer frames or --downscale"):
        load_split(tmp_path)
    assert load_split(tmp_path, downscale=2).images.shape == (5, H // 2, W // 2, 3)
