"""Keyframe images on disk, not in memory: memory that does not grow with the run.

The scale decisions (Eq. 17 re-matching around a chosen length) and the longer-baseline
laser anchors need every keyframe's grey image after the whole run's evidence is in.
Holding them costs 3.8 MB per keyframe at 1600x1200 (uint16), gigabytes over a long
run; :class:`ImageStore` writes each to a private temporary folder as it comes and reads
it back when asked (from the page cache, about 1 ms).
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from omnipipe.scratch import ScratchStore


class ImageStore(ScratchStore):
    """An append-only list of arrays kept as ``.npy`` files in a temporary folder.

    Use as a context manager (or call :meth:`close`): the folder, which only this
    object wrote to, is removed at the end.
    """

    def __init__(self) -> None:
        super().__init__("omnipipe-keyframes-")
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
