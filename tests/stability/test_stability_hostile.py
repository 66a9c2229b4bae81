"""Hostile inputs against the `pointgt` command line, run in-process on a tiny model: damaged or crafted model
files, point/id files, images and datasets, extreme flags, bad output paths, interrupts and a full disk.

Every case must end in exit code 2 with a one-line error naming the input (or in correct output), and no file of
the user's may be lost. Part of the cases are generated: seeded random corruptions of a valid model, PNG and .npy
file, and every numeric setting of a model file replaced by extreme values.
"""
import argparse
import hashlib
import io
import json
import os
import random
import shutil
import struct
import subprocess
import sys
import zipfile
import zlib
from pathlib import Path

import numpy as np
import pytest
import torch

from core.bundle import load_bundle, save_bundle
from core.modelfile import pgt
from core.util.errors import PointGTError
from tests.helpers.synthetic import fibonacci_cameras, render_split, write_split
from tests.helpers.tiny import tiny_bundle
from tools import cli

pytestmark = pytest.mark.stability
REPO = Path(__file__).resolve().parents[2]

# A fit of a few seconds: 16 px views, 3 steps, a 4-chart atlas of 8 texels.
FAST_FIT = ["--steps", "3", "--no-progress", "--device", "cpu", "--threads", "1", "--num-points", "200",
            "--feature-dim", "4", "--key-width", "8", "--value-width", "8", "--patches", "1", "--patch-size", "8",
            "--atlas-steps", "2", "--atlas-texture-steps", "0", "--atlas-charts", "4", "--atlas-texture-res", "8",
            "--atlas-width-chart", "8", "--atlas-width-map", "8", "--atlas-depth-chart", "1", "--atlas-depth-map", "1",
            "--atlas-eval-samples", "64", "--atlas-batch", "64", "--atlas-footprint-iters", "2", "--atlas-device",
            "cpu", "--no-profile"]


@pytest.fixture(scope="module")
def env(tmp_path_factory):
    """Folder with the tiny model (m.pgt), a one-camera transforms file and a 16 px dataset (data/)."""
    torch.set_num_threads(1)
    bundle, _, test = tiny_bundle("fast")
    root = tmp_path_factory.mktemp("hostile")
    save_bundle(root / "m.pgt", bundle)
    (root / "cams.json").write_text(json.dumps({"camera_angle_x": float(test.camera_angle_x), "frames": [
        {"file_path": "./view", "transform_matrix": test.c2w[0].tolist()}]}))
    write_split(root / "data", render_split("card", fibonacci_cameras(4, seed=0), 16))
    write_split(root / "data", render_split("card", fibonacci_cameras(2, seed=5), 16, split="test"))
    return argparse.Namespace(root=root, model=root / "m.pgt", cams=root / "cams.json", data=root / "data",
                              bundle=bundle)


def run_cli(capsys, *argv):
    """(exit code, stderr) of `pointgt ARGV` run in-process."""
    capsys.readouterr()
    code = cli.main([str(a) for a in argv])
    return code, capsys.readouterr().err


def refused(capsys, *argv, names=()):
    """Run the command and check the refusal: exit 2, one line, naming every string in `names`."""
    code, err = run_cli(capsys, *argv)
    assert code == 2, (argv, err)
    assert err.strip().count("\n") == 0 and "Traceback" not in err, err
    for name in names:
        assert str(name) in err, (name, err)
    return err


def render_args(env, tmp_path, *extra):
    return ["render", env.model, "--cameras", env.cams, "--out", tmp_path / "frames", "--size", "8",
            "--device", "cpu", *extra]


# ------------------------------------------------------------------------------------- crafting model files
def read_members(path):
    with zipfile.ZipFile(path) as zf:
        return {n: zf.read(n) for n in zf.namelist()}


def write_members(path, members, header=None):
    """A .pgt from members {name: bytes}; `header` (a dict) replaces pointgt.json."""
    members = dict(members)
    if header is not None:
        members[pgt.HEADER] = json.dumps(header).encode()
    with zipfile.ZipFile(path, "w", zipfile.ZIP_STORED) as zf:
        for name, data in members.items():
            zf.writestr(name, data)
    return path


