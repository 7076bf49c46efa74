"""Keyframe images on disk, not in memory: memory that does not grow with the run.

The scale decisions (Eq. 17 re-matching around a chosen length) and the longer-baseline
laser anchors need every keyframe's grey image after the whole run's evidence is in.
Holding them costs 3.8 MB per keyframe at 1600x1200 (uint16), gigabytes over a long
run; :class:`ImageStore` writes each to a private temporary folder as it comes and reads
it back when asked (from the page cache, about 1 ms).
"""

from __future__ import annotations

from pathlib import Path
from types import TracebackType

import numpy as np

from omnipipe.scratch import scratch_folder


class ImageStore:
    """An append-only list of arrays kept as ``.npy`` files in a temporary folder.

    Use as a context manager (or call :meth:`close`): the folder, which only this
    object wrote to, is removed at the end.
    """

    def __init__(self) -> None:
        self._dir = scratch_folder("omnipipe-keyframes-")
        self._n = 0

    def append(self, image: np.ndarray) -> None:
        """Store ``image`` as the next item."""
        np.save(self._path(self._n), np.ascontiguousarray(image), allow_pickle=False)
        self._n += 1

    def __getitem__(self, k: int) -> np.ndarray:
        if not -self._n <= k < self._n:
            raise IndexError(f"image {k} of {self._n}")
        return np.load(self._path(k % self._n), allow_pickle=False)

    def __len__(self) -> int:
        return self._n

    def _path(self, k: int) -> Path:
        return Path(self._dir.name) / f"{k:06d}.npy"

    def close(self) -> None:
        """Remove the folder and its files."""
        self._dir.cleanup()

    def __enter__(self) -> ImageStore:
        return self

    def __exit__(
        self,
        exc_type: type[BaseException] | None,
        exc: BaseException | None,
        tb: TracebackType | None,
    ) -> None:
        self.close()


# Scratch bytes the decoding pass may hand on (2 GiB: about 1,100 frames of 1600x1200);
# the frames after them are decoded again by the motion's workers.
HANDOFF_BUDGET_BYTES = 2 * 2**30

_FULL = "FULL"


class GrayHandoff:
    """The moving frames' grey images, from the pass that decoded them to the motion's
    workers (:class:`omnipipe.sfm.tasks.FeatureTask`), so that no frame is decoded twice.

    The decoding pass's workers write a frame's grey image (:func:`hand_on`) into this
    folder; the parent notes it (:meth:`note`) and, past ``budget_bytes``, leaves a
    marker that stops further writes (those frames are decoded again later). A worker
    takes a frame's image back once (:func:`take_back`: the file is removed as it is
    read; a frame without one is decoded), so the folder holds the frames not yet used. Files of frames the run found
    stationary are removed by :meth:`discard`. Local process pools only (the workers
    share this machine's file system); the folder, which only omnipipe wrote to, is
    removed by :meth:`close`.
    """

    def __init__(self, n_frames: int, budget_bytes: int = HANDOFF_BUDGET_BYTES) -> None:
        self._dir = scratch_folder("omnipipe-grays-")
        self.folder = self._dir.name
        self.budget_bytes = budget_bytes
        self._bytes = 0
        self._noted = np.zeros(n_frames, bool)

    def note(self, i: int, nbytes: int) -> None:
        """Frame ``i``'s image was written (``nbytes`` bytes); past the budget, no more."""
        self._noted[i] = True
        self._bytes += nbytes
        if self._bytes >= self.budget_bytes:
            (Path(self.folder) / _FULL).touch()

    def discard(self, i: int) -> None:
        """Remove frame ``i``'s file (a frame no later stage reads)."""
        if self._noted[i]:
            Path(handoff_path(self.folder, i)).unlink(missing_ok=True)
            self._noted[i] = False

    def close(self) -> None:
        """Remove the folder and what is left in it."""
        self._dir.cleanup()

    def __enter__(self) -> GrayHandoff:
        return self

    def __exit__(
        self,
        exc_type: type[BaseException] | None,
        exc: BaseException | None,
        tb: TracebackType | None,
    ) -> None:
        self.close()


def handoff_path(folder: str, i: int) -> str:
    """Frame ``i``'s file in a :class:`GrayHandoff`'s ``folder``."""
    return str(Path(folder) / f"{i:07d}.npy")


def hand_on(folder: str, i: int, gray: np.ndarray) -> int:
    """Write frame ``i``'s grey image into a :class:`GrayHandoff`'s ``folder`` (in a
    worker); returns the bytes written, 0 when the hand-off is full."""
    if (Path(folder) / _FULL).exists():
        return 0
    path = Path(handoff_path(folder, i))
    np.save(path, np.ascontiguousarray(gray), allow_pickle=False)
    return int(path.stat().st_size)


def take_back(folder: str, i: int) -> np.ndarray | None:
    """Frame ``i``'s image handed on into ``folder``, its file removed; None when it was
    not (a stationary frame's chunk, a full hand-off, another machine's worker)."""
    path = handoff_path(folder, i)
    try:
        image = np.load(path, allow_pickle=False)
    except FileNotFoundError:
        return None
    Path(path).unlink(missing_ok=True)
    return image
