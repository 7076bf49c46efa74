"""The process's memory: freed pages handed back to the system between steps of a run.

Each stage frees its large intermediates when it is done with them; glibc keeps many of
the freed (small, fragmented) blocks resident, so without :func:`release_freed_memory`
the process's peak grows with the run by what earlier steps had freed.
"""

from __future__ import annotations

__all__ = ["release_freed_memory"]


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
