"""The streamed PNG writer (:mod:`omnipipe.model.png`): its files decode to the input's
pixels, whatever the bands, and its rows are filtered as PIL filters them."""

from __future__ import annotations

import io
import struct
import zlib
from pathlib import Path

import numpy as np
import pytest
from PIL import Image

from omnipipe.image import PNG_COMPRESS_LEVEL
from omnipipe.model import png
from omnipipe.model._kernels import png_filter_rows


def _cost(v: np.ndarray) -> np.ndarray:
    return np.minimum(v, 256 - v).sum(axis=1, dtype=np.int64)


def filter_rows(rows: np.ndarray, above: np.ndarray, bpp: int) -> np.ndarray:
    """NumPy reference of :func:`omnipipe.model._kernels.png_filter_rows`: (n, 1 + L)
    uint8 scanlines of the (n, L) uint8 ``rows`` below the (L,) row ``above``."""
    x = rows.astype(np.int16)
    up = np.vstack([above[None].astype(np.int16), x[:-1]])
    left = np.zeros_like(x)
    left[:, bpp:] = x[:, :-bpp]
    diag = np.zeros_like(x)
    diag[:, bpp:] = up[:, :-bpp]
    pa, pb, pc = np.abs(up - diag), np.abs(left - diag), np.abs(left + up - 2 * diag)
    paeth = np.where((pa <= pb) & (pa <= pc), left, np.where(pb <= pc, up, diag))
    candidates = {0: x, 2: (x - up) & 0xFF, 1: (x - left) & 0xFF, 4: (x - paeth) & 0xFF}
    kind = np.zeros(len(x), np.uint8)
    best = _cost(candidates[0])
    for code in (2, 1, 4):  # PIL's order: a later filter only when strictly better
        cost = _cost(candidates[code])
        better = cost < best
        kind[better], best[better] = code, cost[better]
    out = np.empty((len(x), x.shape[1] + 1), np.uint8)
    out[:, 0] = kind
    for code, v in candidates.items():
        out[kind == code, 1:] = v[kind == code]
    return out


def _idat_stream(data: bytes) -> bytes:
    """The decompressed IDAT data (the filtered scanlines) of the PNG file ``data``."""
    at, packed = 8, b""
    while at < len(data):
        (n,) = struct.unpack(">I", data[at : at + 4])
        if data[at + 4 : at + 8] == b"IDAT":
            packed += data[at + 8 : at + 8 + n]
        at += 12 + n
    return zlib.decompress(packed)


def _images(rng: np.random.Generator, shape: tuple[int, ...]) -> list[np.ndarray]:
    """Noise, a smooth ramp (Sub and Paeth win), repeated rows (Up wins), all zeros."""
    smooth = np.cumsum(rng.integers(-3, 4, shape), axis=1).astype(np.uint8)
    rows = np.repeat(rng.integers(0, 256, (1, *shape[1:]), dtype=np.uint8), shape[0], axis=0)
    return [rng.integers(0, 256, shape, dtype=np.uint8), smooth, rows, np.zeros(shape, np.uint8)]


SHAPES = [(45, 33, 3), (7, 5), (30, 20, 4), (10, 9, 2), (1, 1, 3), (3, 2, 1)]


@pytest.mark.parametrize("shape", SHAPES)
def test_kernel_filters_as_the_numpy_reference_and_as_pil(shape: tuple[int, ...]) -> None:
    """Every row's filter and bytes: the kernel's = the reference's = PIL's own (its
    file's IDAT stream decompressed), so the files compress as PIL's do."""
    rng = np.random.default_rng(27)
    for image in _images(rng, shape):
        bpp = 1 if image.ndim == 2 else image.shape[2]
        flat = image.reshape(len(image), -1)
        above = np.zeros(flat.shape[1], np.uint8)
        out = np.empty((len(flat), flat.shape[1] + 1), np.uint8)
        png_filter_rows(flat, above, bpp, out)
        assert np.array_equal(out, filter_rows(flat, above, bpp))
        if bpp != 2:  # PIL writes no grey + alpha from an array
            pil = io.BytesIO()
            Image.fromarray(image if bpp != 1 or image.ndim == 2 else image[..., 0]).save(
                pil, format="png", compress_level=PNG_COMPRESS_LEVEL
            )
            assert _idat_stream(pil.getvalue()) == out.tobytes()
    assert {int(k) for k in out[:, 0]} <= {0, 1, 2, 4}


@pytest.mark.parametrize("shape", SHAPES)
def test_streamed_png_decodes_to_the_input(tmp_path: Path, monkeypatch: pytest.MonkeyPatch, shape) -> None:
    """Round trip: the file write_png makes a band of rows at a time (one row, 7 rows
    with a ragged last band, all at once) decodes to the input's pixels in its mode,
    and its scanlines are the same whatever the bands."""
    channels = 1 if len(shape) == 2 else shape[2]
    for image in _images(np.random.default_rng(6), shape):
        streams = set()
        for band in (1, 7, 1000):
            monkeypatch.setattr(png, "BAND_BYTES", band * image[0].size)
            png.write_png(tmp_path / "a.png", image)
            with Image.open(tmp_path / "a.png") as im:
                assert im.mode == {1: "L", 2: "LA", 3: "RGB", 4: "RGBA"}[channels]
                assert np.array_equal(np.asarray(im), image.reshape(np.asarray(im).shape))
                assert np.asarray(im).size == image.size
            streams.add(_idat_stream((tmp_path / "a.png").read_bytes()))
        assert len(streams) == 1


def test_streamed_png_of_an_array_in_the_scratch(tmp_path: Path) -> None:
    """An image mapped from the run's scratch (omnipipe.spill) is read a band at a time
    (its pages dropped after each): the same file as of the array in memory."""
    from omnipipe.spill import is_on_disk, on_disk

    image = np.random.default_rng(5).integers(0, 256, (300, 41, 3), dtype=np.uint8)
    spilled = on_disk(image)
    assert is_on_disk(spilled)
    png.write_png(tmp_path / "a.png", spilled)
    png.write_png(tmp_path / "b.png", image)
    assert (tmp_path / "a.png").read_bytes() == (tmp_path / "b.png").read_bytes()
    assert np.array_equal(np.asarray(Image.open(tmp_path / "a.png")), image)


def test_writer_refuses_wrong_rows() -> None:
    """Rows of another width, dtype or more than the height, and a short image, raise."""
    writer = png.PngWriter(io.BytesIO(), width=4, height=2, channels=3)
    with pytest.raises(ValueError):
        writer.write_rows(np.zeros((1, 5, 3), np.uint8))
    with pytest.raises(ValueError):
        writer.write_rows(np.zeros((1, 4, 3), np.float32))
    with pytest.raises(ValueError):
        writer.write_rows(np.zeros((3, 4, 3), np.uint8))
    writer.write_rows(np.zeros((1, 4, 3), np.uint8))
    with pytest.raises(ValueError):
        writer.close()
    with pytest.raises(ValueError):
        png.PngWriter(io.BytesIO(), width=4, height=2, channels=5)
