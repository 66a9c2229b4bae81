"""Bad input files the project reads, beyond the per-format tests (tests/core/modelfile, tests/core/images):
point files (.npy) and painted atlas images as `pointgt render` reads them, model files whose container is valid
but whose content is not, and failures in the middle of a save (the old file survives, no temp file is left)."""
import argparse
import json
import os
import pickle

import numpy as np
import pytest
import torch
from PIL import Image

from core.bundle import load_bundle, save_bundle
from core.modelfile import pgt
from core.modelfile.pgt import save_pgt
from core.points.checkpoint import model_to_arrays
from core.util import atomic
from core.util.errors import DataError, InputError, ModelFileError, PointGTError
from tests.helpers.tiny import tiny_bundle
from tools.commands import render as render_cmd

pytestmark = pytest.mark.stability


@pytest.fixture(scope="module")
def saved(tmp_path_factory):
    """(folder, model path, cameras JSON path, bundle): the tiny model saved, one 16 px camera."""
    bundle, _, test = tiny_bundle("fast")
    root = tmp_path_factory.mktemp("files")
    model = root / "m.pgt"
    save_bundle(model, bundle)
    cams = root / "cams.json"
    cams.write_text(json.dumps({"camera_angle_x": float(test.camera_angle_x),
                                "frames": [{"file_path": "./view", "transform_matrix": test.c2w[0].tolist()}]}))
    return root, model, cams, bundle


def _render(saved, tmp_path, **kw):
    root, model, cams, _ = saved
    p = argparse.ArgumentParser()
    render_cmd.add_arguments(p)
    argv = [str(model), "--cameras", str(cams), "--out", str(tmp_path / "out"), "--size", "16", "--device", "cpu"]
    for k, v in kw.items():
        argv += [f"--{k}", str(v)]
    return render_cmd.run(p.parse_args(argv))


# ------------------------------------------------------------------------------------------------ point files
class _Marker:
    """Unpickling this would create a file: proof that code ran."""

    def __init__(self, path):
        self.path = str(path)

    def __reduce__(self):
        return (open, (self.path, "w"))


