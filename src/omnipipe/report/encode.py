"""Images and long texts as the page's pieces: an image as PNG bytes or an unnamed
scratch file (a band of rows at a time), base64 text and data URIs a piece at a time,
matplotlib figures as PNG data URIs (collected once drawn), JSON number lists a chunk at a
time and a text file read back in pieces: none holds a long run's image or page text whole.
:data:`RESIZE_DROP_S` paces the page drops while a whole image kept in the scratch is
resized (the figures' and the 3-D view's).
"""

from __future__ import annotations

import base64
import gc
import io
import tempfile
from collections.abc import Iterator
from typing import IO, TYPE_CHECKING

import numpy as np

from omnipipe.image import PNG_COMPRESS_LEVEL

if TYPE_CHECKING:
    from matplotlib.figure import Figure


def png_data_uri(image: np.ndarray) -> str:
    return PNG_URI_HEAD + base64.b64encode(_png_bytes(image)).decode("ascii")


PNG_URI_HEAD = "data:image/png;base64,"


def _png_bytes(image: np.ndarray) -> bytes:
    """``image`` (uint8) as PNG bytes, encoded a band of rows at a time
    (:func:`omnipipe.model.png.write_png`: no copy of the image)."""
    from omnipipe.model.png import write_png

    buf = io.BytesIO()
    write_png(buf, image)
    return buf.getvalue()


def png_file(image: np.ndarray) -> IO[bytes]:
    """:func:`_png_bytes` of ``image`` in an unnamed file of the run's scratch
    (:func:`omnipipe.scratch.scratch_dir`; gone when closed), positioned at its start:
    neither a copy of the image nor the encoded bytes are held in memory."""
    from omnipipe.model.png import write_png
    from omnipipe.scratch import scratch_dir

    fh = tempfile.TemporaryFile(prefix="omnipipe-png-", dir=scratch_dir())
    write_png(fh, image)
    fh.seek(0)
    return fh


def base64_file_parts(fh: IO[bytes]) -> Iterator[str]:
    """``base64.b64encode`` of the rest of the file ``fh`` as text, read and encoded a piece
    at a time (the pieces join to the whole's encoding)."""
    while piece := fh.read(_BASE64_PIECE):
        yield base64.b64encode(piece).decode("ascii")


_BASE64_PIECE = 3 << 18
"""Bytes encoded at a time by :func:`base64_file_parts` (a multiple of 3: the pieces' text
joins to the whole's)."""


FIGURE_DPI = 110
"""Pixels per inch of the report's figures."""


def figure_data_uri(fig: Figure) -> str:
    import matplotlib.pyplot as plt

    buf = io.BytesIO()
    fig.savefig(
        buf, format="png", dpi=FIGURE_DPI, bbox_inches="tight",
        pil_kwargs={"compress_level": PNG_COMPRESS_LEVEL},
    )
    plt.close(fig)
    return "data:image/png;base64," + base64.b64encode(buf.getbuffer()).decode("ascii")


def collected(uri: str) -> str:
    """``uri``, once the figure it was drawn from is collected: a closed figure is a
    cycle of objects (its canvas's pixel buffer among them) that the collector would
    otherwise free only when it next runs, under the next figures. Call it on a plot function's result, after its frame is gone."""
    gc.collect()
    return uri


RESIZE_DROP_S = 0.005
"""Seconds between two drops of the scratch's pages (:func:`omnipipe.spill.dropping_pages`)
while one call reads a whole image kept there (the atlas, the unrolled wall): the pages
it read in the last few milliseconds resident, not the image's."""


_NUMBERS_CHUNK = 1 << 16
"""Values formatted at once by :func:`number_chunks` (their Python floats, about 100 bytes
each, are a chunk's, not the mesh's)."""


def number_chunks(fmt: str, values: np.ndarray) -> Iterator[str]:
    """The values of ``values`` (any shape, row-major) in ``fmt``, comma-separated, in
    pieces of :data:`_NUMBERS_CHUNK` values (a comma between pieces, none after the last)."""
    flat = np.asarray(values).ravel()
    for a in range(0, len(flat), _NUMBERS_CHUNK):
        chunk = flat[a : a + _NUMBERS_CHUNK]
        text = (fmt + ",") * len(chunk) % tuple(chunk.tolist())
        yield text if a + _NUMBERS_CHUNK < len(flat) else text[:-1]


_TEXT_PIECE = 1 << 20
"""Characters :func:`text_file_parts` reads at a time."""


def text_file_parts(fh: IO[str]) -> Iterator[str]:
    """The rest of the text file ``fh`` in pieces of :data:`_TEXT_PIECE` characters; the
    file closed after the last."""
    with fh:
        while piece := fh.read(_TEXT_PIECE):
            yield piece
