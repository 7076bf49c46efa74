"""omnipipe.memory: large freed blocks go back to the system at once."""

import ctypes
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from omnipipe.memory import return_large_blocks


def _anon_mb() -> float:
    """The process's resident anonymous memory (MB), counted exactly: smaps_rollup walks
    the page tables, while status's RssAnon is the kernel's per-CPU-batched counter,
    which was seen not to move at all over a 24 MB array in a long test process."""
    try:
        with open("/proc/self/smaps_rollup", encoding="ascii") as fh:
            for line in fh:
                if line.startswith("Anonymous:"):
                    return int(line.split()[1]) / 1024.0
    except OSError:
        pass
    with open("/proc/self/status", encoding="ascii") as fh:
        for line in fh:
            if line.startswith("RssAnon:"):
                return int(line.split()[1]) / 1024.0
    raise AssertionError("no RssAnon")


def _has_mallopt() -> bool:
    try:
        ctypes.CDLL(None).mallopt  # noqa: B018
    except (OSError, AttributeError):
        return False
    return True


def _freed_blocks_leave() -> None:
    """The check itself, run in a fresh process (:func:`test_large_freed_blocks_leave_the_resident_memory`)."""
    return_large_blocks()
    return_large_blocks()  # idempotent
    # glibc's default raises its mapping threshold to a freed mapped block's size: the
    # second array would then be made in the heap and stay resident once freed.
    for _ in range(3):
        before = _anon_mb()
        a = np.ones(3 << 20)  # 24 MB, every page touched
        assert _anon_mb() > before + 20
        del a
        assert _anon_mb() < before + 4


@pytest.mark.skipif(not sys.platform.startswith("linux") or not _has_mallopt(), reason="glibc on Linux")
def test_large_freed_blocks_leave_the_resident_memory():
    # A fresh process: in a long test process the allocator's state left by earlier
    # tests (other threads' arenas, cached blocks) made the 24 MB array's pages already
    # resident, and the first assertion saw no growth.
    code = "import tests.test_memory as m; m._freed_blocks_leave()"
    root = Path(__file__).resolve().parent.parent
    done = subprocess.run([sys.executable, "-c", code], cwd=root, capture_output=True, text=True, timeout=120)
    assert done.returncode == 0, done.stderr[-2000:]
