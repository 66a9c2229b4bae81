"""The `.pgt` model file: one uncompressed ZIP archive of a JSON header and raw little-endian arrays.

    pointgt.json        {"magic": "pointgt-model", "format_version": 1, "producer": "pointgt 0.1.0",
                         "meta": {...free JSON...},
                         "arrays": {"points/xyz": {"dtype": "float32", "shape": [N, 3],
                                                   "member": "arrays/00000.bin", "sha256": "..."}, ...},
                         "allow_nonfinite": [names of float arrays allowed to hold NaN/inf]}
    arrays/00000.bin    the array's bytes, C order, little-endian
    ...

Loading never executes code (no pickle, no torch.load) and uses numpy only, so Blender's bundled Python can
read models without torch. Every problem raises ModelFileError saying what to do.
"""
from __future__ import annotations

import hashlib
import json
import os
import re
import zipfile
from pathlib import Path

import numpy as np

from core.util.atomic import atomic_path
from core.util.errors import InputError, ModelFileError

MAGIC = "pointgt-model"
FORMAT_VERSION = 1
MIN_FORMAT_VERSION = 1  # oldest format this code still reads
HEADER = "pointgt.json"
DTYPES = ("float32", "float16", "int32", "int64", "uint8", "bool")
_NAME = re.compile(r"^[A-Za-z0-9_.\-]+(/[A-Za-z0-9_.\-]+)*$")
_ZIP_TIME = (1980, 1, 1, 0, 0, 0)  # fixed member timestamps: saving the same model twice gives the same bytes
_CHUNK = 1 << 22
# zip flag bits PointGT never writes and zipfile cannot read without more (a password, patch data): encrypted,
# compressed patched data, strong encryption; a member that claims one is damaged
_FOREIGN_FLAGS = 0x1 | 0x20 | 0x40
# what zipfile raises on a damaged archive or member besides BadZipFile: NotImplementedError for a zip version or
# flags it does not support, RuntimeError for an encrypted member, ValueError (UnicodeDecodeError) for a member name
# a damaged flag marks as UTF-8
_ZIP_READ_ERRORS = (zipfile.BadZipFile, EOFError, OSError, zipfile.LargeZipFile, NotImplementedError, RuntimeError,
                    ValueError)


def _zipinfo(member: str) -> zipfile.ZipInfo:
    info = zipfile.ZipInfo(member, _ZIP_TIME)
    info.compress_type = zipfile.ZIP_STORED
    info.external_attr = 0o644 << 16  # rw-r--r-- if someone unzips it
    return info


def producer_version() -> str:
    try:
        from importlib.metadata import version
        return f"pointgt {version('pointgt')}"
    except Exception:  # the Blender add-on may carry core/ without package metadata
        return "pointgt (unknown version)"


# ----------------------------------------------------------------------------------------------------- saving

