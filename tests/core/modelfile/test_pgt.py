import json
import pickle
import subprocess
import sys
import zipfile

import numpy as np
import pytest

import core.modelfile.pgt as pgt
from core.modelfile.pgt import FORMAT_VERSION, PgtFile, load_pgt, read_meta, save_pgt
from core.util.errors import InputError, ModelFileError


def sample_arrays(seed=0):
    rng = np.random.default_rng(seed)
    return {
        "points/xyz": rng.standard_normal((1000, 3)).astype(np.float32),
        "points/feat": rng.standard_normal((1000, 8)).astype(np.float16),
        "points/id": np.arange(1000, dtype=np.int64),
        "net/attn.0.weight": rng.standard_normal((16, 4)).astype(np.float32),
        "net/attn.0.bias": rng.standard_normal(16).astype(np.float32),
        "atlas/texture": rng.integers(0, 256, (4, 8, 8, 3), dtype=np.uint8),
        "atlas/charts": rng.integers(-5, 5, (7,), dtype=np.int32),
        "mask": rng.random((5, 5)) > 0.5,
        "scalar/step": np.array(250000, dtype=np.int64),
        "scalar/lr": np.array(1e-3, dtype=np.float32),
        "empty/rows": np.zeros((0, 3), dtype=np.float32),
        "empty/flat": np.zeros((0,), dtype=np.uint8),
    }


META = {"fit": {"points": 1000, "lr": 0.001, "names": ["a", "b"]}, "scene": "lego", "note": "ünïcode ✓", "n": None}


def _assert_same(a: dict, b: dict):
    assert sorted(a) == sorted(b)
    for k in a:
        assert a[k].dtype == b[k].dtype and a[k].shape == b[k].shape, k
        np.testing.assert_array_equal(a[k], b[k], err_msg=k)


def test_round_trip_is_exact_for_every_dtype_and_shape(tmp_path):
    arrays = sample_arrays()
    save_pgt(tmp_path / "m.pgt", arrays, META)
    got, meta = load_pgt(tmp_path / "m.pgt")
    _assert_same(got, arrays)
    assert meta == META
    assert got["points/xyz"].flags.writeable and got["scalar/step"].shape == ()


def test_round_trip_big_non_contiguous_and_big_endian(tmp_path):
    big = np.random.default_rng(1).standard_normal((600_000, 3)).astype(np.float32)  # ~7 MB
    arrays = {"big": big, "strided": big[::7, ::-1][:50], "be": np.arange(10, dtype=">i4"),
              "be_f": np.linspace(0, 1, 5).astype(">f4")}
    save_pgt(tmp_path / "b.pgt", arrays, {})
    got, _ = load_pgt(tmp_path / "b.pgt")
    for k, v in arrays.items():
        np.testing.assert_array_equal(got[k], v)
        assert got[k].dtype.isnative
    with zipfile.ZipFile(tmp_path / "b.pgt") as zf:
        assert all(i.compress_type == zipfile.ZIP_STORED for i in zf.infolist())
        header = json.loads(zf.read("pointgt.json"))
        member = header["arrays"]["be"]["member"]
        assert zf.read(member) == np.arange(10, dtype="<i4").tobytes()  # raw little-endian on disk


def test_subsets_prefixes_and_lazy_reader(tmp_path):
    save_pgt(tmp_path / "m.pgt", sample_arrays(), META)
    got, meta = load_pgt(tmp_path / "m.pgt", names=["points/xyz", "net/"])
    assert sorted(got) == ["net/attn.0.bias", "net/attn.0.weight", "points/xyz"] and meta == META
    with pytest.raises(ModelFileError, match="has no array 'points/rgb'; it holds"):
        load_pgt(tmp_path / "m.pgt", names=["points/rgb"])
    with pytest.raises(ModelFileError, match="no arrays under 'unet/'"):
        load_pgt(tmp_path / "m.pgt", names=["unet/"])
    with PgtFile(tmp_path / "m.pgt") as f:
        assert f.shape("atlas/texture") == (4, 8, 8, 3) and f.dtype("mask") == np.bool_
        assert f.header["format_version"] == FORMAT_VERSION and f.header["producer"].startswith("pointgt")
        np.testing.assert_array_equal(f.read("points/id"), np.arange(1000))


def test_read_meta_reads_only_the_header(tmp_path):
    save_pgt(tmp_path / "m.pgt", sample_arrays(), META)
    _flip_byte_in_member(tmp_path / "m.pgt", "points/xyz")
    assert read_meta(tmp_path / "m.pgt") == META  # array data is never touched
    with pytest.raises(ModelFileError, match="'points/xyz' is corrupt"):
        load_pgt(tmp_path / "m.pgt")


