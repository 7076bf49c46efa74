"""PNG files written a band of rows at a time (the image never copied whole).

PIL copies an RGB image whole before it encodes it (4 bytes a pixel: 28 MB for the
texture atlas of a 10,000-frame run at 400x300), and OpenCV's ``imencode`` wants the
whole image too. :class:`PngWriter` takes the rows in bands: each band is filtered by
:func:`omnipipe.model._kernels.png_filter_rows` (PNG filter types 0-4 chosen per row
by PIL's own rule: the filtered bytes are PIL's, so the files compress as PIL's do)
and fed to one ``zlib`` stream, whose output goes out as IDAT chunks as it comes.
What is held is a band and its filtered copy. :func:`write_png` writes a whole
(H, W[, C]) uint8 array this way; an array in the run's scratch (:mod:`omnipipe.spill`)
has its pages dropped after each band. The files decode to exactly the array's pixels
(8-bit grey, grey + alpha, RGB or RGBA); their bytes are not PIL's (another zlib build,
other IDAT chunk sizes).
"""

from __future__ import annotations

import struct
import zlib
from pathlib import Path
from typing import BinaryIO

import numpy as np

from omnipipe.image import PNG_COMPRESS_LEVEL
from omnipipe.model._kernels import png_filter_rows

_SIGNATURE = b"\x89PNG\r\n\x1a\n"

_COLOUR_TYPE = {1: 0, 2: 4, 3: 2, 4: 6}
"""PNG colour type per channel count: grey, grey + alpha, RGB, RGBA."""

BAND_BYTES = 1 << 18
"""Raw image bytes filtered and compressed at a time (:func:`write_png`'s bands)."""


def _chunk(kind: bytes, data: bytes | memoryview) -> bytes:
    """One PNG chunk: length, type, data, CRC of type and data."""
    return struct.pack(">I", len(data)) + kind + bytes(data) + struct.pack(">I", zlib.crc32(data, zlib.crc32(kind)))


class PngWriter:
    """An 8-bit PNG of ``height`` x ``width`` pixels of ``channels`` (1-4) written into
    the binary file ``fh`` as its rows are given (:meth:`write_rows`, top to bottom, in
    bands of any size); :meth:`close` ends it (every row must have been given)."""

    def __init__(self, fh: BinaryIO, width: int, height: int, channels: int, level: int = PNG_COMPRESS_LEVEL) -> None:
        if channels not in _COLOUR_TYPE or width < 1 or height < 1:
            raise ValueError(f"PngWriter: {height}x{width} pixels of {channels} channels")
        self._fh, self._shape = fh, (width, channels)
        self._left = height
        self._above = np.zeros(width * channels, np.uint8)
        self._z = zlib.compressobj(level, zlib.DEFLATED, 15, 9, zlib.Z_FILTERED)
        head = struct.pack(">IIBBBBB", width, height, 8, _COLOUR_TYPE[channels], 0, 0, 0)
        fh.write(_SIGNATURE + _chunk(b"IHDR", head))

    def write_rows(self, rows: np.ndarray) -> None:
        """The next (n, width[, channels]) uint8 rows."""
        width, channels = self._shape
        rows = np.asarray(rows)
        if rows.dtype != np.uint8 or rows.ndim < 2 or rows.shape[1] != width or rows[:1].size not in (0, width * channels):
            raise ValueError(f"PngWriter: rows {rows.dtype}{rows.shape} for {width} px of {channels} channels")
        if len(rows) > self._left:
            raise ValueError("PngWriter: more rows than the image's height")
        if not len(rows):
            return
        flat = rows.reshape(len(rows), width * channels)
        lines = np.empty((len(flat), flat.shape[1] + 1), np.uint8)
        png_filter_rows(flat, self._above, channels, lines)
        self._idat(self._z.compress(lines))
        self._above = flat[-1].copy()
        self._left -= len(rows)

    def close(self) -> None:
        """The last IDAT and IEND (raises ValueError if rows are missing)."""
        if self._left:
            raise ValueError(f"PngWriter: {self._left} rows missing")
        self._idat(self._z.flush())
        self._fh.write(_chunk(b"IEND", b""))

    def _idat(self, data: bytes) -> None:
        if data:
            self._fh.write(_chunk(b"IDAT", data))


def write_png(dst: Path | BinaryIO, image: np.ndarray, level: int = PNG_COMPRESS_LEVEL) -> None:
    """The (H, W) or (H, W, C) uint8 ``image`` (C = 1-4) as a PNG into ``dst`` (a path or
    a binary file), :data:`BAND_BYTES` of its rows at a time: what is held is a band's
    work, not a copy of the image; an image in the run's scratch (:mod:`omnipipe.spill`)
    has its pages dropped after each band."""
    from omnipipe.spill import drop_pages, is_on_disk

    h, w = image.shape[:2]
    channels = 1 if image.ndim == 2 else image.shape[2]
    band = max(1, BAND_BYTES // (w * channels))
    spilled = is_on_disk(image)

    def encode(fh: BinaryIO) -> None:
        writer = PngWriter(fh, w, h, channels, level)
        for top in range(0, h, band):
            writer.write_rows(np.ascontiguousarray(image[top : top + band]))
            if spilled:
                drop_pages()
        writer.close()

    if isinstance(dst, (str, Path)):
        with open(dst, "wb") as fh:
            encode(fh)
    else:
        encode(dst)