def save_pgt(path: str | os.PathLike, arrays: dict[str, np.ndarray], meta: dict | None = None, backup: bool = True,
             allow_nonfinite=()) -> Path:
    """Write `arrays` ({name: ndarray of any shape}) and JSON-serialisable `meta` to one .pgt file.

    Names are slash-separated paths of [A-Za-z0-9_.-] ("points/xyz", "net/attn.0.weight"). Dtypes must be one of
    DTYPES (convert float64 with .astype(np.float32)). Float arrays holding NaN/inf are rejected unless their name
    is in `allow_nonfinite` (a NaN in a model is almost always a training bug). The write is atomic; the file it
    replaces is kept as `<name>.bak` when backup=True. Returns the path written.
    """
    path = Path(path)
    meta = {} if meta is None else meta
    allow_nonfinite = sorted(set(allow_nonfinite))
    prepared = _prepare_arrays(path, arrays, allow_nonfinite)
    index = {}
    for i, (name, arr) in enumerate(prepared.items()):
        index[name] = {"dtype": arr.dtype.name, "shape": list(arr.shape), "member": f"arrays/{i:05d}.bin",
                       "sha256": hashlib.sha256(_raw(arr)).hexdigest()}
    header = {"magic": MAGIC, "format_version": FORMAT_VERSION, "producer": producer_version(), "meta": meta,
              "arrays": index, "allow_nonfinite": [n for n in allow_nonfinite if n in index]}
    try:
        header_bytes = json.dumps(header, indent=1, allow_nan=False, ensure_ascii=False).encode("utf-8")
    except (TypeError, ValueError) as exc:
        raise InputError(f"{path}: meta must be plain JSON (dict/list/str/int/finite float/bool/None): {exc}") from exc
    with atomic_path(path, backup=backup) as tmp:
        with zipfile.ZipFile(tmp, "w", compression=zipfile.ZIP_STORED, allowZip64=True) as zf:
            zf.writestr(_zipinfo(HEADER), header_bytes)
            for name, arr in prepared.items():
                _write_member(zf, index[name]["member"], arr)
        with open(tmp, "rb+") as fh:
            os.fsync(fh.fileno())
    return path


def _prepare_arrays(path: Path, arrays: dict, allow_nonfinite: list[str]) -> dict[str, np.ndarray]:
    """Validate names/dtypes/values; return C-contiguous little-endian arrays in a stable (sorted) order."""
    if not isinstance(arrays, dict):
        raise InputError(f"{path}: arrays must be a dict of name -> numpy array, got {type(arrays).__name__}")
    for name in arrays:
        if not isinstance(name, str) or not _NAME.match(name) or len(name) > 256 \
                or any(part in (".", "..") for part in name.split("/")):
            raise InputError(f"{path}: array name {name!r} is invalid; use slash-separated parts of "
                             "letters, digits, '_', '.', '-' (e.g. 'net/attn.0.weight')")
    out = {}
    for name in sorted(arrays):
        arr = arrays[name]
        if not isinstance(arr, np.ndarray):
            raise InputError(f"{path}: array {name!r} is a {type(arr).__name__}, not a numpy array; "
                             "convert tensors with .detach().cpu().numpy()")
        if arr.dtype.name not in DTYPES:
            raise InputError(f"{path}: array {name!r} has dtype {arr.dtype}; allowed: {', '.join(DTYPES)} "
                             "(e.g. .astype(np.float32))")
        if arr.dtype.kind == "f" and name not in allow_nonfinite and not np.isfinite(arr).all():
            raise InputError(f"{path}: array {name!r} holds {int((~np.isfinite(arr)).sum())} NaN/inf values; "
                             "fix the model or list the name in allow_nonfinite")
        out[name] = arr.astype(arr.dtype.newbyteorder("<"), order="C", copy=False)  # keeps 0-d shape
    return out


def _raw(arr: np.ndarray) -> memoryview:
    """The bytes of a C-contiguous array without copying (0-d and empty arrays included)."""
    return memoryview(arr.reshape(-1)).cast("B")


def _write_member(zf: zipfile.ZipFile, member: str, arr: np.ndarray) -> None:
    info = _zipinfo(member)
    info.file_size = arr.nbytes
    with zf.open(info, "w", force_zip64=arr.nbytes >= (1 << 31)) as fh:
        fh.write(_raw(arr))


# ---------------------------------------------------------------------------------------------------- loading

