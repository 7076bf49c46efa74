"""PNG frames through ISA-L's inflate: the same pixels as libspng, or refused (None)."""

from __future__ import annotations

import struct
import zlib

import cv2
import numpy as np
import pytest

from omnipipe.inputs import png
from omnipipe.inputs._kernels import png_unfilter

pytestmark = pytest.mark.skipif(not png.available(), reason="isal not installed")


def _reference_unfilter(data: np.ndarray, h: int, s: int, bpp: int) -> np.ndarray:
    """The PNG specification's reconstruction (section 9.2), one byte at a time."""
    out = np.zeros((h, s), np.int64)
    rows = data.reshape(h, s + 1).astype(np.int64)
    for y in range(h):
        kind, x = rows[y, 0], rows[y, 1:]
        for i in range(s):
            a = out[y, i - bpp] if i >= bpp else 0
            b = out[y - 1, i] if y > 0 else 0
            c = out[y - 1, i - bpp] if y > 0 and i >= bpp else 0
            if kind == 0:
                pred = 0
            elif kind == 1:
                pred = a
            elif kind == 2:
                pred = b
            elif kind == 3:
                pred = (a + b) // 2
            else:
                p = a + b - c
                pa, pb, pc = abs(p - a), abs(p - b), abs(p - c)
                pred = a if pa <= pb and pa <= pc else (b if pb <= pc else c)
            out[y, i] = (x[i] + pred) % 256
    return out.astype(np.uint8)


@pytest.mark.parametrize("bpp", [1, 3, 4])
def test_unfilter_matches_the_reference_for_every_filter_type(bpp: int) -> None:
    rng = np.random.default_rng(11)
    h, s = 12, 7 * bpp
    data = rng.integers(0, 256, (h, s + 1)).astype(np.uint8)
    data[:, 0] = [0, 1, 2, 3, 4, 1, 1, 2, 4, 3, 0, 4]  # every type, and Up / Paeth on row 0's
    data[0, 0] = 2
    out = np.empty((h, s), np.uint8)
    assert png_unfilter(data.reshape(-1), out, bpp)
    assert np.array_equal(out, _reference_unfilter(data.reshape(-1), h, s, bpp))
    data[5, 0] = 5  # no such filter type
    assert not png_unfilter(data.reshape(-1), out, bpp)


def _encoded(image: np.ndarray, level: int) -> bytes:
    ok, buf = cv2.imencode(".png", image, [cv2.IMWRITE_PNG_COMPRESSION, level])
    assert ok
    return buf.tobytes()


@pytest.mark.parametrize("channels", [1, 3, 4])
def test_decoded_as_libspng_decodes_it(channels: int, tmp_path) -> None:
    """libpng's adaptive filters (all five types) at several zlib levels, and the
    project's own writer: the same pixels as libspng."""
    pyspng = pytest.importorskip("pyspng")
    from omnipipe.dataset import write_image

    rng = np.random.default_rng(channels)
    shape = (37, 53) if channels == 1 else (37, 53, channels)
    smooth = cv2.GaussianBlur(rng.integers(0, 256, shape).astype(np.uint8), (7, 7), 2)
    image = np.where(rng.random(shape) < 0.1, rng.integers(0, 256, shape), smooth).astype(np.uint8)
    for level in (0, 1, 6, 9):
        raw = _encoded(image, level)
        got = png.decode_png8(raw)
        assert got is not None and got.dtype == np.uint8
        assert np.array_equal(got, pyspng.load(raw))
    if channels == 3:
        write_image(tmp_path / "frame.png", image)
        raw = (tmp_path / "frame.png").read_bytes()
        assert np.array_equal(png.decode_png8(raw), pyspng.load(raw))


def _chunk(kind: bytes, data: bytes) -> bytes:
    return struct.pack(">I", len(data)) + kind + data + struct.pack(">I", zlib.crc32(kind + data))


def test_files_it_does_not_take_are_left_to_the_other_decoders() -> None:
    rng = np.random.default_rng(5)
    image = rng.integers(0, 256, (9, 11, 3)).astype(np.uint8)
    raw = _encoded(image, 3)
    assert png.decode_png8(raw) is not None
    # A gamma chunk (it could change the pixels) after IHDR (8 + 25 bytes).
    gamma = raw[:33] + _chunk(b"gAMA", struct.pack(">I", 45455)) + raw[33:]
    assert png.decode_png8(gamma) is None
    assert png.decode_png8(raw[: len(raw) - 30]) is None  # truncated
    assert png.decode_png8(_encoded(image.astype(np.uint16) * 257, 3)) is None  # 16-bit
    broken = bytearray(raw)
    idat = raw.index(b"IDAT") + 4
    broken[idat + 20 : idat + 24] = b"\x00\x00\x00\x00"  # the zlib stream damaged
    assert png.decode_png8(bytes(broken)) is None  # the stream's checksum or syntax
    assert png.decode_png8(b"GIF89a" + raw[6:]) is None
