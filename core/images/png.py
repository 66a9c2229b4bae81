"""PNG read/write as float arrays in [0, 1] (display space, row 0 = top), via Pillow.

Reading converts every PNG flavour to RGB or RGBA float32: palette (with or without a transparency entry),
greyscale, greyscale+alpha, 1-bit, 8-bit and 16-bit, all at full precision. Pillow would reduce 16-bit colour
and grey+alpha PNGs to 8 bits, so those (non-interlaced) are decoded here with zlib + numpy. Every chunk CRC is
checked, which also catches files cut off after the pixel data. Writing is 8-bit RGB/RGBA, atomic, and keeps a
`.bak` of the file it replaces.
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
MAX_SIDE = 16384  # pixels per side of any image read
MAX_PIXELS = 1 << 26  # 8192 x 8192 (a 4096² atlas is a quarter of it); checked from the header, before decoding
_BAND_BYTES = 1 << 25  # work memory of the 16-bit unfilter per band of rows


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
        try:
            chunks = _png_chunks(data)
            _check_size(chunks)
            deep = _decode_16bit_colour(chunks)
        except _TooLarge as exc:
            raise DataError(f"{path}: image is too large ({exc}); PointGT reads images of up to {MAX_SIDE} pixels "
                            f"per side and {MAX_PIXELS} pixels in all") from exc
        except (ValueError, zlib.error) as exc:
            raise DataError(f"{path}: PNG is truncated or corrupt ({exc}); re-export or re-copy the file") from exc
        except MemoryError as exc:
            raise DataError(f"{path}: not enough memory to decode this image") from exc
        if deep is not None:
            return deep
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
    except MemoryError as exc:
        raise DataError(f"{path}: not enough memory to decode this image") from exc


class _TooLarge(ValueError):
    """The header declares an image beyond MAX_SIDE / MAX_PIXELS."""


def _check_size(chunks) -> None:
    """Refuse PNGs whose IHDR declares more pixels than MAX_PIXELS (or a side beyond MAX_SIDE), before decoding."""
    if not chunks or chunks[0][0] != b"IHDR" or len(chunks[0][1]) != 13:
        raise ValueError("first chunk is not a valid IHDR")
    width, height = struct.unpack(">II", chunks[0][1][:8])
    if width == 0 or height == 0:
        raise ValueError(f"the header declares an empty image ({width}x{height})")
    if width > MAX_SIDE or height > MAX_SIDE or width * height > MAX_PIXELS:
        raise _TooLarge(f"the header declares {width}x{height} pixels")


def _png_chunks(data: bytes) -> list[tuple[bytes, memoryview]]:
    """[(chunk type, payload)] up to IEND, every CRC checked; ValueError on truncation or corruption.
    (Pillow decodes a file whose tail - zlib checksum, IEND - is cut off without complaint.)"""
    pos, view, chunks = len(_SIGNATURE), memoryview(data), []
    while True:
        if pos + 8 > len(data):
            raise ValueError("file ends before its IEND chunk")
        length, kind = struct.unpack(">I4s", data[pos:pos + 8])
        end = pos + 12 + length
        if end > len(data):
            raise ValueError(f"chunk {kind.decode('latin-1')} runs past the end of the file")
        if zlib.crc32(view[pos + 4:end - 4]) & 0xFFFFFFFF != struct.unpack(">I", data[end - 4:end])[0]:
            raise ValueError(f"CRC mismatch in chunk {kind.decode('latin-1')} at byte {pos}")
        chunks.append((kind, view[pos + 8:end - 4]))
        if kind == b"IEND":
            return chunks
        pos = end


def _decode_16bit_colour(chunks) -> np.ndarray | None:
    """Full-precision float32 [H, W, 3|4] for 16-bit RGB / RGBA / grey+alpha non-interlaced PNGs, else None."""
    if not chunks or chunks[0][0] != b"IHDR" or len(chunks[0][1]) != 13:
        raise ValueError("first chunk is not a valid IHDR")
    width, height, depth, colour, _, _, interlace = struct.unpack(">IIBBBBB", chunks[0][1])
    channels = {2: 3, 4: 2, 6: 4}.get(colour)
    if depth != 16 or channels is None or interlace != 0:
        return None  # Pillow reads these at full precision (or interlaced: 8-bit, rare)
    bpp = 2 * channels
    _check_size(chunks)
    expected = height * (1 + width * bpp)
    # max_length caps memory if the stream inflates to more than the header promises.
    raw = zlib.decompressobj().decompress(b"".join(bytes(p) for k, p in chunks if k == b"IDAT"), expected + 1)
    if len(raw) != expected:
        raise ValueError(f"pixel data holds {len(raw)} bytes, expected {expected}")
    rows = np.frombuffer(raw, np.uint8).reshape(height, 1 + width * bpp)
    pixels = _unfilter(rows[:, 0], rows[:, 1:].reshape(height, width, bpp))
    values = pixels.view(">u2").reshape(height, width, channels).astype(np.float32) / np.float32(65535.0)
    if channels == 2:  # grey + alpha
        return np.concatenate([np.repeat(values[..., :1], 3, axis=-1), values[..., 1:]], axis=-1)
    trns = next((p for k, p in chunks if k == b"tRNS"), None)
    if channels == 3 and trns is not None and len(trns) == 6:  # one fully transparent RGB colour
        key = np.frombuffer(bytes(trns), ">u2").astype(np.float32) / np.float32(65535.0)
        alpha = (~np.all(values == key, axis=-1)).astype(np.float32)
        return np.concatenate([values, alpha[..., None]], axis=-1)
    return values


def _unfilter(ftype: np.ndarray, filt: np.ndarray) -> np.ndarray:
    """Undo PNG row filters: ftype [H] in 0..4, filtered bytes [H, W, bpp] -> raw bytes [H, W, bpp] uint8.

    Rows are processed in bands whose work memory stays near _BAND_BYTES whatever the image size (a band's work
    arrays grow with rows x (rows + W)); each band continues from the last row of the one above.
    """
    h, w, bpp = filt.shape
    if np.any(ftype > 4):
        raise ValueError(f"unknown row filter type {int(ftype.max())}")
    band = int(max(1, min(h, _BAND_BYTES // (4 * bpp * (w + 1)))))
    out = np.empty((h, w, bpp), np.uint8)
    above = np.zeros((w, bpp), np.int16)  # the row above the image is zero
    for r0 in range(0, h, band):
        r1 = min(h, r0 + band)
        out[r0:r1] = _unfilter_band(ftype[r0:r1], filt[r0:r1], above)
        above = out[r1 - 1].astype(np.int16)
    return out


def _unfilter_band(ftype: np.ndarray, filt: np.ndarray, above: np.ndarray) -> np.ndarray:
    """_unfilter for rows [B, W, bpp] below the already decoded row `above` [W, bpp].

    Each pixel depends on its left, upper and upper-left neighbours, so the pixels of one anti-diagonal
    (r + x = d) are independent: B + W - 1 vectorised steps instead of a loop over pixels. The work array is
    stored skewed, diag[d + 1, r + 1] = pixel (r, d - r), so each step reads and writes contiguous slices;
    column 0 holds `above` (diag[x, 0] = above[x]); never-written cells are PNG's zero "outside the image".
    """
    h, w, bpp = filt.shape
    r_idx = np.arange(h)[:, None]
    d_idx = r_idx + np.arange(w)[None, :]  # [B, W] diagonal of each pixel
    f_skew = np.zeros((h + w - 1, h, bpp), np.int16)
    f_skew[d_idx, r_idx] = filt
    diag = np.zeros((h + w, h + 1, bpp), np.int16)
    diag[:w, 0] = above
    zero = np.zeros((1, bpp), np.int16)
    # One 0/1 weight per row and filter type: pred = sum_k use[k] * predictor_k (cheaper than np.select).
    use = [(ftype == k).astype(np.int16)[:, None] for k in range(1, 5)]
    for d in range(h + w - 1):
        lo, hi = max(0, d - w + 1), min(h, d + 1)  # rows that have a pixel on this diagonal
        a = diag[d, lo + 1:hi + 1]
        b = diag[d, lo:hi]
        c = diag[d - 1, lo:hi] if d else zero  # pixel (0, 0) has no upper-left neighbour
        p = a + b - c
        pa, pb, pc = np.abs(p - a), np.abs(p - b), np.abs(p - c)
        paeth = np.where((pa <= pb) & (pa <= pc), a, np.where(pb <= pc, b, c))
        pred = use[0][lo:hi] * a + use[1][lo:hi] * b + use[2][lo:hi] * ((a + b) >> 1) + use[3][lo:hi] * paeth
        diag[d + 1, lo + 1:hi + 1] = (f_skew[d, lo:hi] + pred) & 0xFF
    return diag[d_idx + 1, r_idx + 1].astype(np.uint8)


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
