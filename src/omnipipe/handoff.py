"""Decoded frames handed from the pass that decoded them to the later stages' workers.

Decoding a 1600x1200 PNG costs 22 ms of CPU; writing the decoded array to the run's
scratch folder costs 5 ms and reading it back 2 ms (from the page cache). The decoding
pass (:mod:`omnipipe.pipeline.frame_pass`) therefore leaves each moving frame, as
decoded, in a :class:`FrameHandoff`, and the camera motion's and the model's workers
read it from there (:meth:`omnipipe.executor.FrameSource.read`) instead of decoding
the frame again: the same array, so the same results. Only up to a budget of bytes
(the frames after it are decoded again), only for a local process pool (its workers
share this file system), and only for as long as the run.
"""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np

from omnipipe.scratch import ScratchStore

# Scratch bytes a run may hand on (2 GiB: about 370 frames of 1600x1200 RGB).
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


def hand_on(folder: str, i: int, image: np.ndarray) -> int:
    """Write frame ``i`` (as decoded) into a :class:`FrameHandoff`'s ``folder`` (in a
    worker); returns the bytes written, 0 when the hand-off is full."""
    if os.path.exists(os.path.join(folder, _FULL)):
        return 0
    image = np.ascontiguousarray(image)
    with open(handoff_path(folder, i), "wb") as fh:
        np.lib.format.write_array(fh, image, allow_pickle=False)
        return fh.tell()


def handed(folder: str, i: int, mapped: bool = False) -> np.ndarray | None:
    """Frame ``i`` as the decoding pass left it in ``folder``; None when it did not (a
    stationary frame, a full hand-off, a folder already closed).

    ``mapped``: a read-only array on the file's pages in the OS's cache instead of a
    copy of them, for a reader that takes one channel of it (no frame-sized copy).
    """
    try:
        if mapped:
            return np.asarray(np.load(handoff_path(folder, i), mmap_mode="r"))
        return np.load(handoff_path(folder, i), allow_pickle=False)
    except FileNotFoundError:
        return None