def test_saving_is_deterministic(tmp_path):
    save_pgt(tmp_path / "a.pgt", sample_arrays(), META)
    save_pgt(tmp_path / "b.pgt", sample_arrays(), META)
    assert (tmp_path / "a.pgt").read_bytes() == (tmp_path / "b.pgt").read_bytes()


def test_module_never_imports_torch():
    code = "import sys, core.modelfile.pgt; sys.exit('torch' in sys.modules)"
    assert subprocess.run([sys.executable, "-c", code]).returncode == 0


# -------------------------------------------------------------------------------------------- save-side checks

@pytest.mark.parametrize("arrays,pattern", [
    ({"x": np.zeros(3)}, "dtype float64; allowed"),
    ({"x": np.array(["a"])}, "dtype <U1"),
    ({"x": np.zeros(2, dtype=np.complex64)}, "dtype complex64"),
    ({"x": [1.0, 2.0]}, "not a numpy array"),
    ({"../evil": np.zeros(1, np.float32)}, "name '../evil' is invalid"),
    ({"/abs": np.zeros(1, np.float32)}, "invalid"),
    ({"a//b": np.zeros(1, np.float32)}, "invalid"),
    ({"": np.zeros(1, np.float32)}, "invalid"),
    ({"sp ace": np.zeros(1, np.float32)}, "invalid"),
    ({3: np.zeros(1, np.float32), "ok": np.zeros(1, np.float32)}, "invalid"),
    ({"a/./b": np.zeros(1, np.float32)}, "invalid"),
    ({"w": np.array([1.0, np.nan], np.float32)}, r"'w' holds 1 NaN/inf values"),
    ({"w": np.array([np.inf], np.float16)}, "NaN/inf"),
])
def test_save_rejects_bad_arrays_and_leaves_no_file(tmp_path, arrays, pattern):
    with pytest.raises(InputError, match=pattern):
        save_pgt(tmp_path / "m.pgt", arrays, {})
    assert list(tmp_path.iterdir()) == []


def test_save_rejects_meta_that_is_not_plain_json(tmp_path):
    for meta in ({"lr": float("nan")}, {"obj": object()}, {"arr": np.zeros(2)}):
        with pytest.raises(InputError, match="meta must be plain JSON"):
            save_pgt(tmp_path / "m.pgt", {}, meta)
    assert list(tmp_path.iterdir()) == []


def test_non_finite_arrays_allowed_by_name_round_trip(tmp_path):
    arr = np.array([np.nan, np.inf, -np.inf, 1.0], np.float32)
    save_pgt(tmp_path / "m.pgt", {"depth": arr}, {}, allow_nonfinite=["depth"])
    got, _ = load_pgt(tmp_path / "m.pgt")
    np.testing.assert_array_equal(got["depth"], arr)


def test_atomic_save_keeps_backup_and_failed_save_leaves_old_file(tmp_path, monkeypatch):
    path = tmp_path / "m.pgt"
    save_pgt(path, {"v": np.array([1], np.int32)}, {"gen": 1})
    first = path.read_bytes()
    save_pgt(path, {"v": np.array([2], np.int32)}, {"gen": 2})
    assert (tmp_path / "m.pgt.bak").read_bytes() == first and read_meta(path) == {"gen": 2}
    second = path.read_bytes()

    calls = []

    def failing_write(zf, member, arr):
        calls.append(member)
        if len(calls) == 2:
            raise OSError("No space left on device")
        real_write(zf, member, arr)
    real_write = pgt._write_member
    monkeypatch.setattr(pgt, "_write_member", failing_write)
    with pytest.raises(OSError, match="No space"):
        save_pgt(path, {"a": np.zeros(4, np.float32), "b": np.ones(4, np.float32)}, {"gen": 3})
    assert path.read_bytes() == second and (tmp_path / "m.pgt.bak").read_bytes() == first
    assert sorted(p.name for p in tmp_path.iterdir()) == ["m.pgt", "m.pgt.bak"]  # no temp file left behind


# -------------------------------------------------------------------------------------------- load-side checks

def _rewrite(path, header_fn=None, members_fn=None):
    """Rebuild a .pgt with an edited header and/or edited members (CRCs recomputed by zipfile)."""
    with zipfile.ZipFile(path) as zf:
        members = {n: zf.read(n) for n in zf.namelist()}
    header = json.loads(members["pointgt.json"])
    if header_fn:
        header_fn(header)
    members["pointgt.json"] = json.dumps(header).encode()
    if members_fn:
        members_fn(members, header)
    with zipfile.ZipFile(path, "w") as zf:
        for n, data in members.items():
            zf.writestr(n, data)