def crafted(env, path, edit):
    """Copy the tiny model with `edit(header, members)` applied (members: {name: bytes}, editable)."""
    members = read_members(env.model)
    header = json.loads(members[pgt.HEADER])
    edit(header, members)
    return write_members(path, members, header)


def set_array(header, members, name, arr):
    """Store `arr` under `name` with a correct checksum (the content is what is hostile, not the container)."""
    entry = header["arrays"][name]
    raw = np.ascontiguousarray(arr, dtype=entry["dtype"]).tobytes()
    entry["shape"], entry["sha256"] = list(arr.shape), hashlib.sha256(raw).hexdigest()
    members[entry["member"]] = raw


def with_nan(header, members, name):
    arr = np.frombuffer(members[header["arrays"][name]["member"]], header["arrays"][name]["dtype"]).copy()
    arr[::3] = np.nan
    set_array(header, members, name, arr.reshape(header["arrays"][name]["shape"]))


# ------------------------------------------------------------------------------------------------ data loss
def test_fit_over_an_existing_model_keeps_it_as_the_one_backup(env, tmp_path, capsys):
    out = tmp_path / "model.pgt"
    shutil.copy(env.model, out)
    old = out.read_bytes()
    shutil.copy(env.model, tmp_path / "model.pgt.bak")  # an older backup: replaced by exactly one new one
    assert run_cli(capsys, "fit", env.data, "--out", out, *FAST_FIT)[0] == 0
    assert (tmp_path / "model.pgt.bak").read_bytes() == old  # stage 2's save did not overwrite it
    new = load_bundle(out, device="cpu")
    assert new.atlas is not None and out.read_bytes() != old
    assert not [p for p in tmp_path.iterdir() if p.name.endswith(".part")]


def test_fit_interrupted_in_stage_2_says_what_out_holds(env, tmp_path, capsys, monkeypatch):
    import core.pipeline

    out = tmp_path / "model.pgt"
    shutil.copy(env.model, out)
    old = out.read_bytes()

    def interrupted(*a, **k):
        raise KeyboardInterrupt

    monkeypatch.setattr(core.pipeline, "fit_atlas_stage", interrupted)
    code, err = run_cli(capsys, "fit", env.data, "--out", out, *FAST_FIT)
    assert code == 130 and err.strip().count("\n") == 0
    assert "stage-1 model" in err and "model.pgt.bak" in err and "pointgt atlas" in err, err
    assert (tmp_path / "model.pgt.bak").read_bytes() == old
    assert load_bundle(out, device="cpu").atlas is None  # exactly what the message says


def test_fit_interrupted_in_stage_1_leaves_out_unchanged(env, tmp_path, capsys, monkeypatch):
    import core.points.train

    out = tmp_path / "model.pgt"
    shutil.copy(env.model, out)
    old = out.read_bytes()

    def interrupted(*a, **k):
        raise KeyboardInterrupt

    monkeypatch.setattr(core.points.train, "fit_points", interrupted)
    code, err = run_cli(capsys, "fit", env.data, "--out", out, *FAST_FIT)
    assert code == 130 and "unchanged" in err
    assert out.read_bytes() == old and not (tmp_path / "model.pgt.bak").exists()


def test_atlas_interrupted_leaves_the_model_unchanged(env, tmp_path, capsys, monkeypatch):
    import core.pipeline

    model = tmp_path / "model.pgt"
    shutil.copy(env.model, model)
    old = model.read_bytes()
    monkeypatch.setattr(core.pipeline, "fit_atlas_stage", lambda *a, **k: (_ for _ in ()).throw(KeyboardInterrupt))
    for argv in (["atlas", model, env.data, "--atlas-device", "cpu"],
                 ["fit", env.data, "--out", model, "--stage", "atlas", *FAST_FIT]):
        code, err = run_cli(capsys, *argv)
        assert code == 130 and "unchanged" in err and str(model) in err, err
        assert model.read_bytes() == old and not (tmp_path / "model.pgt.bak").exists()


