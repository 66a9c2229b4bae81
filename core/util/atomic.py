"""Atomic file writes: a crash or a full disk never leaves a half-written file, and an existing file
is kept as `<name>.bak` before it is replaced (never overwrite a user's file without a backup).

The backup itself is made atomically too: the old file is hard-linked (or, where the file system has no hard
links, copied and synced) to a temporary name and then renamed onto `<name>.bak`, so a full disk or an interrupt
leaves either the previous `.bak` or the new one, never a truncated one. A write that fails raises OutputError
(an OSError that is also a PointGTError), whose message names the file and says that the old one is unchanged.
"""
from __future__ import annotations

import contextlib
import errno
import os
import shutil
import tempfile
from pathlib import Path

from core.util.errors import PointGTError


class OutputError(PointGTError, OSError):
    """Writing an output file failed (disk full, file size limit, permissions); the previous file is unchanged."""

    def __str__(self) -> str:  # the message alone, without OSError's "[Errno N]" prefix
        return self.strerror if self.strerror else super().__str__()


def _reason(exc: OSError) -> str:
    if exc.errno in (errno.ENOSPC, errno.EDQUOT):
        return "the disk is full"
    if exc.errno == errno.EFBIG:
        return "the file size limit was reached"
    return exc.strerror or str(exc)


def _output_error(path: Path, exc: OSError, what: str = "") -> OutputError:
    err = OutputError(exc.errno, f"{path}: could not write{what} ({_reason(exc)}: {exc}); the existing file and "
                                 "its .bak were left as they were")
    err.__cause__ = exc
    return err


def backup_file(path: str | os.PathLike) -> Path | None:
    """Atomically make `<path>.bak` a copy of `path` (when it exists); returns the .bak path or None.
    Raises OutputError (the previous .bak kept) when no copy can be made."""
    path = Path(path)
    if not path.is_file():
        return None
    bak = path.with_name(path.name + ".bak")
    fd, tmp = tempfile.mkstemp(prefix=f".{bak.name}.", suffix=".part", dir=path.parent)
    os.close(fd)
    try:
        try:
            os.unlink(tmp)
            os.link(path, tmp)  # no data copied: the old file's bytes stay where they are
        except OSError:
            shutil.copy2(path, tmp)
            with open(tmp, "rb+") as fh:
                os.fsync(fh.fileno())
        os.replace(tmp, bak)
    except OSError as exc:
        raise _output_error(path, exc, " the backup .bak") from exc
    finally:
        if os.path.lexists(tmp):
            os.unlink(tmp)
    return bak


def check_output_file(path: str | os.PathLike, flag: str) -> Path:
    """Before any work: `path` must be writable as a file (not a folder, its folder not under a file).
    Raises InputError naming `flag` otherwise. Returns the path."""
    from core.util.errors import InputError

    path = Path(path)
    if path.is_dir():
        raise InputError(f"{flag} {path}: is a folder; give a file name")
    if path.exists() and not path.is_file():
        raise InputError(f"{flag} {path}: is not a regular file (a device or pipe); give a file name")
    _check_parent(path.parent, flag, path)
    return path


def check_output_dir(path: str | os.PathLike, flag: str) -> Path:
    """Before any work: `path` must be an existing folder or creatable as one. Raises InputError naming `flag`."""
    from core.util.errors import InputError

    path = Path(path)
    if path.exists() and not path.is_dir():
        raise InputError(f"{flag} {path}: is a file, not a folder; give a folder")
    _check_parent(path if path.exists() else path.parent, flag, path)
    return path


def _check_parent(folder: Path, flag: str, path: Path) -> None:
    from core.util.errors import InputError

    probe = folder
    while not probe.exists():  # the nearest existing ancestor decides whether the folders can be created
        if probe.parent == probe:
            break
        probe = probe.parent
    if probe.exists() and not probe.is_dir():
        raise InputError(f"{flag} {path}: {probe} is a file, so no folder can be made there")
    if probe.exists() and not os.access(probe, os.W_OK | os.X_OK):
        raise InputError(f"{flag} {path}: no permission to write in {probe}")


@contextlib.contextmanager
def atomic_path(path: str | os.PathLike, backup: bool = True):
    """Yield a temporary path next to `path`; on success move it into place (keeping a .bak).
    OSErrors while writing or moving become OutputError naming `path`; the old file stays as it was."""
    path = Path(path)
    try:
        path.parent.mkdir(parents=True, exist_ok=True)
        fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.", suffix=".part", dir=path.parent)
    except OSError as exc:
        raise _output_error(path, exc) from exc
    os.close(fd)
    # mkstemp creates 0600 files; give the result the permissions a plain open() would (0666 minus umask).
    umask = os.umask(0)
    os.umask(umask)
    os.chmod(tmp, 0o666 & ~umask)
    try:
        try:
            yield Path(tmp)
        except OutputError:
            raise
        except OSError as exc:
            raise _output_error(path, exc) from exc
        if backup:
            backup_file(path)
        try:
            os.replace(tmp, path)
        except OSError as exc:
            raise _output_error(path, exc) from exc
    finally:
        if os.path.exists(tmp):
            os.unlink(tmp)


def atomic_write_bytes(path: str | os.PathLike, data: bytes, backup: bool = True) -> None:
    with atomic_path(path, backup=backup) as tmp:
        with open(tmp, "wb") as fh:
            fh.write(data)
            fh.flush()
            os.fsync(fh.fileno())


def atomic_write_text(path: str | os.PathLike, text: str, backup: bool = True) -> None:
    atomic_write_bytes(path, text.encode("utf-8"), backup=backup)