def _flip_byte_in_member(path, name):
    """Flip one byte of an array's data in place, without touching the zip's own CRC."""
    with zipfile.ZipFile(path) as zf:
        member = json.loads(zf.read("pointgt.json"))["arrays"][name]["member"]
        info = zf.getinfo(member)
    data = bytearray(path.read_bytes())
    start = info.header_offset + 30 + len(info.filename.encode()) + len(info.extra)
    data[start + info.file_size // 2] ^= 0x01
    path.write_bytes(bytes(data))


@pytest.fixture
def model(tmp_path):
    path = tmp_path / "m.pgt"
    save_pgt(path, sample_arrays(), META)
    return path


def test_missing_file_and_folder(tmp_path):
    with pytest.raises(ModelFileError, match="model file not found"):
        load_pgt(tmp_path / "nope.pgt")
    with pytest.raises(ModelFileError, match="is a folder"):
        load_pgt(tmp_path)


@pytest.mark.parametrize("fraction", [0.0, 0.001, 0.25, 0.5, 0.9, 0.999])
def test_truncated_files_are_rejected(model, fraction):
    data = model.read_bytes()
    model.write_bytes(data[:int(len(data) * fraction)])
    with pytest.raises(ModelFileError, match="m.pgt: not a readable .pgt model file"):
        load_pgt(model)


def test_truncation_message_points_to_the_backup(model):
    save_pgt(model, sample_arrays(1), META)  # now m.pgt.bak exists
    data = model.read_bytes()
    model.write_bytes(data[:len(data) // 2])
    with pytest.raises(ModelFileError, match=r"truncated.*restore the previous version from m\.pgt\.bak"):
        load_pgt(model)


def test_flipped_byte_in_array_data_is_detected(model):
    _flip_byte_in_member(model, "net/attn.0.weight")
    with pytest.raises(ModelFileError, match="'net/attn.0.weight' is corrupt"):
        load_pgt(model)


def test_sha256_catches_changes_even_with_a_valid_zip_crc(model):
    def tamper(members, header):
        m = header["arrays"]["points/id"]["member"]
        members[m] = np.arange(1, 1001, dtype="<i8").tobytes()  # same size, new CRC
    _rewrite(model, members_fn=tamper)
    with pytest.raises(ModelFileError, match=r"'points/id' is corrupt \(sha256 checksum mismatch\)"):
        load_pgt(model)
    assert load_pgt(model, names=["points/xyz"])[0]["points/xyz"].shape == (1000, 3)  # others still readable


def _central_record(data, member):
    """Offset of member's record in the zip's central directory (bytes of a .pgt), where zipfile reads its flags."""
    name = member.encode()
    pos = data.find(b"PK\x01\x02")
    while pos >= 0:
        n = int.from_bytes(data[pos + 28:pos + 30], "little")
        if bytes(data[pos + 46:pos + 46 + n]) == name:
            return pos
        pos = data.find(b"PK\x01\x02", pos + 46 + n)
    raise AssertionError(f"{member} not in the central directory")


def test_damaged_zip_directory_fields_are_model_file_errors(model):
    """Damaged bytes that make zipfile itself fail with something other than BadZipFile: a 'version needed' no
    zip reader supports (NotImplementedError on opening), a member flagged as UTF-8-named whose local name is not
    UTF-8 (UnicodeDecodeError on reading it)."""
    good = model.read_bytes()
    with zipfile.ZipFile(model) as zf:
        member = json.loads(zf.read("pointgt.json"))["arrays"]["points/xyz"]["member"]
        local = zf.getinfo(member).header_offset
    data = bytearray(good)
    data[_central_record(data, member) + 6] = 0xFF  # version needed to extract: 25.5
    model.write_bytes(bytes(data))
    with pytest.raises(ModelFileError, match="m.pgt: not a readable .pgt model file: its zip directory is damaged"):
        load_pgt(model)
    data = bytearray(good)
    data[_central_record(data, member) + 9] |= 0x08  # flag bit 11: the name is UTF-8
    data[local + 30] = 0xFF                          # ... but the local header's name is not
    model.write_bytes(bytes(data))
    with pytest.raises(ModelFileError, match=r"m.pgt: array 'points/xyz' is corrupt"):
        load_pgt(model)


@pytest.mark.parametrize("bit", [0x01, 0x20, 0x40])  # encrypted, compressed patched data, strong encryption
@pytest.mark.parametrize("which", ["array", "header"])
def test_members_claiming_encryption_or_patch_data_are_model_file_errors(model, bit, which):
    """A damaged flag byte makes zipfile raise NotImplementedError or RuntimeError on opening the member; the
    reader names the file instead."""
    with zipfile.ZipFile(model) as zf:
        member = json.loads(zf.read("pointgt.json"))["arrays"]["points/xyz"]["member"]
    data = bytearray(model.read_bytes())
    data[_central_record(data, "pointgt.json" if which == "header" else member) + 8] |= bit
    model.write_bytes(bytes(data))
    with pytest.raises(ModelFileError, match="m.pgt: .*encrypted or patched"):
        load_pgt(model)


@pytest.mark.parametrize("edit,pattern", [
    (lambda h: h.update(magic="something-else"), "not a PointGT model"),
    (lambda h: h.update(format_version=FORMAT_VERSION + 1), "made by a newer PointGT.*update the add-on"),
    (lambda h: h.update(format_version=0), "older than this PointGT supports"),
    (lambda h: h.update(format_version="1"), "not an integer"),
    (lambda h: h.update(format_version=True), "not an integer"),
    (lambda h: h.update(meta=[1]), "'meta' must be an object"),
    (lambda h: h.update(arrays=[]), "'arrays' must be an object"),
    (lambda h: h["arrays"]["mask"].update(dtype="object"), "dtype 'object' is not allowed"),
    (lambda h: h["arrays"]["mask"].update(dtype="float64"), "dtype 'float64' is not allowed"),
    (lambda h: h["arrays"]["points/xyz"].update(shape=[1000, 4]), "holds 12000 bytes but .* need 16000"),
    (lambda h: h["arrays"]["points/xyz"].update(shape=[-1000, -3]), "non-negative integers"),
    (lambda h: h["arrays"]["points/xyz"].update(shape="1000x3"), "non-negative integers"),
    (lambda h: h["arrays"]["points/id"].update(dtype="int32"), "need 4000"),
    (lambda h: h["arrays"]["points/id"].update(member="arrays/99999.bin"), "missing from the archive"),
    (lambda h: h["arrays"]["points/id"].update(member="../../etc/passwd"), "missing from the archive"),
    (lambda h: h["arrays"]["points/id"].pop("sha256"), "malformed sha256"),
    (lambda h: h["arrays"].update(x=5), "not an object"),
])
def test_header_problems_are_rejected(model, edit, pattern):
    _rewrite(model, header_fn=edit)
    with pytest.raises(ModelFileError, match=pattern):
        load_pgt(model)


def test_invalid_json_header_and_missing_header(model, tmp_path):
    def bad_json(members, header):
        members["pointgt.json"] = b'{"magic": "pointgt-model", '
    _rewrite(model, members_fn=bad_json)
    with pytest.raises(ModelFileError, match="pointgt.json is not valid JSON"):
        read_meta(model)
    with zipfile.ZipFile(tmp_path / "other.pgt", "w") as zf:
        zf.writestr("readme.txt", "hello")
    with pytest.raises(ModelFileError, match=r"no pointgt.json inside.*other zip archive \(readme.txt\)"):
        load_pgt(tmp_path / "other.pgt")


class _Evil:
    """Unpickling this creates a marker file: proof that code ran."""

    def __init__(self, marker):
        self.marker = str(marker)

    def __reduce__(self):
        return (open, (self.marker, "w"))


def test_pickles_renamed_to_pgt_are_rejected_without_running(tmp_path):
    marker = tmp_path / "pwned"
    payload = pickle.dumps({"weights": _Evil(marker)}, protocol=4)
    assert payload[:1] == b"\x80"
    (tmp_path / "evil.pgt").write_bytes(payload)
    with pytest.raises(ModelFileError, match="looks like a Python pickle"):
        load_pgt(tmp_path / "evil.pgt")
    with zipfile.ZipFile(tmp_path / "ckpt.pgt", "w") as zf:  # the layout torch.save uses
        zf.writestr("archive/data.pkl", payload)
        zf.writestr("archive/version", "3\n")
    with pytest.raises(ModelFileError, match="looks like a PyTorch checkpoint"):
        read_meta(tmp_path / "ckpt.pgt")
    assert not marker.exists()


def test_garbage_and_empty_files(tmp_path):
    (tmp_path / "text.pgt").write_text("just some text, not a model")
    with pytest.raises(ModelFileError, match="not a zip archive"):
        load_pgt(tmp_path / "text.pgt")
    (tmp_path / "empty.pgt").write_bytes(b"")
    with pytest.raises(ModelFileError, match="it is empty"):
        load_pgt(tmp_path / "empty.pgt")