_FULL_DISK = r"""
import os, resource, sys
from core.util import atomic
mode, path, size = sys.argv[1], sys.argv[2], int(sys.argv[3])
if mode == "copy":  # a file system without hard links: the backup is a copy
    def no_link(*a, **k):
        raise OSError(1, "Operation not permitted")
    atomic.os.link = no_link
resource.setrlimit(resource.RLIMIT_FSIZE, (size, size))  # like `ulimit -f`: writes past `size` bytes fail
try:
    atomic.atomic_write_bytes(path, b"n" * (2 * size))
except atomic.OutputError as exc:
    print(exc)
    sys.exit(2)
"""


@pytest.mark.parametrize("mode", ["link", "copy"])
def test_full_disk_never_truncates_the_model_or_its_backup(tmp_path, mode):
    """With a 64 kB file size limit, replacing a 100 kB model fails cleanly: model and previous .bak intact."""
    path, bak = tmp_path / "m.pgt", tmp_path / "m.pgt.bak"
    path.write_bytes(b"o" * 100_000)
    bak.write_bytes(b"b" * 100_000)
    res = subprocess.run([sys.executable, "-c", _FULL_DISK, mode, str(path), str(64_000)], capture_output=True,
                         text=True, cwd=REPO, env={**os.environ, "PYTHONPATH": str(REPO)}, timeout=60)
    assert res.returncode == 2, res.stderr
    assert "m.pgt" in res.stdout and "left as they were" in res.stdout and res.stdout.strip().count("\n") == 0
    assert "Errno" not in res.stdout.split(":")[0]
    assert path.read_bytes() == b"o" * 100_000 and bak.read_bytes() == b"b" * 100_000
    assert sorted(p.name for p in tmp_path.iterdir()) == ["m.pgt", "m.pgt.bak"]


def test_backup_is_a_complete_copy_and_replaced_atomically(tmp_path, monkeypatch):
    from core.util import atomic

    path = tmp_path / "a.bin"
    atomic.atomic_write_bytes(path, b"one")
    atomic.atomic_write_bytes(path, b"two")
    atomic.atomic_write_bytes(path, b"three")
    assert path.read_bytes() == b"three" and (tmp_path / "a.bin.bak").read_bytes() == b"two"
    monkeypatch.setattr(atomic.os, "link", lambda *a, **k: (_ for _ in ()).throw(OSError(1, "no links")))
    atomic.atomic_write_bytes(path, b"four")
    assert (tmp_path / "a.bin.bak").read_bytes() == b"three"
    assert sorted(p.name for p in tmp_path.iterdir()) == ["a.bin", "a.bin.bak"]


# ----------------------------------------------------------------------------------------- silent garbage
@pytest.mark.parametrize("name", ["points/features", "points/influence", "net/"])
def test_nan_in_model_arrays_is_refused_on_load(env, tmp_path, capsys, name):
    def edit(header, members):
        target = name if not name.endswith("/") else next(n for n in header["arrays"] if n.startswith(name)
                                                          and header["arrays"][n]["dtype"] == "float32")
        with_nan(header, members, target)

    bad = crafted(env, tmp_path / "nan.pgt", edit)
    refused(capsys, *render_args(env, tmp_path)[:1], bad, *render_args(env, tmp_path)[2:], names=[bad, "NaN"])
    # Listing the name in allow_nonfinite does not make a NaN model loadable either.
    bad2 = crafted(env, tmp_path / "nan_allowed.pgt",
                   lambda h, m: (edit(h, m), h.__setitem__("allow_nonfinite", sorted(h["arrays"]))))
    with pytest.raises(PointGTError, match="NaN"):
        load_bundle(bad2, device="cpu")


def test_nan_atlas_is_not_exported_as_a_black_png(env, tmp_path, capsys):
    bad = crafted(env, tmp_path / "nan_atlas.pgt", lambda h, m: with_nan(h, m, "atlas/image"))
    refused(capsys, "export", bad, "--atlas", tmp_path / "a.png", names=[bad])
    allowed = crafted(env, tmp_path / "nan_atlas2.pgt", lambda h, m: (
        with_nan(h, m, "atlas/image"), h.__setitem__("allow_nonfinite", h["allow_nonfinite"] + ["atlas/image"])))
    refused(capsys, "export", allowed, "--atlas", tmp_path / "a.png", names=[allowed, "atlas/image"])
    assert not (tmp_path / "a.png").exists()


