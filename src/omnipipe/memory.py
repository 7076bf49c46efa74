"""The process's memory: freed pages handed back to the system between steps of a run.

Each stage frees its large intermediates when it is done with them; glibc keeps many of
the freed (small, fragmented) blocks resident, so without :func:`release_freed_memory`
the process's peak grows with the run by what earlier steps had freed.
"""

from __future__ import annotations

__all__ = ["release_freed_memory", "return_large_blocks"]

MMAP_THRESHOLD_BYTES = 1 << 20
"""Blocks of at least this many bytes are mapped on their own by glibc's allocator
(:func:`return_large_blocks`): freed, their pages go back to the system at once."""

TRIM_THRESHOLD_BYTES = 4 << 20
"""Free bytes at the top of glibc's heap beyond which a ``free`` gives them back."""

_M_TRIM_THRESHOLD = -1
_M_MMAP_THRESHOLD = -3
"""glibc's ``mallopt`` parameter numbers (malloc.h)."""


def return_large_blocks() -> None:
    """Make glibc's allocator give the pages of large freed blocks back to the system at
    once, in this process and the workers it forks later (``mallopt``; idempotent; a
    no-op where the C library has none).

    glibc maps a block of its own only above a threshold that it raises to the size of
    every mapped block freed, up to 32 MiB: after the first large array of a run is
    freed, arrays up to that size (a long run's per-point and per-cell arrays) are made
    in the heap, and their pages stay resident when freed, under the later steps, until
    :func:`release_freed_memory`. The more a step's arrays grow with the run, the more
    the process's peak grew with them. Fixed thresholds
    (:data:`MMAP_THRESHOLD_BYTES`, :data:`TRIM_THRESHOLD_BYTES`) keep every block of 1 MiB
    and more mapped on its own. No effect on any result.
    """
    import ctypes

    try:
        mallopt = ctypes.CDLL(None).mallopt
    except (OSError, AttributeError):
        return
    mallopt(_M_MMAP_THRESHOLD, MMAP_THRESHOLD_BYTES)
    mallopt(_M_TRIM_THRESHOLD, TRIM_THRESHOLD_BYTES)


def release_freed_memory() -> None:
    """Return the pages the C allocator holds free to the system (glibc's ``malloc_trim``).

    A stage's many small freed blocks (rings, features, matches, qhull's work) otherwise
    stay resident under the next stage's arrays, so the process's peak grew with the run
    by what the earlier stages had freed. Also unmaps the pages of the arrays kept in
    the run's scratch (:func:`omnipipe.spill.drop_pages`): the next step maps only
    what it reads. No effect on any result; ``malloc_trim`` a no-op where the C
    library has none.
    """
    import ctypes

    from omnipipe.spill import drop_pages

    drop_pages()
    try:
        trim = ctypes.CDLL(None).malloc_trim
    except (OSError, AttributeError):
        return
    trim(0)
