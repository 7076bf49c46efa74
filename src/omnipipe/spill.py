"""Arrays a run holds for a later step, kept in its scratch rather than in its memory.

A run's results grow with its length (the wall points, the mesh, the texture atlas,
the analysis' per-point coordinates: about 12 MB per 1,000 frames at 400x300) and are
held from the stage that makes them to the writers at the end. :func:`on_disk` copies
such an array into an unnamed file in the run's scratch folder
(:func:`omnipipe.scratch.scratch_dir`; gone with the process however it ends) and
returns an array mapped onto that file: the same dtype, shape and values, writable,
usable wherever the array was (an ``np.ndarray``; pickled it is an ordinary array).
Its pages are the file's, in the system's page cache: they count in the process's
resident memory only while a step reads them, and :func:`drop_pages` (called by
:func:`omnipipe.memory.release_freed_memory` between the steps) unmaps them again, so
the run's peak holds what its current step reads, not every result made so far. The
kernel writes the file back and reclaims its pages under memory pressure, as it does
with any file's. A step that passes over every keyframe or frame maps the pages of all
of them in turn; within :func:`dropping_pages` (the reconstruction's stages and its
writers) a thread unmaps them every :data:`DROP_INTERVAL_S`, so such a pass holds what
it read in the last fraction of a second.

:func:`shared_on_disk` makes such an array read-only: sent to a worker of a local
process pool (:mod:`omnipipe.executor`), it travels by reference (the file, through
``/proc/PID/fd``, and where in it) rather than pickled whole, and the worker maps it
copy-on-write (writable, its writes its own, as an unpickled array's would be).
"""

from __future__ import annotations

import contextlib
import mmap
import os
import pickle
import tempfile
import threading
import time
import weakref
from collections.abc import Callable, Iterator
from typing import Any

import numpy as np

from omnipipe.scratch import scratch_dir

_MAPS: weakref.WeakSet[mmap.mmap] = weakref.WeakSet()
"""Every live mapping made here (gone when its last array is)."""

_MAPS_LOCK = threading.Lock()
"""Held while :data:`_MAPS` gains a mapping or is listed (the two may be in two threads:
:func:`dropping_pages`)."""


def _new_lock_in_child() -> None:
    """A forked worker's own lock (the parent's may have been held by its dropping
    thread at the fork, which the worker does not have)."""
    global _MAPS_LOCK
    _MAPS_LOCK = threading.Lock()


os.register_at_fork(after_in_child=_new_lock_in_child)

_FILES: weakref.WeakKeyDictionary[mmap.mmap, tuple[int, int, int]] = weakref.WeakKeyDictionary()
"""Each live mapping's (process that made it, its own descriptor of the file, the
address of its first byte): what a worker needs to map it too (:func:`shared_on_disk`)."""

_COPY_BYTES = 1 << 22
"""Bytes copied into the file at a time by :func:`on_disk` (no second whole copy)."""


def _mapped(nbytes: int, fill: np.ndarray | None) -> mmap.mmap:
    """A shared, writable mapping of a new unnamed scratch file of ``nbytes`` bytes
    (zeros, or ``fill``'s bytes written in)."""
    with tempfile.TemporaryFile(prefix="omnipipe-spill-", dir=scratch_dir()) as fh:
        if fill is None:
            fh.truncate(nbytes)
        else:
            for piece in _c_order_pieces(fill):
                fh.write(memoryview(piece).cast("B"))
            fh.flush()
        return _map_file(fh, nbytes)


def _map_file(fh: Any, nbytes: int) -> mmap.mmap:
    """The shared, writable mapping of the open scratch file ``fh``'s ``nbytes`` bytes,
    registered (:data:`_MAPS`, :data:`_FILES`); ``fh`` may be closed after."""
    mapping = mmap.mmap(fh.fileno(), nbytes)  # holds its own copy of the descriptor
    fd = os.dup(fh.fileno())  # for the workers that map it too (closed with the mapping)
    with _MAPS_LOCK:
        _MAPS.add(mapping)
    _FILES[mapping] = (os.getpid(), fd, np.frombuffer(mapping, np.uint8, count=1).ctypes.data)
    weakref.finalize(mapping, os.close, fd)
    return mapping


