"""PNG read/write as float arrays in [0, 1] (display space, row 0 = top), via Pillow.

Reading converts every PNG flavour to RGB or RGBA float32: palette (with or without a transparency entry),
greyscale, greyscale+alpha, 1-bit, 8-bit and 16-bit. 16-bit greyscale keeps its full precision; Pillow hands
16-bit *colour* PNGs over already reduced to 8 bits per channel, so those come back with 1/255 steps.
Writing is 8-bit RGB/RGBA, atomic, and keeps a `.bak` of the file it replaces.
"""
from __future__ import annotations

import io
import os
import struct
import warnings
import zlib
from pathlib import Path

import numpy as np

from core.util.atomic import atomic_path
from core.util.errors import DataError, InputError

# Modes Pillow can hand us, and the mode we convert them to before going to numpy.
_TO_RGB = {"1", "L", "P", "RGB", "CMYK", "YCbCr", "LAB", "HSV"}
_TO_RGBA = {"LA", "La", "PA", "RGBA", "RGBa"}
_SIXTEEN_BIT_GREY = {"I;16", "I;16B", "I;16L", "I;16N", "I"}
_SIGNATURE = b"\x89PNG\r\n\x1a\n"


def read_png(path: str | os.PathLike) -> np.ndarray:
    """Read an image file as float32 [H, W, C] in [0, 1]; C = 4 when the file has alpha, else 3.

    Raises DataError naming the file when it is missing, not an image, or truncated/corrupt.
    """
    from PIL import Image, UnidentifiedImageError

    path = Path(path)
    if not path.is_file():
        what = "is a folder, not an image file" if path.is_dir() else "does not exist"
        raise DataError(f"{path}: image {what}; check the path (frames' file_path are relative to the dataset folder)")
    data = path.read_bytes()
    if data.startswith(_SIGNATURE):
        problem = _png_structure_problem(data)
        if problem:
            raise DataError(f"{path}: PNG is truncated or corrupt ({problem}); re-export or re-copy the file")
    try:
        with warnings.catch_warnings():
            warnings.simplefilter("error", Image.DecompressionBombWarning)
            with Image.open(io.BytesIO(data)) as img:
                img.load()  # decode now so truncation/corruption surfaces here, inside the try
                return _to_float(img, path)
    except UnidentifiedImageError as exc:
        raise DataError(f"{path}: not a readable image (unknown or corrupt header); re-export it as PNG") from exc
    except (Image.DecompressionBombError, Image.DecompressionBombWarning) as exc:
        raise DataError(f"{path}: image is implausibly large ({exc}); check the file") from exc
    except (OSError, SyntaxError, ValueError) as exc:
        # Pillow reports truncated data and bad CRC/zlib streams as OSError/SyntaxError/ValueError.
        raise DataError(f"{path}: image is truncated or corrupt ({exc}); re-export or re-copy the file") from exc


def _png_structure_problem(data: bytes) -> str | None:
    """Walk the PNG chunks and check every CRC and the final IEND. Pillow decodes a file whose tail
    (zlib checksum, IEND) is cut off without complaint, so truncation is caught here."""
    pos, view = len(_SIGNATURE), memoryview(data)  # view: CRC over slices without copying
    while True:
        if pos + 8 > len(data):
            return "file ends before its IEND chunk"
        length, kind = struct.unpack(">I4s", data[pos:pos + 8])
        end = pos + 12 + length
        if end > len(data):
            return f"chunk {kind!r} runs past the end of the file"
        crc = struct.unpack(">I", data[end - 4:end])[0]
        if zlib.crc32(view[pos + 4:end - 4]) & 0xFFFFFFFF != crc:
            return f"CRC mismatch in chunk {kind!r} at byte {pos}"
        if kind == b"IEND":
            return None
        pos = end


def _to_float(img, path: Path) -> np.ndarray:
    mode = img.mode
    if mode in _SIXTEEN_BIT_GREY:
        # 16-bit greyscale ("I" is how older Pillow versions hand it over): full 0..65535 range.
        grey = np.clip(np.asarray(img).astype(np.float32) / 65535.0, 0.0, 1.0)
        return np.repeat(grey[..., None], 3, axis=-1)
    if mode == "F":
        grey = np.clip(np.nan_to_num(np.asarray(img, dtype=np.float32)), 0.0, 1.0)
        return np.repeat(grey[..., None], 3, axis=-1)
    has_alpha = mode in _TO_RGBA or (mode in {"P", "L", "RGB"} and "transparency" in img.info)
    if mode not in _TO_RGB and mode not in _TO_RGBA:
        raise DataError(f"{path}: unsupported image mode {mode!r}; re-export it as 8-bit RGB or RGBA PNG")
    arr = np.asarray(img.convert("RGBA" if has_alpha else "RGB"))
    return arr.astype(np.float32) / np.float32(255.0)  # division, not * (1/255): exact inverse of write_png


def write_png(path: str | os.PathLike, image, backup: bool = True, strict: bool = False) -> Path:
    """Write float [H, W, 3] or [H, W, 4] (also [H, W] or [H, W, 1] greyscale) in [0, 1] as an 8-bit PNG.

    Values are rounded to the nearest of 256 levels. With strict=False, NaN becomes 0 and values outside
    [0, 1] (including ±inf) are clipped; with strict=True they raise InputError instead. The write is atomic
    and an existing file is kept as `<name>.bak` when backup=True. Returns the path written.
    """
    from PIL import Image

    path = Path(path)
    arr = np.asarray(image)
    if arr.ndim == 3 and arr.shape[-1] == 1:
        arr = arr[..., 0]
    if not (arr.ndim == 2 or (arr.ndim == 3 and arr.shape[-1] in (3, 4))):
        raise InputError(f"{path}: expected an image array [H, W, 3|4] (or [H, W]), got shape {tuple(arr.shape)}")
    if arr.shape[0] == 0 or arr.shape[1] == 0:
        raise InputError(f"{path}: cannot write an empty image of shape {tuple(arr.shape)}")
    if arr.dtype == np.bool_ or not (np.issubdtype(arr.dtype, np.floating) or np.issubdtype(arr.dtype, np.integer)):
        raise InputError(f"{path}: expected float values in [0, 1], got dtype {arr.dtype}")
    arr = arr.astype(np.float32, copy=False)
    bad_nan = np.isnan(arr)
    bad_range = ~bad_nan & ((arr < 0.0) | (arr > 1.0))
    if strict and (bad_nan.any() or bad_range.any()):
        raise InputError(f"{path}: image has {int(bad_nan.sum())} NaN values and {int(bad_range.sum())} values "
                         "outside [0, 1]; fix the source or call write_png(..., strict=False) to clip them")
    arr = np.clip(np.where(bad_nan, 0.0, arr), 0.0, 1.0)
    u8 = np.rint(arr * 255.0).astype(np.uint8)
    with atomic_path(path, backup=backup) as tmp:
        with open(tmp, "wb") as fh:
            # Mode follows the shape: [H, W] -> L, [H, W, 3] -> RGB, [H, W, 4] -> RGBA.
            Image.fromarray(u8).save(fh, format="PNG")
            fh.flush()
            os.fsync(fh.fileno())
    return path