class PgtFile:
    """Lazy reader: the header is read and checked on open; arrays are read (and checksummed) on demand.

    with PgtFile(path) as f:
        f.meta, f.names, f.shape("points/xyz"), f.read("points/xyz")
    """

    def __init__(self, path: str | os.PathLike):
        self.path = Path(path)
        self._zip = _open_zip(self.path)
        try:
            self.header = _read_header(self.path, self._zip)
        except BaseException:
            self._zip.close()
            raise
        self.meta: dict = self.header["meta"]
        self.index: dict = self.header["arrays"]
        self.allow_nonfinite: set[str] = set(self.header.get("allow_nonfinite", []))

    @property
    def names(self) -> list[str]:
        return list(self.index)

    def shape(self, name: str) -> tuple[int, ...]:
        return tuple(self._entry(name)["shape"])

    def dtype(self, name: str) -> np.dtype:
        return np.dtype(self._entry(name)["dtype"])

    def read(self, name: str) -> np.ndarray:
        """The array stored under `name` (native byte order, writable), after its sha256 was verified and, for
        float arrays not listed in the header's allow_nonfinite, after checking that it holds no NaN/inf."""
        entry = self._entry(name)
        dtype = np.dtype(entry["dtype"]).newbyteorder("<")
        try:  # the size was checked against the archive on open, so only a real shortage of memory fails here
            arr = np.empty(tuple(entry["shape"]), dtype=dtype)
        except MemoryError as exc:
            raise ModelFileError(f"{self.path}: array {name!r} {entry['shape']} needs more memory than is "
                                 "available; close other programs or use a machine with more memory") from exc
        buf = _raw(arr)
        digest = hashlib.sha256()
        try:
            with self._zip.open(entry["member"]) as fh:
                pos = 0
                while pos < len(buf):
                    n = fh.readinto(buf[pos:pos + _CHUNK])
                    if not n:
                        break
                    digest.update(buf[pos:pos + n])
                    pos += n
                extra = fh.read(1)
        except _ZIP_READ_ERRORS as exc:
            raise ModelFileError(f"{self.path}: array {name!r} is corrupt ({exc}); {_recover_hint(self.path)}") from exc
        if pos != len(buf) or extra:
            raise ModelFileError(f"{self.path}: array {name!r} has the wrong size for shape {entry['shape']}; "
                                 f"{_recover_hint(self.path)}")
        if digest.hexdigest() != entry["sha256"]:
            raise ModelFileError(f"{self.path}: array {name!r} is corrupt (sha256 checksum mismatch); "
                                 f"{_recover_hint(self.path)}")
        if arr.dtype.kind == "f" and name not in self.allow_nonfinite:
            bad = int(arr.size - np.count_nonzero(np.isfinite(arr)))
            if bad:
                raise ModelFileError(f"{self.path}: array {name!r} holds {bad} NaN/inf values, which the file does "
                                     f"not allow for it (a damaged or badly trained model); {_recover_hint(self.path)}")
        return arr.astype(arr.dtype.newbyteorder("="), copy=False)

    def _entry(self, name: str) -> dict:
        if name not in self.index:
            raise ModelFileError(f"{self.path}: has no array {name!r}; it holds {_summary(self.names)}")
        return self.index[name]

    def close(self) -> None:
        self._zip.close()

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self.close()


def load_pgt(path: str | os.PathLike, names=None) -> tuple[dict[str, np.ndarray], dict]:
    """Read arrays and meta. names=None reads every array; otherwise a list of names, where an entry ending in
    "/" selects every array under that prefix ("net/"). Returns ({name: ndarray}, meta)."""
    with PgtFile(path) as f:
        wanted = f.names if names is None else _select(f, names)
        return {name: f.read(name) for name in wanted}, f.meta


def read_meta(path: str | os.PathLike) -> dict:
    """Only the free `meta` dict (configs, scene info): reads the header, none of the arrays."""
    with PgtFile(path) as f:
        return f.meta


def _select(f: PgtFile, names) -> list[str]:
    if isinstance(names, str):
        names = [names]
    out = []
    for want in names:
        if want.endswith("/"):
            group = [n for n in f.names if n.startswith(want)]
            if not group:
                raise ModelFileError(f"{f.path}: has no arrays under {want!r}; it holds {_summary(f.names)}")
            out += group
        else:
            f._entry(want)
            out.append(want)
    return list(dict.fromkeys(out))