class ScratchWriter:
    """An (n,) array of ``dtype`` written into a new scratch file a piece at a time, in
    order, through the file (none of its pages mapped into the process while it is
    written: a whole-run result made a block at a time never sits in memory whole), then
    :meth:`array`: the file mapped, as :func:`on_disk`'s arrays are."""

    def __init__(self, n: int, dtype: np.dtype | type) -> None:
        self.n, self.dtype, self._done = int(n), np.dtype(dtype), 0
        self._fh = tempfile.TemporaryFile(prefix="omnipipe-spill-", dir=scratch_dir())

    def write(self, piece: np.ndarray) -> None:
        """Append ``piece``'s values (1-D, cast to the writer's dtype)."""
        piece = np.ascontiguousarray(piece, self.dtype).reshape(-1)
        if self._done + len(piece) > self.n:
            raise ValueError(f"ScratchWriter: more than {self.n} values written")
        self._fh.write(memoryview(piece).cast("B"))
        self._done += len(piece)

    def array(self) -> np.ndarray:
        """The (n,) array written (every value must have been)."""
        with self._fh as fh:
            if self._done != self.n:
                raise ValueError(f"ScratchWriter: {self._done} of {self.n} values written")
            if self.n * self.dtype.itemsize == 0:
                return np.zeros(self.n, self.dtype)
            fh.flush()
            return np.ndarray((self.n,), self.dtype, buffer=_map_file(fh, self.n * self.dtype.itemsize))


