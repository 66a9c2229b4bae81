import struct
import zlib

import numpy as np
import pytest
from PIL import Image

from core.images.png import read_png, write_png
from core.util.errors import DataError, InputError


def _rgba_u8(h=5, w=7, seed=0):
    return np.random.default_rng(seed).integers(0, 256, size=(h, w, 4), dtype=np.uint8)


def test_8bit_rgba_and_rgb_read_exactly(tmp_path):
    u8 = _rgba_u8()
    Image.fromarray(u8).save(tmp_path / "a.png")
    Image.fromarray(u8[..., :3]).save(tmp_path / "b.png")
    a, b = read_png(tmp_path / "a.png"), read_png(tmp_path / "b.png")
    assert a.dtype == np.float32 and a.shape == (5, 7, 4) and b.shape == (5, 7, 3)
    np.testing.assert_array_equal(np.rint(a * 255).astype(np.uint8), u8)
    np.testing.assert_array_equal(b, a[..., :3])


def test_write_read_round_trip_is_exact_on_the_8bit_grid(tmp_path):
    img = _rgba_u8(6, 4, seed=1).astype(np.float32) / 255.0
    write_png(tmp_path / "x.png", img)
    np.testing.assert_array_equal(read_png(tmp_path / "x.png"), img)
    write_png(tmp_path / "y.png", img[..., :3])
    np.testing.assert_array_equal(read_png(tmp_path / "y.png"), img[..., :3])


def test_greyscale_palette_and_one_bit_become_rgb(tmp_path):
    g = np.arange(12, dtype=np.uint8).reshape(3, 4) * 20
    Image.fromarray(g, mode="L").save(tmp_path / "g.png")
    out = read_png(tmp_path / "g.png")
    assert out.shape == (3, 4, 3)
    np.testing.assert_allclose(out[..., 1], g / 255.0, atol=1e-7)

    pal = Image.fromarray(g, mode="L").convert("P")
    pal.save(tmp_path / "p.png")
    assert Image.open(tmp_path / "p.png").mode == "P"
    np.testing.assert_allclose(read_png(tmp_path / "p.png")[..., 0], g / 255.0, atol=1e-7)

    Image.fromarray(g > 100).save(tmp_path / "bw.png")
    np.testing.assert_array_equal(read_png(tmp_path / "bw.png")[..., 2], (g > 100).astype(np.float32))


def test_palette_with_transparency_gets_alpha(tmp_path):
    img = Image.new("P", (4, 2))
    img.putpalette([255, 0, 0, 0, 255, 0] + [0] * 762)
    img.putdata([0, 1, 0, 1, 1, 1, 0, 0])
    img.save(tmp_path / "t.png", transparency=1)
    out = read_png(tmp_path / "t.png")
    assert out.shape == (2, 4, 4)
    np.testing.assert_array_equal(out[0, :, 3], [1, 0, 1, 0])
    np.testing.assert_array_equal(out[0, 0, :3], [1, 0, 0])


def test_greyscale_alpha_becomes_rgba(tmp_path):
    la = np.stack([np.full((2, 3), 200, np.uint8), np.full((2, 3), 51, np.uint8)], axis=-1)
    Image.fromarray(la, mode="LA").save(tmp_path / "la.png")
    out = read_png(tmp_path / "la.png")
    assert out.shape == (2, 3, 4)
    np.testing.assert_allclose(out[0, 0], [200 / 255] * 3 + [0.2], atol=1e-7)


def test_16bit_greyscale_keeps_full_precision(tmp_path):
    g = np.array([[0, 1, 257, 65535], [1000, 30000, 40000, 65534]], dtype=np.uint16)
    Image.fromarray(g).save(tmp_path / "g16.png")
    out = read_png(tmp_path / "g16.png")
    assert out.shape == (2, 4, 3)
    np.testing.assert_allclose(out[..., 0], g / 65535.0, rtol=0, atol=1e-7)


def _chunk(kind: bytes, data: bytes) -> bytes:
    return struct.pack(">I", len(data)) + kind + data + struct.pack(">I", zlib.crc32(kind + data) & 0xFFFFFFFF)