def _summary(names: list[str]) -> str:
    return (", ".join(names[:8]) + (f" and {len(names) - 8} more" if len(names) > 8 else "")) if names else "none"


def _recover_hint(path: Path) -> str:
    bak = path.with_name(path.name + ".bak")
    where = f"restore the previous version from {bak.name} or " if bak.exists() else ""
    return f"{where}re-export the model"


def _open_zip(path: Path) -> zipfile.ZipFile:
    if not path.exists():
        raise ModelFileError(f"{path}: model file not found; check the path (a .pgt is made by `pointgt fit`)")
    if path.is_dir():
        raise ModelFileError(f"{path}: is a folder, not a .pgt model file")
    if not path.is_file():
        raise ModelFileError(f"{path}: is not a regular file (a device, pipe or socket), not a .pgt model file")
    with open(path, "rb") as fh:
        head = fh.read(4)
    try:
        return zipfile.ZipFile(path, "r")
    except _ZIP_READ_ERRORS as exc:
        if head[:1] == b"\x80":
            what = "it looks like a Python pickle; PointGT never loads pickles (they can run code)"
        elif head.startswith(b"PK") and isinstance(exc, (NotImplementedError, RuntimeError, ValueError)):
            what = f"its zip directory is damaged ({exc})"
        elif head.startswith(b"PK"):
            what = "it is a zip archive whose end is missing (truncated: interrupted save or incomplete copy)"
        elif not head:
            what = "it is empty"
        else:
            what = "it is not a zip archive"
        raise ModelFileError(f"{path}: not a readable .pgt model file: {what}; {_recover_hint(path)}") from exc


def _refuse_foreign_flags(path: Path, info: zipfile.ZipInfo, what: str) -> None:
    """A member whose zip flags claim encryption or patch data (_FOREIGN_FLAGS: PointGT never writes them, and
    zipfile fails on them with NotImplementedError / RuntimeError) is a damaged archive: ModelFileError."""
    if info.flag_bits & _FOREIGN_FLAGS:
        raise ModelFileError(f"{what} claims to be encrypted or patched, which PointGT never writes; the archive is "
                             f"corrupt; {_recover_hint(path)}")


def _read_header(path: Path, zf: zipfile.ZipFile) -> dict:
    members = set(zf.namelist())
    if HEADER not in members:
        torchish = any(m.endswith("data.pkl") for m in members)
        what = "it looks like a PyTorch checkpoint, which PointGT never unpickles" if torchish else \
            f"it is some other zip archive ({_summary(sorted(members))})"
        raise ModelFileError(f"{path}: not a .pgt model file (no {HEADER} inside): {what}")
    info = zf.getinfo(HEADER)
    if info.file_size > 64 << 20:
        raise ModelFileError(f"{path}: {HEADER} is implausibly large ({info.file_size} bytes); the file is corrupt")
    _refuse_foreign_flags(path, info, f"{path}: {HEADER}")
    try:
        raw = zf.read(HEADER)
    except _ZIP_READ_ERRORS as exc:
        raise ModelFileError(f"{path}: {HEADER} is corrupt ({exc}); {_recover_hint(path)}") from exc
    try:
        header = json.loads(raw.decode("utf-8"))
    except (UnicodeDecodeError, ValueError) as exc:
        raise ModelFileError(f"{path}: {HEADER} is not valid JSON ({exc}); {_recover_hint(path)}") from exc
    except RecursionError as exc:
        raise ModelFileError(f"{path}: {HEADER} is nested too deeply to be a PointGT header; the file is corrupt or "
                             "was not written by PointGT") from exc
    if not isinstance(header, dict) or header.get("magic") != MAGIC:
        raise ModelFileError(f"{path}: not a PointGT model (magic is "
                             f"{header.get('magic') if isinstance(header, dict) else None!r}, "
                             f"expected {MAGIC!r})")
    version = header.get("format_version")
    producer = header.get("producer", "unknown producer")
    if isinstance(version, bool) or not isinstance(version, int):
        raise ModelFileError(f"{path}: format_version {version!r} is not an integer; the header is corrupt")
    if version > FORMAT_VERSION:
        raise ModelFileError(f"{path}: made by a newer PointGT ({producer}, format {version}; this reader supports "
                             f"up to {FORMAT_VERSION}); update the add-on / pointgt package")
    if version < MIN_FORMAT_VERSION:
        raise ModelFileError(f"{path}: format {version} ({producer}) is older than this PointGT supports "
                             f"(oldest: {MIN_FORMAT_VERSION}); re-export the model with an older release")
    if not isinstance(header.get("meta"), dict):
        raise ModelFileError(f"{path}: header 'meta' must be an object; the header is corrupt")
    index = header.get("arrays")
    if not isinstance(index, dict):
        raise ModelFileError(f"{path}: header 'arrays' must be an object; the header is corrupt")
    allow = header.get("allow_nonfinite", [])
    if not isinstance(allow, list) or not all(isinstance(n, str) for n in allow):
        raise ModelFileError(f"{path}: header 'allow_nonfinite' must be a list of array names; the header is corrupt")
    file_size = path.stat().st_size
    total = 0
    for name, entry in index.items():
        total += _check_entry(path, zf, name, entry, members, file_size)
    if total > file_size:  # members may not overlap: together they cannot hold more bytes than the file
        raise ModelFileError(f"{path}: the arrays declare {total} bytes but the file has {file_size}; the archive "
                             f"is corrupt or crafted; {_recover_hint(path)}")
    return header


