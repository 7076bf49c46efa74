"""Every frame's laser ring on disk, not in memory: memory that does not grow with the run.

The decoding pass finds a ring in each moving frame; camera motion reads a keyframe's
ring a few times and the analysis reads the stations' rings once. Held in memory they
cost about 80 bytes a sample (12 KB a frame on the paper run at 400x300, 1.2 GB over
100,000 frames). :class:`RingStore` appends each ring's arrays to one file in a private
temporary folder as it arrives and reads a ring back when indexed (from the page cache:
tens of microseconds). A ring without samples (a stationary frame's, a frame without a
laser ring) stays in memory: it holds no array worth writing.
"""

from __future__ import annotations

import threading
from collections.abc import Iterator, Sequence
from dataclasses import dataclass, fields
from pathlib import Path
from typing import overload

import numpy as np

from omnipipe.laser.ring import LaserRing
from omnipipe.scratch import scratch_folder

_ARRAYS = tuple(f.name for f in fields(LaserRing) if f.name not in ("scanned", "warnings"))
"""The ring's per-sample arrays, written in this order."""


@dataclass(frozen=True)
class _OnDisk:
    """Where a ring's arrays start in the store's file, and its two small fields."""

    offset: int
    scanned: int
    warnings: tuple[str, ...]


class RingStore(Sequence[LaserRing]):
    """A frame-indexed sequence of :class:`LaserRing` whose arrays live in a file.

    ``put(i, ring)`` sets frame i's ring (in any order; each frame once); indexing reads
    it back as a new :class:`LaserRing` equal to the one put (arrays, dtypes and shapes
    alike). Rings read back are not written through: change one and the store still
    holds the original. The folder, which only this object writes to, is removed by
    :meth:`close` (or when the store is garbage-collected). Thread-safe.
    """

    def __init__(self, frames: int) -> None:
        self._dir = scratch_folder("omnipipe-rings-")
        self._path = Path(self._dir.name) / "rings.npy-stream"
        self._file = open(self._path, "w+b")  # closed by close()
        self._lock = threading.Lock()
        self._items: list[LaserRing | _OnDisk | None] = [None] * frames

    def put(self, index: int, ring: LaserRing) -> None:
        """Store ``ring`` as frame ``index``'s (kept in memory when it has no samples)."""
        if self._items[index] is not None:
            raise ValueError(f"frame {index} already has a ring")
        arrays = [np.asarray(getattr(ring, name)) for name in _ARRAYS]
        if not any(a.size for a in arrays):
            self._items[index] = ring
            return
        with self._lock:
            self._file.seek(0, 2)
            offset = self._file.tell()
            for a in arrays:
                np.save(self._file, a, allow_pickle=False)
        self._items[index] = _OnDisk(offset, ring.scanned, tuple(ring.warnings))

    def __len__(self) -> int:
        return len(self._items)

    @overload
    def __getitem__(self, index: int) -> LaserRing: ...

    @overload
    def __getitem__(self, index: slice) -> list[LaserRing]: ...

    def __getitem__(self, index: int | slice) -> LaserRing | list[LaserRing]:
        if isinstance(index, slice):
            return [self[i] for i in range(*index.indices(len(self)))]
        item = self._items[index]
        if item is None:
            raise KeyError(f"frame {index % len(self)} has no ring yet")
        if isinstance(item, LaserRing):
            return item
        with self._lock:
            self._file.flush()
            self._file.seek(item.offset)
            arrays = {name: np.load(self._file, allow_pickle=False) for name in _ARRAYS}
        return LaserRing(**arrays, scanned=item.scanned, warnings=list(item.warnings))

    def __iter__(self) -> Iterator[LaserRing]:
        for i in range(len(self)):
            yield self[i]

    def close(self) -> None:
        """Close and remove the file and its folder."""
        self._file.close()
        self._dir.cleanup()
