"""Every frame's laser ring on disk, not in memory: memory that does not grow with the run.

The decoding pass finds a ring in each moving frame; camera motion reads a keyframe's
ring a few times and the analysis reads the stations' rings once. Held in memory they
cost about 80 bytes a sample (12 KB a frame on the paper run at 400x300, 1.2 GB over
100,000 frames). :class:`RingStore` appends each ring's arrays to one file in a private
temporary folder as it arrives and reads a ring back when indexed (from the page cache:
tens of microseconds). A ring without samples (a stationary frame's, a frame without a
laser ring) stays in memory: it holds no array worth writing.

A ring's record in the file: a header (:data:`_HEADER`: each array's dtype and shape)
followed by the arrays' bytes in C order, written with one call and read with one for
the header and one per array, each into an array of its own (an ``np.save`` per array
parsed a text header for each: 2 ms a ring read back, 0.9 ms written).
"""

from __future__ import annotations

import shutil
import threading
from collections.abc import Iterator, Sequence
from dataclasses import dataclass, fields
from pathlib import Path
from typing import BinaryIO, overload

import numpy as np

from omnipipe.laser.ring import LaserRing
from omnipipe.scratch import scratch_folder

_ARRAYS = tuple(f.name for f in fields(LaserRing) if f.name not in ("scanned", "warnings"))
"""The ring's per-sample arrays, written in this order."""

_HEADER = np.dtype([("dtype", "S8"), ("ndim", "<i8"), ("shape", "<i8", (3,))])
"""One record per array of :data:`_ARRAYS` at the start of a ring's record: its dtype
(``numpy.dtype.str``), its number of dimensions (at most 3) and its shape."""


def _record(arrays: list[np.ndarray]) -> bytes:
    """A ring's record: the header of ``arrays`` and their bytes.

    Raises:
        ValueError: an array of more than 3 dimensions or of an object dtype.
    """
    head = np.zeros(len(arrays), _HEADER)
    for k, a in enumerate(arrays):
        if a.ndim > 3 or a.dtype.hasobject:
            raise ValueError(f"ring array {_ARRAYS[k]}: {a.dtype} of {a.ndim} dimensions is not stored")
        head[k]["dtype"] = a.dtype.str.encode()
        head[k]["ndim"] = a.ndim
        head[k]["shape"][: a.ndim] = a.shape
    return b"".join([head.tobytes(), *(np.ascontiguousarray(a).tobytes() for a in arrays)])


def _arrays(fh: BinaryIO) -> dict[str, np.ndarray]:
    """The arrays of the ring record at ``fh``'s position, each writable and its own:
    each read into a buffer of its own, so an array kept holds its own bytes only (views
    of one buffer for the record kept the whole record alive through any one of them,
    e.g. a ring's empty ``gap_edges`` kept as it is where its other arrays went to the
    run's scratch: the whole ring held per station through the analysis' ring pass)."""
    head = np.frombuffer(fh.read(len(_ARRAYS) * _HEADER.itemsize), _HEADER)
    out = {}
    for name, d, shape, ndim in zip(_ARRAYS, head["dtype"], head["shape"], head["ndim"], strict=True):
        a = np.empty(tuple(int(x) for x in shape[:ndim]), np.dtype(d.decode()))
        if a.nbytes and fh.readinto(memoryview(a).cast("B")) != a.nbytes:
            raise ValueError("ring record: the file ends inside it")
        out[name] = a
    return out


@dataclass(frozen=True)
class _OnDisk:
    """Where a ring's arrays start in the store's file, and its two small fields."""

    offset: int
    scanned: int
    warnings: tuple[str, ...]


@dataclass
class RingIndex:
    """Where each frame's ring is in a :class:`RingStore`'s file (what a checkpoint saves
    beside a copy of the file; a few bytes a frame).

    Attributes:
        offset: (N,) int64 byte offset of each frame's arrays in the file; -1: the ring
            is one of ``in_memory``, -2: the frame has no ring yet.
        scanned: (N,) int64 scan lines of each ring on disk (0 elsewhere).
        warnings: (N,) each ring's warnings (empty elsewhere).
        in_memory: the rings without samples, in frame order of ``offset == -1``.
    """

    offset: np.ndarray
    scanned: np.ndarray
    warnings: list[list[str]]
    in_memory: list[LaserRing]


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
        record = _record(arrays)
        with self._lock:
            self._file.seek(0, 2)
            offset = self._file.tell()
            self._file.write(record)
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
            arrays = _arrays(self._file)
        return LaserRing(**arrays, scanned=item.scanned, warnings=list(item.warnings))

    def __iter__(self) -> Iterator[LaserRing]:
        for i in range(len(self)):
            yield self[i]

    def index(self) -> RingIndex:
        """Where each ring is (:class:`RingIndex`): with :meth:`copy_to`, what
        :meth:`restore` builds an equal store from."""
        n = len(self._items)
        offset, scanned = np.full(n, -2, np.int64), np.zeros(n, np.int64)
        warnings: list[list[str]] = [[] for _ in range(n)]
        in_memory: list[LaserRing] = []
        for i, item in enumerate(self._items):
            if isinstance(item, _OnDisk):
                offset[i], scanned[i], warnings[i] = item.offset, item.scanned, list(item.warnings)
            elif isinstance(item, LaserRing):
                offset[i] = -1
                in_memory.append(item)
        return RingIndex(offset, scanned, warnings, in_memory)

    def copy_to(self, fh: BinaryIO) -> None:
        """Write the store's file into the open binary file ``fh``, a block at a time."""
        with self._lock:
            self._file.flush()
            self._file.seek(0)
            shutil.copyfileobj(self._file, fh, 1 << 20)

    @staticmethod
    def restore(path: Path, index: RingIndex) -> RingStore:
        """A store equal to the one whose :meth:`copy_to` wrote ``path`` and whose
        :meth:`index` is ``index``: ``path`` copied (a block at a time) into the new
        store's own file, no ring read into memory.

        Raises:
            ValueError: ``index`` does not describe a store (lengths differ, too few
                rings in memory, an offset beyond the file).
        """
        n = len(index.offset)
        if not (len(index.scanned) == len(index.warnings) == n) or int(
            np.sum(index.offset == -1)
        ) != len(index.in_memory):
            raise ValueError("ring index: inconsistent lengths")
        store = RingStore(n)
        with open(path, "rb") as src:
            shutil.copyfileobj(src, store._file, 1 << 20)
        size = store._file.tell()
        if n and int(index.offset.max()) >= size:
            store.close()
            raise ValueError("ring index: an offset beyond the file")
        memory = iter(index.in_memory)
        for i, off in enumerate(index.offset.tolist()):
            if off >= 0:
                store._items[i] = _OnDisk(off, int(index.scanned[i]), tuple(index.warnings[i]))
            elif off == -1:
                store._items[i] = next(memory)
        return store

    def close(self) -> None:
        """Close and remove the file and its folder."""
        self._file.close()
        self._dir.cleanup()