@pytest.mark.parametrize("value", ["nan", "inf", "-1", "0"])
def test_bad_temperature_is_refused(env, tmp_path, capsys, value):
    refused(capsys, *render_args(env, tmp_path, f"--temperature={value}"), names=["--temperature"])
    refused(capsys, *render_args(env, tmp_path, f"--temperature={value}", "--atlas", env.root / "none.png"),
            names=["--temperature"])
    assert not (tmp_path / "frames").exists()


def test_plain_render_uses_the_temperature(env, tmp_path, capsys):
    frames = {}
    for t in ("1", "0.3"):
        assert run_cli(capsys, *render_args(env, tmp_path, "--temperature", t))[0] == 0
        frames[t] = (tmp_path / "frames" / "view.png").read_bytes()
    assert frames["1"] != frames["0.3"]
    # one that hands every ray to the background renders nothing: the user hears why, the frame is written
    code, err = run_cli(capsys, *render_args(env, tmp_path, "--temperature", "0.05"))
    last = err.strip().splitlines()[-1]
    assert code == 2 and "Traceback" not in err and "empty" in last and "--temperature 0.05" in last
    assert (tmp_path / "frames" / "view.png").read_bytes() != frames["0.3"]


@pytest.mark.parametrize("flag,value", [("--steps", "-5"), ("--minutes", "-1"),
                                        ("--minutes", "nan"), ("--lr-points", "nan"), ("--lr-points", "-0.1")])
def test_fit_refuses_empty_or_negative_budgets_before_touching_out(env, tmp_path, capsys, flag, value):
    out = tmp_path / "model.pgt"
    out.write_bytes(b"the user's model")
    refused(capsys, "fit", env.data, "--out", out, *FAST_FIT, f"{flag}={value}", names=[flag])
    assert out.read_bytes() == b"the user's model" and not (tmp_path / "model.pgt.bak").exists()


# ------------------------------------------------------------------------------------ sizes before memory
def _zip64_bomb(env, path):
    """A model whose array claims 1 TB in the zip directory (zip64 sizes) and in the header; the file is small."""
    members = read_members(env.model)
    header = json.loads(members[pgt.HEADER])
    entry = header["arrays"]["points/influence"]
    entry["shape"] = [1 << 38]  # 2^38 float32 = 1 TiB
    with zipfile.ZipFile(path, "w", zipfile.ZIP_STORED) as zf:
        zf.writestr(pgt.HEADER, json.dumps(header).encode())
        for name, data in members.items():
            if name != pgt.HEADER:
                zf.writestr(name, data)
        info = zf.getinfo(entry["member"])
        info.file_size = info.compress_size = 1 << 40  # the central directory now claims 1 TiB (zip64 extra)
    return path


def _png(path, width, height, depth=8, colour=2, idat=b""):
    def chunk(kind, data):
        return struct.pack(">I", len(data)) + kind + data + struct.pack(">I", zlib.crc32(kind + data) & 0xFFFFFFFF)

    path.write_bytes(b"\x89PNG\r\n\x1a\n" + chunk(b"IHDR", struct.pack(">IIBBBBB", width, height, depth, colour,
                                                                        0, 0, 0))
                     + chunk(b"IDAT", zlib.compress(idat or b"\x00" * 1024)) + chunk(b"IEND", b""))
    return path


def _npy_claiming(path, shape, dtype="<f4", payload=b""):
    header = f"{{'descr': '{dtype}', 'fortran_order': False, 'shape': {tuple(shape)}, }}"
    header += " " * ((64 - (10 + len(header) + 1) % 64) % 64) + "\n"
    path.write_bytes(b"\x93NUMPY\x01\x00" + struct.pack("<H", len(header)) + header.encode() + payload)
    return path


