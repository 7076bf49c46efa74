"""Native libraries' own complaints on the process's stderr, silenced where omnipipe
reports the problem itself."""

from __future__ import annotations

import os
import sys
import threading
from collections.abc import Iterator
from contextlib import contextmanager

_STDERR_LOCK = threading.Lock()
_STDERR_STATE: dict[str, int] = {"depth": 0, "saved": -1}


@contextmanager
def quiet_native_stderr() -> Iterator[None]:
    """Silence what C libraries write to file descriptor 2 inside the block.

    libpng, libjpeg, FFmpeg and OpenCV's logger print their own complaints straight to
    the process's stderr (e.g. "libpng error: Read Error"), ahead of omnipipe's one-line
    error. Inside the block fd 2 points at the null device; it is restored on every
    exit path. Python's ``sys.stderr`` is flushed first so nothing of ours is lost.
    Re-entrant and thread-safe (the outermost block owns the redirection).
    """
    with _STDERR_LOCK:
        if _STDERR_STATE["depth"] == 0:
            try:
                sys.stderr.flush()
            except (AttributeError, OSError, ValueError):
                pass
            try:
                saved = os.dup(2)
                null = os.open(os.devnull, os.O_WRONLY)
                try:
                    os.dup2(null, 2)
                finally:
                    os.close(null)
            except OSError:
                saved = -1  # no usable fd 2: nothing to silence
            _STDERR_STATE["saved"] = saved
        _STDERR_STATE["depth"] += 1
    try:
        yield
    finally:
        with _STDERR_LOCK:
            _STDERR_STATE["depth"] -= 1
            if _STDERR_STATE["depth"] == 0 and _STDERR_STATE["saved"] >= 0:
                os.dup2(_STDERR_STATE["saved"], 2)
                os.close(_STDERR_STATE["saved"])
                _STDERR_STATE["saved"] = -1