def _npy_cases(tmp_path, n):
    good = np.zeros((n, 3), np.float32)
    cases = {}

    def put(name, arr=None, raw=None, **save_kw):
        p = tmp_path / name
        if raw is not None:
            p.write_bytes(raw)
        else:
            np.save(p, arr, **save_kw)
        cases[name] = p

    put("shape_n4.npy", np.zeros((n, 4), np.float32))
    put("shape_flat.npy", np.zeros(n * 3, np.float32))
    put("ints.npy", np.zeros((n, 3), np.int32))
    put("bools.npy", np.zeros((n, 3), bool))
    put("complex.npy", np.zeros((n, 3), np.complex64))
    put("objects.npy", np.array([_Marker(tmp_path / "pwned")] * 3, dtype=object), allow_pickle=True)
    put("pickle.npy", raw=pickle.dumps(good))
    put("truncated.npy", raw=(lambda b: b[: len(b) // 2])(_npy_bytes(good)))
    put("text.npy", raw=b"0 0 0\n1 1 1\n")
    put("empty.npy", raw=b"")
    np.savez(tmp_path / "archive.npz", good)
    (tmp_path / "archive.npz").rename(tmp_path / "archive.npy")
    cases["archive.npy"] = tmp_path / "archive.npy"
    return cases


def _npy_bytes(arr):
    import io

    buf = io.BytesIO()
    np.save(buf, arr)
    return buf.getvalue()


def test_bad_point_files_are_clear_errors_and_never_run_code(saved, tmp_path):
    n = saved[3].model.num_points
    for name, path in _npy_cases(tmp_path, n).items():
        with pytest.raises(InputError) as err:
            render_cmd.load_npy(path, "--points", "points")
        assert str(path) in str(err.value), name
    assert not (tmp_path / "pwned").exists()


def test_bad_id_files(saved, tmp_path):
    n = saved[3].model.num_points
    for arr, pattern in ((np.zeros((n, 1), np.int64), "shape"), (np.zeros(n, np.float32), "integers"),
                         (np.zeros(n, bool), "integers")):
        np.save(tmp_path / "ids.npy", arr)
        with pytest.raises(InputError, match=pattern) as err:
            render_cmd.load_npy(tmp_path / "ids.npy", "--ids", "ids")
        assert "ids.npy" in str(err.value)


def test_point_file_problems_through_the_render_command_name_the_file(saved, tmp_path):
    n = saved[3].model.num_points
    np.save(tmp_path / "few.npy", np.zeros((n - 1, 3), np.float32))  # valid file, wrong count for this model
    with pytest.raises(InputError, match=r"few\.npy") as err:
        _render(saved, tmp_path, points=tmp_path / "few.npy")
    assert "ids" in str(err.value)
    assert not (tmp_path / "out").exists() or not any((tmp_path / "out").iterdir())


def test_nan_points_in_a_file_render_a_finite_frame(saved, tmp_path):
    xyz = saved[3].model.xyz.detach().numpy().copy()
    xyz[::3] = np.nan
    xyz[1::7] = np.inf
    np.save(tmp_path / "p.npy", xyz)
    assert _render(saved, tmp_path, points=tmp_path / "p.npy", json=tmp_path / "s.json") == 0
    summary = json.loads((tmp_path / "s.json").read_text())
    assert summary["non_finite_points"] == int((~np.isfinite(xyz).all(1)).sum())
    from core.images.png import read_png

    img = read_png(tmp_path / "out" / "view.png")
    assert np.isfinite(img).all() and img.min() >= 0 and img.max() <= 1


def test_points_all_non_finite_are_refused_and_some_are_named(saved, tmp_path, capsys):
    """Every position NaN / inf: nothing could show, so the render is refused before a frame is written; some
    of them: a warning names how many are left out, and the frames render."""
    from core.util.errors import InputError

    xyz = saved[3].model.xyz.detach().numpy().copy()
    np.save(tmp_path / "none.npy", np.full_like(xyz, np.nan))
    with pytest.raises(InputError, match="every one of the .* positions is NaN or infinite"):
        _render(saved, tmp_path, points=tmp_path / "none.npy")
    assert not (tmp_path / "out").exists()
    xyz[:5] = np.inf
    np.save(tmp_path / "some.npy", xyz)
    assert _render(saved, tmp_path, points=tmp_path / "some.npy") == 0
    assert f"5 of {len(xyz)} points" in capsys.readouterr().err


def test_cameras_that_see_nothing_are_an_error_and_some_empty_frames_a_warning(saved, tmp_path, capsys):
    """A render where no frame covers a pixel of the object is an error the user hears about (the frames are
    still written, and the JSON summary counts them); some empty frames are named in a warning."""
    from core.util.errors import InputError

    root, model, cams, _ = saved
    meta = json.loads(cams.read_text())
    away = json.loads(json.dumps(meta))
    for f in away["frames"]:
        f["transform_matrix"][0][3] += 1e4  # every camera moved far to the side, looking past the object
    (tmp_path / "away.json").write_text(json.dumps(away))
    p = argparse.ArgumentParser()
    render_cmd.add_arguments(p)
    argv = [str(model), "--cameras", str(tmp_path / "away.json"), "--out", str(tmp_path / "out"), "--size", "16",
            "--device", "cpu", "--json", str(tmp_path / "s.json")]
    with pytest.raises(InputError, match="every frame .* is empty"):
        render_cmd.run(p.parse_args(argv))
    assert len(list((tmp_path / "out").glob("*.png"))) == len(away["frames"])
    assert json.loads((tmp_path / "s.json").read_text())["empty_frames"] == len(away["frames"])
    both = json.loads(json.dumps(meta))
    both["frames"] = meta["frames"] + [dict(away["frames"][0], file_path=away["frames"][0]["file_path"] + "_away")]
    (tmp_path / "both.json").write_text(json.dumps(both))
    argv[2], argv[4] = str(tmp_path / "both.json"), str(tmp_path / "out2")
    assert render_cmd.run(p.parse_args(argv)) == 0
    assert "1 of" in capsys.readouterr().err


# ----------------------------------------------------------------------------------------------- atlas images
def _atlas_u8(bundle):
    return np.rint(bundle.atlas.packed_image().numpy() * 255).astype(np.uint8)


def test_bad_atlas_images_name_the_file(saved, tmp_path):
    u8 = _atlas_u8(saved[3])
    Image.fromarray(u8[:-3]).save(tmp_path / "small.png")
    good = tmp_path / "good.png"
    Image.fromarray(u8).save(good)
    (tmp_path / "truncated.png").write_bytes(good.read_bytes()[: len(good.read_bytes()) // 2])
    (tmp_path / "garbage.png").write_bytes(b"not a png at all")
    (tmp_path / "jpeg_bytes.png").write_bytes(b"\xff\xd8\xff\xe0" + b"\x00" * 64)
    for name, err_type in (("small.png", InputError), ("truncated.png", DataError), ("garbage.png", DataError),
                           ("jpeg_bytes.png", DataError), ("missing.png", DataError)):
        with pytest.raises(err_type) as err:
            _render(saved, tmp_path, atlas=tmp_path / name)
        assert name in str(err.value), name
        assert isinstance(err.value, PointGTError)


def test_atlas_images_in_other_png_layouts_are_read_correctly(saved, tmp_path):
    """Greyscale, RGBA and 16-bit atlases of the right size are valid paint: the frame matches the 8-bit RGB one."""
    u8 = _atlas_u8(saved[3])
    u8 = u8.copy()
    u8[: u8.shape[0] // 2] = 255 - u8[: u8.shape[0] // 2]  # a real edit, so the texture path runs
    Image.fromarray(u8).save(tmp_path / "rgb.png")
    Image.fromarray(np.dstack([u8, np.full(u8.shape[:2], 255, np.uint8)])).save(tmp_path / "rgba.png")
    u16 = u8.astype(np.uint16) * 257  # the same colours at 16 bits
    _save_png16(tmp_path / "rgb16.png", u16)
    outs = {}
    for name in ("rgb.png", "rgba.png", "rgb16.png"):
        _render(saved, tmp_path, atlas=tmp_path / name, json=tmp_path / "s.json")
        assert json.loads((tmp_path / "s.json").read_text())["texture_rays"] > 0, name
        outs[name] = (tmp_path / "out" / "view.png").read_bytes()
    assert outs["rgba.png"] == outs["rgb.png"] and outs["rgb16.png"] == outs["rgb.png"]
    grey = u8.mean(-1).astype(np.uint8)
    Image.fromarray(grey).save(tmp_path / "grey.png")
    assert _render(saved, tmp_path, atlas=tmp_path / "grey.png") == 0


def _save_png16(path, u16):
    """A 16-bit RGB PNG (Pillow cannot write one), written chunk by chunk."""
    import struct
    import zlib

    h, w, _ = u16.shape
    raw = b"".join(b"\x00" + u16[r].astype(">u2").tobytes() for r in range(h))

    def chunk(kind, data):
        return struct.pack(">I", len(data)) + kind + data + struct.pack(">I", zlib.crc32(kind + data) & 0xFFFFFFFF)

    path.write_bytes(b"\x89PNG\r\n\x1a\n" + chunk(b"IHDR", struct.pack(">IIBBBBB", w, h, 16, 2, 0, 0, 0))
                     + chunk(b"IDAT", zlib.compress(raw)) + chunk(b"IEND", b""))


# ------------------------------------------------------------------------------------- model file content
def _bundle_arrays(bundle):
    arrays, meta = model_to_arrays(bundle.model)
    arrays.update(bundle.atlas.to_arrays())
    meta["atlas"] = bundle.atlas.meta()
    return arrays, meta


def _drop(d, key):
    d.pop(key)


MODEL_CASES = {
    "no_model_section": lambda a, m: _drop(m, "model"),
    "unknown_setting": lambda a, m: m["model"].update(colour_space="aces"),
    "bad_decoder": lambda a, m: m["model"].update(decoder="gan"),
    "k_as_text": lambda a, m: m["model"].update(k="twenty"),
    "xyz_wrong_shape": lambda a, m: a.update({"points/xyz": a["points/xyz"][:, :2].copy()}),
    "no_points": lambda a, m: a.update({"points/xyz": np.zeros((0, 3), np.float32)}),
    "features_missing": lambda a, m: _drop(a, "points/features"),
    "features_wrong_size": lambda a, m: a.update({"points/features": a["points/features"][:, :3].copy()}),
    "network_array_missing": lambda a, m: _drop(a, next(k for k in a if k.startswith("net/"))),
}
_SIDES = {"bandwidth": 0.1, "k": 8, "step": 0.01, "crease": 0.0}


def _sides_arrays(meta, majority):
    return {"atlas/sides/centres": np.zeros((5, 3), np.float32),
            "atlas/sides/normals": np.tile(np.eye(3, dtype=np.float32)[:1], (5, 1)),
            "atlas/sides/majority": np.full(int(meta["atlas"]["n"]), majority, np.float32)}


ATLAS_CASES = {
    "atlas_version": lambda a, m: m["atlas"].update(version=99),
    "atlas_entry_missing": lambda a, m: _drop(m["atlas"], "R"),
    "atlas_array_missing": lambda a, m: _drop(a, next(k for k in a if k.startswith("atlas/net/"))),
    "atlas_image_wrong_size": lambda a, m: a.update({"atlas/image": a["atlas/image"][:-1].copy()}),
    # a mid-surface (version 4) without its arrays, with normals that are not unit vectors, with a bad bandwidth
    "atlas_surface_missing": lambda a, m: m["atlas"].update(version=4, surface={"bandwidth": 0.1, "k": 8}),
    "atlas_surface_bad_normals": lambda a, m: (
        a.update({"atlas/surface/centres": np.zeros((5, 3), np.float32),
                  "atlas/surface/normals": np.full((5, 3), 2.0, np.float32)}),
        m["atlas"].update(version=4, surface={"bandwidth": 0.1, "k": 8})),
    "atlas_surface_bandwidth": lambda a, m: (
        a.update({"atlas/surface/centres": np.zeros((5, 3), np.float32),
                  "atlas/surface/normals": np.tile(np.eye(3, dtype=np.float32)[:1], (5, 1))}),
        m["atlas"].update(version=4, surface={"bandwidth": "wide", "k": 8})),
    # charts split by side (version 5) without their arrays, with a majority that is not +-1, a step that is not
    # positive, or on a grid layout
    "atlas_sides_missing": lambda a, m: (
        [a.pop(k) for k in [k for k in a if k.startswith("atlas/sides/")]],
        m["atlas"].update(version=5, sides=dict(_SIDES))),
    "atlas_sides_bad_majority": lambda a, m: (
        a.update(_sides_arrays(m, 0.5)), m["atlas"].update(version=5, sides=dict(_SIDES))),
    "atlas_sides_bad_step": lambda a, m: (
        a.update(_sides_arrays(m, 1.0)), m["atlas"].update(version=5, sides=dict(_SIDES, step=-1.0))),
    # world lengths no scene has, finite but overflowing once squared or scaled (found by mutating a model's meta)
    "atlas_half_huge": lambda a, m: m["atlas"].update(half=1e300),
    "atlas_sides_bandwidth_huge": lambda a, m: (
        a.update(_sides_arrays(m, 1.0)), m["atlas"].update(version=5, sides=dict(_SIDES, bandwidth=1e300))),
    "atlas_sides_on_grid": lambda a, m: (
        a.update(_sides_arrays(m, 1.0)), m["atlas"].update(version=5, layout="grid", sides=dict(_SIDES))),
    # an island layout's cropped cell grids (version 7): missing, a box outside the grid, a crop of the wrong length,
    # a grid size no atlas has (refused before anything that large is allocated)
    "atlas_cells_missing": lambda a, m: _drop(a, "atlas/islands/cell_crops"),
    "atlas_cells_box_outside": lambda a, m: a.update({"atlas/islands/cell_boxes": a["atlas/islands/cell_boxes"]
                                                      + np.array([0, 0, 1 << 16, 0], np.int32)}),
    "atlas_cells_crops_short": lambda a, m: a.update({"atlas/islands/cell_crops": a["atlas/islands/cell_crops"][1:]}),
    "atlas_cells_grid_huge": lambda a, m: a.update({"atlas/islands/grid": np.array([1 << 24], np.int32)}),
}
# load_bundle prefixes the atlas's own ModelFileError with the model file's path.


@pytest.mark.parametrize("case", list(MODEL_CASES) + list(ATLAS_CASES))
def test_damaged_model_content_is_a_clear_error_naming_the_file(saved, tmp_path, case):
    arrays, meta = _bundle_arrays(saved[3])
    (MODEL_CASES | ATLAS_CASES)[case](arrays, meta)
    path = tmp_path / f"{case}.pgt"
    save_pgt(path, arrays, meta, allow_nonfinite=[k for k in arrays if k.startswith("atlas/texel")])
    with pytest.raises(ModelFileError) as err:
        load_bundle(path, device="cpu")
    assert str(path) in str(err.value)


@pytest.mark.parametrize("case", list(ATLAS_CASES))
def test_damaged_atlas_section_is_a_model_file_error(saved, tmp_path, case):
    arrays, meta = _bundle_arrays(saved[3])
    ATLAS_CASES[case](arrays, meta)
    path = tmp_path / f"{case}.pgt"
    save_pgt(path, arrays, meta, allow_nonfinite=[k for k in arrays if k.startswith("atlas/texel")])
    with pytest.raises(ModelFileError, match="atlas"):
        load_bundle(path, device="cpu")


# ------------------------------------------------------------------------------------------ failed saves
def _only(folder):
    return sorted(p.name for p in folder.iterdir())


def test_model_save_failing_midway_keeps_the_old_model(saved, tmp_path, monkeypatch):
    bundle = saved[3]
    path = tmp_path / "m.pgt"
    save_bundle(path, bundle)
    old = path.read_bytes()
    calls = []
    real = pgt._write_member

    def failing(zf, member, arr):
        calls.append(member)
        if len(calls) == 5:
            raise OSError("No space left on device")
        real(zf, member, arr)

    monkeypatch.setattr(pgt, "_write_member", failing)
    with pytest.raises(OSError, match="No space"):
        save_bundle(path, bundle)
    assert path.read_bytes() == old and _only(tmp_path) == ["m.pgt"]
    monkeypatch.undo()
    loaded = load_bundle(path, device="cpu")
    assert torch.equal(loaded.model.xyz, bundle.model.xyz.detach())


def test_rename_failing_keeps_old_png_json_and_model(saved, tmp_path, monkeypatch):
    from core.images.png import write_png

    png, js, model = tmp_path / "a.png", tmp_path / "s.json", tmp_path / "m.pgt"
    write_png(png, np.zeros((4, 4, 3)))
    atomic.atomic_write_text(js, '{"old": true}')
    save_bundle(model, saved[3])
    before = {p: p.read_bytes() for p in (png, js, model)}

    def failing_replace(src, dst):
        raise OSError("disk unplugged")

    monkeypatch.setattr(atomic.os, "replace", failing_replace)
    for write in (lambda: write_png(png, np.ones((4, 4, 3))), lambda: atomic.atomic_write_text(js, "{}"),
                  lambda: save_bundle(model, saved[3])):
        with pytest.raises(OSError, match="unplugged"):
            write()
    monkeypatch.undo()
    for p, data in before.items():
        assert p.read_bytes() == data, p.name
    # backups of the previous versions may exist (.bak, complete copies); temp files may not
    assert not [n for n in _only(tmp_path) if n.endswith(".part") or n.startswith(".")]
    assert os.path.exists(png)