def test_zip64_bomb_is_refused_before_allocation(env, tmp_path, capsys):
    bomb = _zip64_bomb(env, tmp_path / "bomb.pgt")
    assert zipfile.ZipFile(bomb).getinfo(json.loads(read_members(env.model)[pgt.HEADER])["arrays"]
                                         ["points/influence"]["member"]).file_size == 1 << 40
    refused(capsys, *render_args(env, tmp_path)[:1], bomb, *render_args(env, tmp_path)[2:], names=[bomb])
    refused(capsys, "export", bomb, "--points", tmp_path / "p.npy", names=[bomb])


@pytest.mark.parametrize("depth,colour", [(16, 2), (16, 6), (8, 2), (16, 4)])
def test_png_with_huge_declared_size_is_refused_from_its_header(env, tmp_path, capsys, depth, colour):
    big = _png(tmp_path / "big.png", 16384, 16384, depth, colour)
    refused(capsys, *render_args(env, tmp_path, "--atlas", big), names=[big, "too large"])


def test_16bit_png_unfilter_memory_is_bounded(tmp_path, monkeypatch):
    """The unfilter works in bands: the largest work array stays near _BAND_BYTES (it grew with H·(H+W))."""
    from core.images import png

    rng = np.random.default_rng(0)
    h, w = 96, 64
    u16 = rng.integers(0, 65536, (h, w, 3)).astype(">u2")
    raw = b"".join(bytes([r % 5]) + u16[r].tobytes() for r in range(h))  # every filter type, random bytes
    path = _png(tmp_path / "p16.png", w, h, 16, 2, raw)
    whole = png.read_png(path)
    sizes = []
    real_zeros = np.zeros

    def spy(shape, *a, **k):
        arr = real_zeros(shape, *a, **k)
        sizes.append(arr.nbytes)
        return arr

    monkeypatch.setattr(png, "_BAND_BYTES", 4 * 6 * (w + 1) * 8)  # 8-row bands
    monkeypatch.setattr(png.np, "zeros", spy)
    banded = png.read_png(path)
    monkeypatch.undo()
    assert np.array_equal(whole, banded)
    assert max(sizes) <= 2 * (8 + w) * 9 * 6 * 2  # one band's arrays, not the whole image's


def test_npy_headers_claiming_huge_arrays_are_refused(env, tmp_path, capsys):
    n = env.bundle.model.num_points
    np.save(tmp_path / "p.npy", np.zeros((n, 3), np.float32))
    cases = {"huge.npy": ((10 ** 9, 3), "<f4"), "short.npy": ((n, 3), "<f4"), "ids_huge.npy": ((10 ** 12,), "<i8")}
    for name, (shape, dtype) in cases.items():
        path = _npy_claiming(tmp_path / name, shape, dtype, payload=b"\x00" * 64)
        flag = "--ids" if name.startswith("ids") else "--points"
        extra = ["--points", tmp_path / "p.npy"] if flag == "--ids" else []
        refused(capsys, *render_args(env, tmp_path, *extra, flag, path), names=[path])


@pytest.mark.parametrize("section,key,value", [("model", "feature_dim", 10 ** 9), ("model", "key_width", 10 ** 7),
                                               ("model", "k", 0), ("model", "k", -3), ("model", "temperature", 0.0),
                                               ("atlas", "R", 10 ** 6), ("atlas", "n", 10 ** 6),
                                               ("atlas", "width_map", 10 ** 8), ("atlas", "pad", -1)])
def test_model_settings_that_would_allocate_or_break_name_the_file(env, tmp_path, capsys, section, key, value):
    bad = crafted(env, tmp_path / f"{key}.pgt", lambda h, m: h["meta"][section].__setitem__(key, value))
    err = refused(capsys, *render_args(env, tmp_path)[:1], bad, *render_args(env, tmp_path)[2:], names=[bad])
    assert key in err or "sizes" in err


@pytest.mark.parametrize("argv,flag", [
    (["--size", "100000"], "--size"), (["--size", "0"], "--size"), (["--antialias", "0"], "--antialias"),
    (["--antialias", "99"], "--antialias"), (["--device", "bogus"], "--device")])
