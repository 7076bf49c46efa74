"""Keyframe images on disk, not in memory: memory that does not grow with the run.

The scale decisions (Eq. 17 re-matching around a chosen length) and the longer-baseline
laser anchors need every keyframe's grey image after the whole run's evidence is in.
Holding them costs 1.9 MB per keyframe at 1600x1200 (8-bit frames' grey as uint8; 3.8
MB as uint16), gigabytes over a long run; :class:`ImageStore` writes each to a private temporary folder as it comes and reads
it back when asked (from the page cache, about 1 ms). A local process pool's workers read
them there too, by :class:`StoredImage` (the file's path through the pipe, not the pixels).
A keyframe whose grey image is already on disk as it is (the run's hand-off folder: a
red laser's 8-bit frame, its green plane first) is referred to there, not written again.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from omnipipe.scratch import ScratchStore


@dataclass(frozen=True)
class StoredImage:
    """A picklable reference to one item of an :class:`ImageStore`, for a worker on the
    same file system (a local process pool) to read itself while the store is open.

    Attributes:
        path: the item's ``.npy`` file.
    """

    path: str

    def load(self) -> np.ndarray:
        """The stored array (the same dtype and values as appended)."""
        return np.load(self.path, allow_pickle=False)


def load_image(image: np.ndarray | StoredImage) -> np.ndarray:
    """``image`` itself, or the array a :class:`StoredImage` refers to."""
    return image.load() if isinstance(image, StoredImage) else image


class ImageStore(ScratchStore):
    """An append-only list of arrays kept as ``.npy`` files in a temporary folder.

    Use as a context manager (or call :meth:`close`): the folder, which only this
    object wrote to, is removed at the end.
    """

    def __init__(self) -> None:
        super().__init__("omnipipe-keyframes-")
        self._n = 0
        # Items already on disk elsewhere (:meth:`append_file`): item -> that file.
        self._elsewhere: dict[int, str] = {}

    def append(self, image: np.ndarray) -> None:
        """Store ``image`` as the next item."""
        np.save(self._path(self._n), np.ascontiguousarray(image), allow_pickle=False)
        self._n += 1

    def append_file(self, path: str) -> None:
        """The next item is the first array of the ``.npy`` file ``path`` (what
        ``np.load`` reads there; a file that holds more arrays after it too), left where
        it is, unwritten and not removed by this store: it must stay until the store is
        read no more (a frame in the run's hand-off folder, whose grey image is its first
        array: :func:`omnipipe.sfm.tasks.handed_gray_file`)."""
        self._elsewhere[self._n] = path
        self._n += 1

    def __getitem__(self, k: int) -> np.ndarray:
        if not -self._n <= k < self._n:
            raise IndexError(f"image {k} of {self._n}")
        return np.load(self._path(k % self._n), allow_pickle=False)

    def ref(self, k: int) -> StoredImage:
        """Item ``k``'s file, for a worker on this file system to read (:meth:`StoredImage.load`)."""
        if not -self._n <= k < self._n:
            raise IndexError(f"image {k} of {self._n}")
        return StoredImage(str(self._path(k % self._n)))

    def __len__(self) -> int:
        return self._n

    def _path(self, k: int) -> Path:
        if k in self._elsewhere:
            return Path(self._elsewhere[k])
        return Path(self._dir.name) / f"{k:06d}.npy"