def _check_entry(path: Path, zf: zipfile.ZipFile, name: str, entry, members: set[str], file_size: int) -> int:
    """Check one index entry against the archive (before anything is allocated); returns its size in bytes."""
    where = f"{path}: array {name!r}"
    if not isinstance(entry, dict):
        raise ModelFileError(f"{where}: index entry is not an object; the header is corrupt")
    dtype = entry.get("dtype")
    if dtype not in DTYPES:
        raise ModelFileError(f"{where}: dtype {dtype!r} is not allowed (allowed: {', '.join(DTYPES)}); "
                             "the file was not written by PointGT or is corrupt")
    shape = entry.get("shape")
    if not isinstance(shape, list) or not all(isinstance(s, int) and not isinstance(s, bool) and s >= 0
                                              for s in shape):
        raise ModelFileError(f"{where}: shape {shape!r} is not a list of non-negative integers; header corrupt")
    member, digest = entry.get("member"), entry.get("sha256")
    if not isinstance(digest, str) or not re.fullmatch(r"[0-9a-f]{64}", digest):
        raise ModelFileError(f"{where}: missing or malformed sha256 in the header; the header is corrupt")
    if not isinstance(member, str) or member not in members:
        raise ModelFileError(f"{where}: its data member {member!r} is missing from the archive; "
                             f"{_recover_hint(path)}")
    expected = int(np.prod(shape, dtype=object)) * np.dtype(dtype).itemsize
    info = zf.getinfo(member)
    actual = info.file_size
    if actual != expected:
        raise ModelFileError(f"{where}: data member holds {actual} bytes but dtype {dtype} and shape {shape} "
                             f"need {expected}; {_recover_hint(path)}")
    _refuse_foreign_flags(path, info, f"{where}: its data member")
    # Sizes in the zip directory are claims: a stored member's bytes must really be inside the file.
    if info.compress_type != zipfile.ZIP_STORED or info.compress_size != actual \
            or info.header_offset + info.compress_size > file_size:
        raise ModelFileError(f"{where}: data member claims {actual} bytes (stored as {info.compress_size} at byte "
                             f"{info.header_offset}) that the {file_size}-byte file does not hold; the archive is "
                             f"corrupt or crafted; {_recover_hint(path)}")
    return expected