def test_render_flags_are_checked_first(env, tmp_path, capsys, argv, flag):
    refused(capsys, *render_args(env, tmp_path, *argv), names=[flag])
    assert not (tmp_path / "frames").exists()


def test_dataset_larger_than_memory_is_refused_before_allocation(env, tmp_path, capsys, monkeypatch):
    from core.images import dataset

    monkeypatch.setattr(dataset, "_memory_limit", lambda: 1000)  # 4 views of 16 x 16 need 16 kB
    refused(capsys, "fit", env.data, "--out", tmp_path / "m.pgt", *FAST_FIT,
            names=["transforms_train.json", "--downscale"])


def test_memory_error_is_a_clear_message(env, tmp_path, capsys, monkeypatch):
    import core.bundle

    def out_of_memory(*a, **k):
        raise MemoryError

    monkeypatch.setattr(core.bundle, "load_pgt", out_of_memory)
    refused(capsys, *render_args(env, tmp_path), names=["out of memory"])


def test_deeply_nested_json_is_a_clear_error(env, tmp_path, capsys):
    nested = "[" * 200_000 + "]" * 200_000
    bad = write_members(tmp_path / "deep.pgt", {pgt.HEADER: nested.encode()})
    refused(capsys, *render_args(env, tmp_path)[:1], bad, *render_args(env, tmp_path)[2:], names=[bad])
    meta_deep = crafted(env, tmp_path / "deep_meta.pgt", lambda h, m: None)
    members = read_members(meta_deep)
    text = members[pgt.HEADER].decode().replace('"meta": {', '"meta": {"x": ' + nested + ", ", 1)
    write_members(meta_deep, {**members, pgt.HEADER: text.encode()})
    refused(capsys, *render_args(env, tmp_path)[:1], meta_deep, *render_args(env, tmp_path)[2:], names=[meta_deep])
    cams = tmp_path / "cams.json"
    cams.write_text('{"camera_angle_x": 0.5, "frames": ' + nested + "}")
    refused(capsys, "render", env.model, "--cameras", cams, "--out", tmp_path / "f", "--size", "8",
            names=[cams])
    data = tmp_path / "data"
    shutil.copytree(env.data, data)
    (data / "transforms_test.json").write_text(nested)
    refused(capsys, "fit", data, "--out", tmp_path / "m.pgt", *FAST_FIT, names=["transforms_test.json"])


# ---------------------------------------------------------------------------------------------------- flags
@pytest.mark.parametrize("flag,value", [("--points", "0"), ("--num-points", "-1"), ("--feature-dim", "0"),
                                        ("--patch-size", "0"), ("--patches", "0"), ("--atlas-batch", "0"),
                                        ("--device", "bogus"), ("--atlas-device", "gpu7"), ("--k", "0"),
                                        ("--atlas-texture-res", "100000"), ("--atlas-texture-res", "-1"),
                                        ("--dropout", "1"), ("--downscale", "0"), ("--atlas-lr", "nan"),
                                        ("--neighbor-radius-px", "-2"), ("--neighbor-radius-px", "nan"),
                                        ("--train-scales", "1,x"), ("--train-scales", "2,2"),
                                        ("--train-scales", "0,2")])
def test_fit_flags_are_validated_with_the_flag_named(env, tmp_path, capsys, monkeypatch, flag, value):
    import core.images.dataset

    monkeypatch.setattr(core.images.dataset, "load_split", lambda *a, **k: pytest.fail("read the dataset"))
    refused(capsys, "fit", env.data, "--out", tmp_path / "m.pgt", *FAST_FIT, f"{flag}={value}", names=[flag])
    assert not (tmp_path / "m.pgt").exists()


def test_empty_points_with_empty_ids(env, tmp_path, capsys):
    np.save(tmp_path / "p.npy", np.zeros((0, 3), np.float32))
    np.save(tmp_path / "i.npy", np.zeros(0, np.int64))
    code, err = run_cli(capsys, *render_args(env, tmp_path, "--points", tmp_path / "p.npy", "--ids",
                                             tmp_path / "i.npy"))
    if code == 0:  # every point removed: a transparent frame is the correct output
        from core.images.png import read_png

        img = read_png(tmp_path / "frames" / "view.png")
        assert np.isfinite(img).all() and float(img[..., 3].max()) == 0.0
    else:
        assert code == 2 and "p.npy" in err and err.strip().count("\n") == 0