def encode_png16(values: np.ndarray, colour_type: int, filters, extra: bytes = b"") -> bytes:
    """Reference encoder: uint16 [H, W, C] -> PNG bytes, row r filtered with filters[r % len(filters)].

    Filtering uses only the raw bytes, so unlike decoding it needs no sequential pass."""
    h, w, c = values.shape
    bpp = 2 * c
    raw = values.astype(">u2").view(np.uint8).reshape(h, w * bpp).astype(np.int32)
    a = np.pad(raw, ((0, 0), (bpp, 0)))[:, :-bpp]                 # left neighbour
    b = np.pad(raw, ((1, 0), (0, 0)))[:-1]                        # upper neighbour
    cc = np.pad(raw, ((1, 0), (bpp, 0)))[:-1, :-bpp]               # upper-left neighbour
    p = a + b - cc
    pa, pb, pc = abs(p - a), abs(p - b), abs(p - cc)
    paeth = np.where((pa <= pb) & (pa <= pc), a, np.where(pb <= pc, b, cc))
    preds = [np.zeros_like(raw), a, b, (a + b) // 2, paeth]
    types = np.array([filters[r % len(filters)] for r in range(h)])
    filtered = ((raw - np.stack(preds)[types, np.arange(h)]) % 256).astype(np.uint8)
    rows = np.concatenate([types[:, None].astype(np.uint8), filtered], axis=1)
    return (b"\x89PNG\r\n\x1a\n" + _chunk(b"IHDR", struct.pack(">IIBBBBB", w, h, 16, colour_type, 0, 0, 0))
            + extra + _chunk(b"IDAT", zlib.compress(rows.tobytes())) + _chunk(b"IEND", b""))


@pytest.mark.parametrize("colour_type,channels", [(2, 3), (6, 4), (4, 2)])
@pytest.mark.parametrize("filters", [[0], [1], [2], [3], [4], [0, 1, 2, 3, 4, 4, 3]])
def test_16bit_colour_is_read_at_full_precision(tmp_path, colour_type, channels, filters):
    vals = np.random.default_rng(colour_type).integers(0, 65536, size=(9, 6, channels), dtype=np.uint16)
    vals[0, 0] = 65535
    (tmp_path / "c16.png").write_bytes(encode_png16(vals, colour_type, filters))
    out = read_png(tmp_path / "c16.png")
    expect = vals.astype(np.float64) / 65535.0
    if channels == 2:
        expect = np.concatenate([expect[..., :1].repeat(3, -1), expect[..., 1:]], axis=-1)
    assert out.dtype == np.float32 and out.shape == (9, 6, 4 if channels != 3 else 3)
    np.testing.assert_allclose(out, expect, rtol=0, atol=1e-7)
    # Pillow (8-bit) agrees to within one 8-bit step, a cross-check of the decoder on real filter data.
    np.testing.assert_allclose(np.asarray(Image.open(tmp_path / "c16.png").convert("RGBA" if channels != 3 else "RGB"))
                               / 255.0, out, atol=1.0 / 255 + 1e-6)


def test_16bit_rgb_with_transparent_colour_gets_alpha(tmp_path):
    vals = np.full((2, 3, 3), 1000, dtype=np.uint16)
    vals[1, 2] = (7, 8, 9)
    trns = _chunk(b"tRNS", struct.pack(">HHH", 7, 8, 9))
    (tmp_path / "t16.png").write_bytes(encode_png16(vals, 2, [4], extra=trns))
    out = read_png(tmp_path / "t16.png")
    assert out.shape == (2, 3, 4) and out[..., 3].sum() == 5 and out[1, 2, 3] == 0


def test_16bit_colour_with_bad_pixel_data_is_rejected(tmp_path):
    vals = np.zeros((4, 4, 3), dtype=np.uint16)
    good = encode_png16(vals, 2, [0])
    short = good.replace(struct.pack(">II", 4, 4), struct.pack(">II", 4, 5), 1)  # header promises 5 rows
    ihdr_end = 8 + 8 + 13
    short = short[:8] + _chunk(b"IHDR", short[16:ihdr_end]) + short[ihdr_end + 4:]
    (tmp_path / "short.png").write_bytes(short)
    with pytest.raises(DataError, match=r"short\.png.*pixel data holds"):
        read_png(tmp_path / "short.png")


def test_write_clips_and_zeroes_nan_unless_strict(tmp_path):
    img = np.array([[[np.nan, -0.5, 2.0], [np.inf, -np.inf, 0.5]]], dtype=np.float32)
    write_png(tmp_path / "c.png", img)
    np.testing.assert_allclose(read_png(tmp_path / "c.png"), [[[0, 0, 1], [1, 0, 128 / 255]]], atol=1e-7)
    with pytest.raises(InputError, match="NaN"):
        write_png(tmp_path / "s.png", img, strict=True)
    assert not (tmp_path / "s.png").exists()


def test_write_accepts_greyscale_and_rejects_bad_shapes(tmp_path):
    write_png(tmp_path / "g.png", np.full((3, 2), 0.4))
    assert read_png(tmp_path / "g.png").shape == (3, 2, 3)
    for bad in (np.zeros((3, 2, 2)), np.zeros((3,)), np.zeros((0, 4, 3)), np.zeros((2, 2, 3), dtype=object)):
        with pytest.raises(InputError, match="x.png"):
            write_png(tmp_path / "x.png", bad)


def test_write_keeps_a_backup_of_the_replaced_file(tmp_path):
    p = tmp_path / "img.png"
    write_png(p, np.zeros((2, 2, 3)))
    write_png(p, np.ones((2, 2, 3)))
    assert read_png(p).min() == 1.0 and read_png(p.with_name("img.png.bak")).max() == 0.0
    assert sorted(x.name for x in tmp_path.iterdir()) == ["img.png", "img.png.bak"]  # no temp files left


def test_missing_corrupt_and_truncated_files_name_the_file(tmp_path):
    with pytest.raises(DataError, match=r"nope\.png.*does not exist"):
        read_png(tmp_path / "nope.png")
    with pytest.raises(DataError, match="folder"):
        read_png(tmp_path)
    (tmp_path / "junk.png").write_bytes(b"this is not an image at all")
    with pytest.raises(DataError, match=r"junk\.png.*not a readable image"):
        read_png(tmp_path / "junk.png")
    write_png(tmp_path / "full.png", np.random.default_rng(0).random((64, 64, 4)))
    data = (tmp_path / "full.png").read_bytes()
    for cut in (0, 8, 40, len(data) // 2, len(data) - 20, len(data) - 4):  # -20: only the zlib checksum is lost
        (tmp_path / "cut.png").write_bytes(data[:cut])
        with pytest.raises(DataError, match=r"cut\.png"):
            read_png(tmp_path / "cut.png")
    flipped = bytearray(data)
    flipped[len(data) // 2] ^= 0xFF  # inside the compressed pixel data: zlib/CRC failure
    (tmp_path / "flip.png").write_bytes(bytes(flipped))
    with pytest.raises(DataError, match=r"flip\.png.*corrupt"):
        read_png(tmp_path / "flip.png")
