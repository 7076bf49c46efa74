"""Decoded frames handed from the pass that decoded them to the later stages' workers.

Decoding a 1600x1200 PNG costs more than writing the decoded array to the run's scratch
folder and reading it back (from the page cache). The decoding pass
(:mod:`omnipipe.pipeline.frame_pass`) therefore leaves each moving frame in a
:class:`FrameHandoff`, and the camera motion's and the model's workers read it from
there (:meth:`omnipipe.executor.FrameSource.read`) instead of decoding the frame again.
Only up to a budget of bytes (the frames after it are decoded again), only for a local
process pool (its workers share this file system), and only for as long as the run.

An 8-bit colour frame of a red laser is handed on **planar** (:class:`PlanarFrame`):
its green channel whole, which is all the camera motion reads of it (its grey image,
:func:`omnipipe.sfm.tasks.frame_gray`: the same array, so the same motion), then red
and blue at half resolution (each 2x2 block's mean, as 4:2:0 video keeps its chroma),
which only the model's colours read: half the bytes of the frame as decoded. Any other
frame is handed on as decoded.
"""

from __future__ import annotations

import os
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np

from omnipipe.scratch import ScratchStore

# Scratch bytes a run may hand on (2 GiB: about 370 frames of 1600x1200 RGB as decoded,
# 745 planar).
HANDOFF_BUDGET_BYTES = 2 * 2**30

_FULL = "FULL"


class FrameHandoff(ScratchStore):
    """A scratch folder of decoded frames, one ``.npy`` file per frame index.

    The decoding pass's workers write (:func:`hand_on`); the parent notes what they
    wrote (:meth:`note`) and, past ``budget_bytes``, leaves a marker that stops further
    writes. Workers read with :func:`handed` (None: not handed on: decode it). Frames
    no later stage reads are removed with :meth:`discard`; the folder, which only
    omnipipe wrote to, is removed by :meth:`close` (or at the end of a ``with`` block).
    """

    def __init__(self, n_frames: int, budget_bytes: int = HANDOFF_BUDGET_BYTES) -> None:
        super().__init__("omnipipe-frames-")
        self.folder = self._dir.name
        self.budget_bytes = budget_bytes
        self._bytes = 0
        self._noted = np.zeros(n_frames, bool)

    def note(self, i: int, nbytes: int) -> None:
        """Frame ``i`` was written (``nbytes`` bytes); past the budget, no more are."""
        self._noted[i] = True
        self._bytes += nbytes
        if self._bytes >= self.budget_bytes:
            (Path(self.folder) / _FULL).touch()

    def discard(self, i: int) -> None:
        """Remove frame ``i``'s file (a frame no later stage reads)."""
        if self._noted[i]:
            Path(handoff_path(self.folder, i)).unlink(missing_ok=True)
            self._noted[i] = False


def handoff_path(folder: str, i: int) -> str:
    """Frame ``i``'s file in a :class:`FrameHandoff`'s ``folder``."""
    return os.path.join(folder, f"{i:07d}.npy")