def test_config_limits_apply_to_configs_read_from_files_and_built_in_code():
    from core.atlas.config import AtlasConfig
    from core.config import from_dict, validate
    from core.points.model import ModelConfig
    from core.util.errors import InputError

    with pytest.raises(InputError, match=r"ModelConfig\.k must be at least 1"):
        from_dict(ModelConfig, {"k": 0})
    with pytest.raises(InputError, match="--atlas-batch must be at least 1"):
        validate(AtlasConfig(batch=0), prefix="atlas")
    for cls in (ModelConfig, AtlasConfig):
        validate(cls())  # the defaults are valid


# ------------------------------------------------------------------------------------------- output paths
def test_output_paths_are_checked_before_any_work(env, tmp_path, capsys, monkeypatch):
    import core.images.dataset

    monkeypatch.setattr(core.images.dataset, "load_split", lambda *a, **k: pytest.fail("started the work"))
    (tmp_path / "folder.pgt").mkdir()
    (tmp_path / "afile").write_text("x")
    refused(capsys, "fit", env.data, "--out", tmp_path / "folder.pgt", *FAST_FIT, names=["--out", "folder.pgt"])
    refused(capsys, "fit", env.data, "--out", tmp_path / "afile" / "m.pgt", *FAST_FIT, names=["--out", "afile"])
    monkeypatch.undo()
    refused(capsys, *render_args(env, tmp_path, "--json", tmp_path / "folder.pgt"), names=["--json"])
    refused(capsys, "render", env.model, "--cameras", env.cams, "--out", tmp_path / "afile", "--size", "8",
            names=["--out", "afile"])
    assert not (tmp_path / "frames").exists()
    refused(capsys, "export", env.model, "--atlas", tmp_path / "folder.pgt", names=["--atlas"])
    refused(capsys, "eval", env.model, env.data, "--json", tmp_path / "afile" / "x.json", names=["--json"])
    refused(capsys, "package-addon", "--out", tmp_path / "afile", names=["--out", "afile"])


# -------------------------------------------------------------------------------------------------- minor
def test_model_symlinked_to_a_device_is_not_called_a_folder(env, tmp_path, capsys):
    link = tmp_path / "zero.pgt"
    link.symlink_to("/dev/zero")
    err = refused(capsys, *render_args(env, tmp_path)[:1], link, *render_args(env, tmp_path)[2:], names=[link])
    assert "folder" not in err and "regular file" in err


def test_uint64_ids_report_the_real_value(env, tmp_path, capsys):
    n = env.bundle.model.num_points
    np.save(tmp_path / "p.npy", env.bundle.model.xyz.detach().numpy())
    ids = np.arange(n, dtype=np.uint64)
    ids[0] = np.iinfo(np.uint64).max
    np.save(tmp_path / "i.npy", ids)
    err = refused(capsys, *render_args(env, tmp_path, "--points", tmp_path / "p.npy", "--ids", tmp_path / "i.npy"),
                  names=["i.npy", str(np.iinfo(np.uint64).max)])
    assert "[-1" not in err


@pytest.mark.parametrize("file_path", ["/etc/hostname", "../outside/r_0", "./train/../../outside/r_0"])
def test_dataset_paths_leaving_the_folder_are_refused(env, tmp_path, capsys, file_path):
    data = tmp_path / "data"
    shutil.copytree(env.data, data)
    (tmp_path / "outside").mkdir()
    shutil.copy(data / "train" / "r_0.png", tmp_path / "outside" / "r_0.png")
    doc = json.loads((data / "transforms_train.json").read_text())
    doc["frames"][0]["file_path"] = file_path
    (data / "transforms_train.json").write_text(json.dumps(doc))
    refused(capsys, "fit", data, "--out", tmp_path / "m.pgt", *FAST_FIT, names=["transforms_train.json",
                                                                              "outside the dataset folder"])