def _c_order_pieces(a: np.ndarray) -> Iterator[np.ndarray]:
    """``a``'s values in C order, in contiguous 1-D pieces of about :data:`_COPY_BYTES`
    (a strided ``a``, e.g. a column, copied a block of its first axis at a time: no
    whole copy)."""
    if a.flags.c_contiguous or a.ndim < 2:
        flat = a.reshape(-1) if a.flags.c_contiguous else a  # 1-D: strided slices copy
        step = max(1, _COPY_BYTES // max(a.itemsize, 1))
        for i in range(0, len(flat), step):
            yield np.ascontiguousarray(flat[i : i + step])
        return
    row = max(1, a[0].size * a.itemsize)
    rows = max(1, _COPY_BYTES // row)
    for i in range(0, len(a), rows):
        yield np.ascontiguousarray(a[i : i + rows]).reshape(-1)


def _empty_of(a: np.ndarray) -> np.ndarray:
    """``a`` (holding no bytes) itself when it views no other array's buffer, else a new
    empty array of its shape and dtype: an empty view kept would keep the whole buffer
    it views alive (e.g. a record read back in one buffer) for nothing."""
    return a if a.base is None else np.empty(a.shape, a.dtype)


def on_disk(a: np.ndarray) -> np.ndarray:
    """``a``'s values in a scratch file (module docstring): an (C-ordered) array of the
    same dtype, shape and values, writable; ``a`` itself when its dtype holds Python
    objects or it is on disk already; when it holds no bytes, ``a`` or (a view)
    :func:`_empty_of` it."""
    a = np.asarray(a)
    if a.nbytes == 0:
        return _empty_of(a)
    if a.dtype.hasobject or is_on_disk(a):
        return a
    mapping = _mapped(a.nbytes, a)
    return np.ndarray(a.shape, a.dtype, buffer=mapping)  # one array object on the mapping


def zeros_on_disk(shape: tuple[int, ...], dtype: np.dtype | type) -> np.ndarray:
    """A new array of zeros of ``shape`` and ``dtype`` in a scratch file (module docstring)."""
    dt = np.dtype(dtype)
    size = int(np.prod(shape, dtype=np.int64))
    if size * dt.itemsize == 0:
        return np.zeros(shape, dt)
    return np.ndarray(shape, dt, buffer=_mapped(size * dt.itemsize, None))


def compressed_on_disk(
    a: np.ndarray, keep: np.ndarray, transform: Callable[[np.ndarray], np.ndarray] | None = None
) -> np.ndarray:
    """``a[keep]`` of a 1-D ``a`` and (N,) bool ``keep`` (``transform``: an elementwise
    function applied to it, which may work in place) in a scratch file (as :func:`on_disk`
    of it), gathered and written about :data:`_COPY_BYTES` of ``a`` at a time
    (:class:`ScratchWriter`): no whole copy in memory, nor of ``keep``'s indices."""
    a, keep = np.asarray(a), np.asarray(keep, bool)
    if a.ndim != 1 or keep.shape != a.shape:
        raise ValueError(f"compressed_on_disk: 1-D array and mask of its shape expected, got {a.shape}, {keep.shape}")
    if a.dtype.hasobject:
        return a[keep] if transform is None else transform(a[keep])
    out = ScratchWriter(int(np.count_nonzero(keep)), a.dtype)
    step = max(1, _COPY_BYTES // max(a.itemsize, 1))
    for i in range(0, len(a), step):
        piece = a[i : i + step][keep[i : i + step]]
        out.write(piece if transform is None else transform(piece))
    return out.array()


def pieces_on_disk(pieces: list[np.ndarray]) -> list[np.ndarray]:
    """Arrays of equal trailing shape and dtype (e.g. each ring's (M_k, 2) pixels) in one
    scratch file (as :func:`on_disk` of their concatenation, written piece by piece: no
    concatenation in memory; the pages read and written dropped every
    :data:`_COPY_BYTES`): views of it, one per piece, equal to the pieces."""
    if not pieces:
        return []
    ends = np.cumsum([len(p) for p in pieces])
    dtype = np.result_type(*pieces)
    if dtype.hasobject or int(ends[-1]) * np.prod(pieces[0].shape[1:], dtype=np.int64) * dtype.itemsize == 0:
        whole = on_disk(np.concatenate(pieces))
    else:
        whole = zeros_on_disk((int(ends[-1]), *pieces[0].shape[1:]), dtype)
        done = 0
        for a, p in zip(np.concatenate([[0], ends[:-1]]).tolist(), pieces, strict=True):
            whole[a : a + len(p)] = p
            done += p.nbytes
            if done >= _COPY_BYTES:
                drop_pages()
                done = 0
    return [whole[a:b] for a, b in zip(np.concatenate([[0], ends[:-1]]).tolist(), ends.tolist(), strict=True)]


class Pack:
    """Many small arrays (a keyframe's features, a step's matches) in a few scratch files:
    :meth:`put` appends one to the current file (:data:`SEGMENT_BYTES` each, a new one
    when it is full) and returns an array mapped onto it, as :func:`on_disk` does (the
    same dtype, shape and values; writable; resident only while read, :func:`drop_pages`).
    A file per array would cost two descriptors each: thousands on a long run.

    The values are written into the file (not through the mapping), so putting an array
    maps none of its pages into the process."""

    def __init__(self, segment_bytes: int | None = None) -> None:
        self._segment = int(segment_bytes or SEGMENT_BYTES)
        self._map: mmap.mmap | None = None
        self._used = 0

    def put(self, a: np.ndarray) -> np.ndarray:
        """``a``'s values appended to the pack's file: an array on disk equal to ``a``
        (``a`` itself when it holds Python objects or is on disk already; one holding no
        bytes as :func:`on_disk` returns it; a file of its own, :func:`on_disk`, when it
        would take over a quarter of one)."""
        a = np.asarray(a)
        if a.nbytes == 0:
            return _empty_of(a)
        if a.dtype.hasobject or is_on_disk(a):
            return a
        if 4 * a.nbytes > self._segment:
            return on_disk(a)
        start = -(-self._used // _ALIGN) * _ALIGN
        if self._map is None or start + a.nbytes > self._segment:
            self._map, start = _mapped(self._segment, None), 0
        fd = _FILES[self._map][1]
        data = memoryview(np.ascontiguousarray(a).reshape(-1)).cast("B")
        done = 0
        while done < len(data):
            done += os.pwrite(fd, data[done:], start + done)
        self._used = start + a.nbytes
        # One array object on the mapping (no memoryview, no reshaped view of a flat
        # array: a loop puts thousands, held to the run's end; 120 bytes each, not 550).
        return np.ndarray(a.shape, a.dtype, buffer=self._map, offset=start)


SEGMENT_BYTES = 1 << 24
"""Size of each of a :class:`Pack`'s files (sparse: only what was put takes disk)."""

_ALIGN = 64
"""Each array in a :class:`Pack`'s file starts at a multiple of this many bytes."""


def drop_pages() -> None:
    """Unmap the resident pages of every array :func:`on_disk` made (their values stay
    in the files: the next read maps them again, from the page cache or the disk)."""
    advice = getattr(mmap, "MADV_DONTNEED", None)
    if advice is None:  # a platform without madvise: the kernel reclaims them alone
        return
    with _MAPS_LOCK:
        mappings = list(_MAPS)
    for mapping in mappings:
        try:
            mapping.madvise(advice)
        except (ValueError, OSError):  # closed meanwhile
            continue


DROP_INTERVAL_S = 0.25
"""Seconds between two :func:`drop_pages` of :func:`dropping_pages`' thread at most."""

DROP_POLL_S = 0.01
"""Seconds between two looks of :func:`dropping_pages`' thread at the process's resident
file pages (:func:`_resident_file_bytes`)."""

DROP_GROWTH_BYTES = 4 << 20
"""Resident file pages gained since the last drop beyond which :func:`dropping_pages`'
thread drops them at once (a pass over the whole run's arrays, e.g. one NumPy expression
over every point, maps them faster than one drop per :data:`DROP_INTERVAL_S`)."""


def _resident_file_bytes(fd: int) -> int | None:
    """The process's resident file-backed and shared pages (bytes; ``/proc/self/statm``
    read through its open descriptor ``fd``), or None when it cannot be read."""
    try:
        return int(os.pread(fd, 256, 0).split()[2]) * mmap.PAGESIZE
    except (OSError, ValueError, IndexError):
        return None


@contextlib.contextmanager
def dropping_pages(interval_s: float = DROP_INTERVAL_S) -> Iterator[None]:
    """Within the block, a daemon thread calls :func:`drop_pages` every ``interval_s``
    seconds, and at once when the process's resident file pages have grown by
    :data:`DROP_GROWTH_BYTES` since the last drop (looked at every :data:`DROP_POLL_S`;
    where ``/proc/self/statm`` cannot be read, on the interval alone): the pages of the
    scratch's arrays a pass over the whole run maps (every keyframe's features, every
    frame's ring, every point) are resident for at most about that long after their last
    read, or that much of them. No value changes (a dropped page is read again from the
    page cache or the file); the mappings are this process's shared ones only (a
    worker's copy-on-write mappings, :func:`shared_on_disk`, are never dropped)."""
    stop = threading.Event()
    try:
        fd: int | None = os.open("/proc/self/statm", os.O_RDONLY)
    except OSError:
        fd = None

    def drop_until_stopped() -> None:
        poll = interval_s if fd is None else min(interval_s, DROP_POLL_S)
        level = None if fd is None else _resident_file_bytes(fd)
        last = time.monotonic()
        while not stop.wait(poll):
            now = None if fd is None else _resident_file_bytes(fd)
            grown = now is not None and level is not None and now - level >= DROP_GROWTH_BYTES
            if grown or time.monotonic() - last >= interval_s:
                drop_pages()
                level, last = (None if fd is None else _resident_file_bytes(fd)), time.monotonic()
            elif now is not None and (level is None or now < level):
                level = now  # pages dropped meanwhile (by the run's own drops)

    thread = threading.Thread(target=drop_until_stopped, name="omnipipe-drop-pages", daemon=True)
    thread.start()
    try:
        yield
    finally:
        stop.set()
        thread.join()
        if fd is not None:
            os.close(fd)


def root_buffer(a: np.ndarray) -> object:
    """The object that keeps ``a``'s values alive: the last array in its chain of views,
    or the buffer (mmap, bytes) under it."""
    base: object = a
    while isinstance(base, np.ndarray) and base.base is not None:
        base = base.base
    if isinstance(base, memoryview):
        base = base.obj
    return base


def is_on_disk(a: np.ndarray) -> bool:
    """True when ``a`` (or the array it views) lies in a file :func:`on_disk` made."""
    base = root_buffer(a)
    return isinstance(base, mmap.mmap) and base in _MAPS


def shared_on_disk(a: np.ndarray) -> np.ndarray:
    """``a``'s values in a scratch file (:func:`on_disk`), read-only: pickled for a local
    pool's worker (``multiprocessing``'s pickler, which :func:`share_with_local_workers`
    told), it is sent by reference (module docstring), not by value. ``a`` itself
    (pickled by value) when it cannot be on disk (no bytes, Python objects)."""
    b = on_disk(a)
    if not is_on_disk(b):
        return b
    b = b.view()
    b.flags.writeable = False  # what the workers read cannot change under them
    return b


def share_with_local_workers() -> None:
    """Let ``multiprocessing``'s pickler (a local process pool's queues) send the arrays
    :func:`shared_on_disk` made by reference (once per process; a no-op without
    ``/proc``)."""
    from multiprocessing.reduction import ForkingPickler

    if os.path.isdir(f"/proc/{os.getpid()}/fd"):
        ForkingPickler.register(np.ndarray, _reduce)


def _reduce(a: np.ndarray) -> tuple[Any, ...]:
    """How ``multiprocessing`` pickles an ndarray: by reference when it is one of
    :func:`shared_on_disk`'s made by this process, else as numpy does."""
    ref = _reference(a)
    if ref is None:
        return a.__reduce_ex__(pickle.DEFAULT_PROTOCOL)
    return _attach, ref


def _reference(a: np.ndarray) -> tuple[int, int, int, int, str, tuple[int, ...], tuple[int, ...]] | None:
    """(pid, fd, offset of a's lowest byte in the file, bytes spanned, dtype, shape,
    strides) of a read-only array in a scratch file this process made; None otherwise."""
    if a.flags.writeable or a.size == 0 or a.dtype.hasobject:
        return None
    base = a
    while isinstance(base, np.ndarray) and base.base is not None:
        base = base.base
    if isinstance(base, memoryview):
        base = base.obj
    known = _FILES.get(base) if isinstance(base, mmap.mmap) else None
    if known is None or known[0] != os.getpid():
        return None
    pid, fd, start = known
    low, high = _byte_bounds(a)
    return (pid, fd, low - start, high - low, a.dtype.str, a.shape, tuple(int(v) for v in a.strides))


def _byte_bounds(a: np.ndarray) -> tuple[int, int]:
    """Addresses of ``a``'s lowest byte and one past its highest."""
    low = high = a.ctypes.data
    for n, stride in zip(a.shape, a.strides, strict=True):
        if stride < 0:
            low += (n - 1) * stride
        else:
            high += (n - 1) * stride
    return low, high + a.itemsize


def _attach(
    pid: int, fd: int, offset: int, span: int, dtype: str, shape: tuple[int, ...], strides: tuple[int, ...]
) -> np.ndarray:
    """The array :func:`_reference` describes, mapped copy-on-write from the file of
    process ``pid`` (writable; its writes stay in this process)."""
    first = offset - offset % mmap.ALLOCATIONGRANULARITY
    with open(f"/proc/{pid}/fd/{fd}", "rb") as fh:
        mapping = mmap.mmap(fh.fileno(), offset + span - first, access=mmap.ACCESS_COPY, offset=first)
    below = sum(s * (n - 1) for n, s in zip(shape, strides, strict=True) if s < 0)  # <= 0
    at = offset - first - below  # the first element's byte in the mapping
    return np.ndarray(shape, np.dtype(dtype), buffer=mapping, offset=at, strides=strides)
