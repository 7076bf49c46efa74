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
with any file's.
"""

from __future__ import annotations

import mmap
import tempfile
import weakref

import numpy as np

from omnipipe.scratch import scratch_dir

_MAPS: weakref.WeakSet[mmap.mmap] = weakref.WeakSet()
"""Every live mapping made here (gone when its last array is)."""

_COPY_BYTES = 1 << 22
"""Bytes copied into the file at a time by :func:`on_disk` (no second whole copy)."""


def _mapped(nbytes: int, fill: np.ndarray | None) -> mmap.mmap:
    """A shared, writable mapping of a new unnamed scratch file of ``nbytes`` bytes
    (zeros, or ``fill``'s bytes written in)."""
    with tempfile.TemporaryFile(prefix="omnipipe-spill-", dir=scratch_dir()) as fh:
        if fill is None:
            fh.truncate(nbytes)
        else:
            flat = fill.reshape(-1)  # C order (a copy only if ``fill`` is not contiguous)
            step = max(1, _COPY_BYTES // max(fill.itemsize, 1))
            for a in range(0, len(flat), step):
                fh.write(memoryview(np.ascontiguousarray(flat[a : a + step])).cast("B"))
            fh.flush()
        mapping = mmap.mmap(fh.fileno(), nbytes)  # holds its own copy of the descriptor
    _MAPS.add(mapping)
    return mapping


def on_disk(a: np.ndarray) -> np.ndarray:
    """``a``'s values in a scratch file (module docstring): an (C-ordered) array of the
    same dtype, shape and values, writable; ``a`` itself when it holds no bytes, its
    dtype holds Python objects or it is on disk already."""
    a = np.asarray(a)
    if a.nbytes == 0 or a.dtype.hasobject or is_on_disk(a):
        return a
    mapping = _mapped(a.nbytes, a)
    return np.frombuffer(mapping, a.dtype, count=a.size).reshape(a.shape)


def zeros_on_disk(shape: tuple[int, ...], dtype: np.dtype | type) -> np.ndarray:
    """A new array of zeros of ``shape`` and ``dtype`` in a scratch file (module docstring)."""
    dt = np.dtype(dtype)
    size = int(np.prod(shape, dtype=np.int64))
    if size * dt.itemsize == 0:
        return np.zeros(shape, dt)
    return np.frombuffer(_mapped(size * dt.itemsize, None), dt, count=size).reshape(shape)


def pieces_on_disk(pieces: list[np.ndarray]) -> list[np.ndarray]:
    """Arrays of equal trailing shape and dtype (e.g. each ring's (M_k, 2) pixels) in one
    scratch file (:func:`on_disk`): views of it, one per piece, equal to the pieces."""
    if not pieces:
        return []
    whole = on_disk(np.concatenate(pieces))
    ends = np.cumsum([len(p) for p in pieces])
    return [whole[a:b] for a, b in zip(np.concatenate([[0], ends[:-1]]).tolist(), ends.tolist(), strict=True)]


def drop_pages() -> None:
    """Unmap the resident pages of every array :func:`on_disk` made (their values stay
    in the files: the next read maps them again, from the page cache or the disk)."""
    advice = getattr(mmap, "MADV_DONTNEED", None)
    if advice is None:  # a platform without madvise: the kernel reclaims them alone
        return
    for mapping in list(_MAPS):
        try:
            mapping.madvise(advice)
        except (ValueError, OSError):  # closed meanwhile
            continue


def is_on_disk(a: np.ndarray) -> bool:
    """True when ``a`` (or the array it views) lies in a file :func:`on_disk` made."""
    base = a
    while isinstance(base, np.ndarray) and base.base is not None:
        base = base.base
    if isinstance(base, memoryview):
        base = base.obj
    return isinstance(base, mmap.mmap) and base in _MAPS