# ---------------------------------------------------------------------------------------- generated inputs
def _load_or_model_error(path):
    """Loading either works (and the model renders finite) or raises ModelFileError; nothing else."""
    from core.points.render import render_frame
    from core.util.errors import ModelFileError

    try:
        bundle = load_bundle(path, device="cpu")
    except ModelFileError as exc:
        assert str(path) in str(exc)
        return "refused"
    c2w = torch.eye(4)
    c2w[2, 3] = 3.0
    out = render_frame(bundle.model, c2w, 6, 6, 8.0)
    assert bool(torch.isfinite(out["rgb"]).all()) and bool(torch.isfinite(out["alpha"]).all())
    return "loaded"


def test_generated_byte_corruptions_of_a_model(env, tmp_path):
    data = env.model.read_bytes()
    rng = random.Random(14)
    outcomes = []
    for i in range(40):
        blob = bytearray(data)
        kind = i % 4
        if kind == 0:  # flip a few bytes anywhere
            for _ in range(rng.randint(1, 8)):
                blob[rng.randrange(len(blob))] ^= 1 << rng.randrange(8)
        elif kind == 1:  # truncate
            blob = blob[:rng.randrange(len(blob))]
        elif kind == 2:  # overwrite a span with junk
            a = rng.randrange(len(blob))
            blob[a:a + 64] = bytes(rng.randrange(256) for _ in range(64))[:len(blob) - a]
        else:  # flip bytes in the zip directory at the end
            for _ in range(rng.randint(1, 4)):
                blob[len(blob) - 1 - rng.randrange(min(len(blob), 2000))] ^= 0xFF
        path = tmp_path / f"c{i}.pgt"
        path.write_bytes(bytes(blob))
        outcomes.append(_load_or_model_error(path))
    assert outcomes.count("refused") >= 30


def _numeric_settings(meta):
    for section in ("model", "atlas"):
        for key, val in meta[section].items():
            if isinstance(val, (int, float)) and not isinstance(val, bool):
                yield section, key


def test_generated_extreme_settings_in_a_model_file(env, tmp_path):
    meta = json.loads(read_members(env.model)[pgt.HEADER])["meta"]
    extremes = [0, -1, 10 ** 12, 1e300, -1e-300, 0.5]
    outcomes = {}
    for section, key in _numeric_settings(meta):
        for j, value in enumerate(extremes):
            path = crafted(env, tmp_path / f"{section}_{key}_{j}.pgt",
                           lambda h, m: h["meta"][section].__setitem__(key, value))
            outcomes[(section, key, value)] = _load_or_model_error(path)
    assert outcomes[("model", "k", 0)] == "refused" and outcomes[("atlas", "R", 10 ** 12)] == "refused"


def test_generated_corruptions_of_png_and_npy_files(env, tmp_path):
    from core.images.png import read_png
    from core.util.errors import DataError, InputError
    from tools.commands.render import load_npy

    rng = random.Random(7)
    u16 = np.random.default_rng(1).integers(0, 65536, (12, 10, 4)).astype(">u2")
    png16 = _png(tmp_path / "good16.png", 10, 12, 16, 6, b"".join(b"\x04" + u16[r].tobytes() for r in range(12)))
    buf = io.BytesIO()
    np.save(buf, np.random.default_rng(2).normal(size=(50, 3)).astype(np.float32))
    sources = {"png": png16.read_bytes(), "npy": buf.getvalue()}
    for i in range(60):
        kind = "png" if i % 2 else "npy"
        blob = bytearray(sources[kind])
        if i % 3 == 0:
            blob = blob[:rng.randrange(len(blob))]
        else:
            for _ in range(rng.randint(1, 6)):
                blob[rng.randrange(len(blob))] = rng.randrange(256)
        path = tmp_path / f"g{i}.{kind}"
        path.write_bytes(bytes(blob))
        try:
            arr = read_png(path) if kind == "png" else load_npy(path, "--points", "points")
        except (DataError, InputError) as exc:
            assert str(path) in str(exc)
            continue
        assert arr.dtype == np.float32 and (kind == "npy" or (np.isfinite(arr).all() and arr.min() >= 0))