@dataclass(frozen=True)
class PlanarFrame:
    """An (H, W, 3) 8-bit RGB frame of a red laser as handed on: green whole, red and blue
    at half resolution.

    Attributes:
        green: (H, W) uint8, the frame's green channel as decoded.
        red_blue: (ceil(H / 2), ceil(W / 2), 2) uint8: red and blue, each the mean of a
            2x2 block of pixels (``cv2.INTER_AREA``); half-pixel (j, i) is centred on
            full pixel (2j + 0.5, 2i + 0.5).
    """

    green: np.ndarray
    red_blue: np.ndarray

    @staticmethod
    def of(image: np.ndarray, planes: tuple[np.ndarray, ...] | None = None) -> PlanarFrame:
        """The planar form of an (H, W, 3) uint8 RGB ``image``; ``planes``: its three
        channels as ``cv2.split(image)`` gives them, when the caller has split it already
        (the decoding pass: its station signature reads the green one)."""
        h, w = image.shape[:2]
        half = ((w + 1) // 2, (h + 1) // 2)
        red, green, blue = cv2.split(image) if planes is None else planes  # one pass over the frame
        return PlanarFrame(green, cv2.merge([cv2.resize(c, half, interpolation=cv2.INTER_AREA) for c in (red, blue)]))

    def rgb(self) -> np.ndarray:
        """(H, W, 3) uint8: red and blue interpolated back to full resolution (bilinear)."""
        h, w = self.green.shape
        up = cv2.resize(self.red_blue, (w, h), interpolation=cv2.INTER_LINEAR)
        return cv2.merge([up[..., 0], np.ascontiguousarray(self.green), up[..., 1]])

    def sample(self, pixels: np.ndarray) -> np.ndarray:
        """(n, 3) uint8 bilinear RGB at (n, 2) float pixels (col, row) of the full frame,
        the border replicated (green from the whole channel, red and blue from the
        half-resolution ones at the same place)."""
        from omnipipe.image import sample_bilinear

        px = np.asarray(pixels, np.float32).reshape(-1, 2)
        out = np.empty((len(px), 3), np.uint8)
        if not len(px):
            return out
        out[:, 1] = sample_bilinear(self.green, px, border=cv2.BORDER_REPLICATE)
        out[:, 0::2] = sample_bilinear(self.red_blue, (px - 0.5) / 2, border=cv2.BORDER_REPLICATE)
        return out


def plane_split(image: np.ndarray, laser_channel: str | None) -> bool:
    """Whether ``image`` is handed on planar (:class:`PlanarFrame`): an (H, W, 3) uint8
    frame of a red laser, whose grey image is its green channel."""
    return (
        laser_channel == "red" and image.dtype == np.uint8 and image.ndim == 3 and image.shape[2] == 3
    )


def handoff_full(folder: str) -> bool:
    """Whether a :class:`FrameHandoff`'s ``folder`` takes no more frames (its budget is
    spent: :meth:`FrameHandoff.note`)."""
    return os.path.exists(os.path.join(folder, _FULL))


def hand_on(
    folder: str,
    i: int,
    image: np.ndarray,
    laser_channel: str | None = None,
    planes: tuple[np.ndarray, ...] | None = None,
) -> int:
    """Write frame ``i`` into a :class:`FrameHandoff`'s ``folder`` (in a worker): planar
    where :func:`plane_split` (the green channel's array first, then red and blue's; from
    ``planes``, ``cv2.split(image)``, when given), else as decoded; returns the bytes
    written, 0 when the hand-off is full."""
    if handoff_full(folder):
        return 0
    arrays = (
        (lambda p: (p.green, p.red_blue))(PlanarFrame.of(image, planes))
        if plane_split(image, laser_channel)
        else (np.ascontiguousarray(image),)
    )
    with open(handoff_path(folder, i), "wb") as fh:
        for a in arrays:
            np.lib.format.write_array(fh, a, allow_pickle=False)
        return fh.tell()


def handed(folder: str, i: int, mapped: bool = False) -> np.ndarray | None:
    """Frame ``i`` as the decoding pass left it in ``folder``, (H, W, 3) or (H, W); None
    when it did not (a stationary frame, a full hand-off, a folder already closed).

    ``mapped``: a read-only array on the pages of the file's first array in the OS's
    cache instead of a copy, for a reader of the frame's grey image
    (:func:`omnipipe.sfm.tasks.frame_gray`): the whole frame, or a planar frame's green
    channel (its grey image: no frame-sized copy, a third of the pages). Otherwise the
    whole frame (a planar one as :meth:`PlanarFrame.rgb`).
    """
    if mapped:
        try:
            return np.asarray(np.load(handoff_path(folder, i), mmap_mode="r"))
        except FileNotFoundError:
            return None
    frame = handed_frame(folder, i)
    return frame.rgb() if isinstance(frame, PlanarFrame) else frame


def handed_frame(folder: str, i: int) -> np.ndarray | PlanarFrame | None:
    """Frame ``i`` as the decoding pass left it in ``folder``: the array as decoded, or
    the :class:`PlanarFrame` it was handed on as; None when it was not handed on."""
    try:
        with open(handoff_path(folder, i), "rb") as fh:
            first = np.lib.format.read_array(fh, allow_pickle=False)
            if fh.tell() == os.fstat(fh.fileno()).st_size:
                return first
            return PlanarFrame(first, np.lib.format.read_array(fh, allow_pickle=False))
    except FileNotFoundError:
        return None
