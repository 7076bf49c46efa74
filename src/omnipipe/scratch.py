"""Where a run keeps what waits on disk (rings, keyframe images): its private scratch folder.

Stores that keep a run's large intermediates on disk rather than in memory
(:class:`~omnipipe.laser.store.RingStore`, :class:`~omnipipe.sfm.image_store.ImageStore`)
make their folders with :func:`scratch_folder`. Inside :func:`scratch_beside` (the CLI's
``reconstruct`` and ``batch``) that is a folder ``.OUT.scratch-XXXXXXXX`` beside OUT, on
OUT's file system (the system's temporary folder may be a RAM disk, which would give
the memory back to the run); elsewhere the system's temporary folder.

Safety: the folder is made by :func:`tempfile.mkdtemp` (a new name, mode 0700: nothing
else writes into it) and carries a marker with the run's process id; it is removed when
the run ends, however it ends. A folder left by a killed run (its process gone) is
removed by the next run into the same OUT; a folder without omnipipe's marker, or whose
process still runs, is left alone.
"""

from __future__ import annotations

import contextlib
import json
import os
import shutil
import tempfile
from collections.abc import Iterator
from contextvars import ContextVar
from pathlib import Path
from types import TracebackType
from typing import Self

MARKER = "omnipipe-scratch.json"

_base: ContextVar[Path | None] = ContextVar("omnipipe_scratch_base", default=None)


def scratch_folder(prefix: str) -> tempfile.TemporaryDirectory[str]:
    """A new private temporary folder (removed by its ``cleanup``) in the run's scratch
    folder (:func:`scratch_beside`), else in the system's temporary folder."""
    base = _base.get()
    # A store closed while a run unwinds from an error may still see a dying worker's
    # last file appear: its removal then leaves the rest to scratch_beside's final sweep
    # (after the pool is gone) rather than replacing the run's error with its own.
    return tempfile.TemporaryDirectory(
        prefix=prefix, dir=None if base is None else str(base), ignore_cleanup_errors=True
    )


def scratch_dir() -> str | None:
    """The run's scratch folder (:func:`scratch_beside`), or None: the system's temporary
    folder is used."""
    base = _base.get()
    return None if base is None else str(base)


class ScratchStore:
    """Base of the stores that keep a run's files in a private :func:`scratch_folder`:
    :meth:`close` (or the end of a ``with`` block) removes the folder and its files."""

    def __init__(self, prefix: str) -> None:
        self._dir = scratch_folder(prefix)

    def close(self) -> None:
        """Remove the folder and its files."""
        self._dir.cleanup()

    def __enter__(self) -> Self:
        return self

    def __exit__(
        self,
        exc_type: type[BaseException] | None,
        exc: BaseException | None,
        tb: TracebackType | None,
    ) -> None:
        self.close()


def _prefix(out: Path) -> str:
    return f".{out.name}.scratch-"


@contextlib.contextmanager
def scratch_beside(out: str | Path) -> Iterator[Path | None]:
    """Within the block, :func:`scratch_folder` makes its folders in a private folder
    beside ``out`` (removed at the end); the folders killed runs into ``out`` left are
    removed first. Yields the folder, or None when ``out``'s parent cannot hold one
    (then the system's temporary folder is used)."""
    target = Path(os.path.abspath(Path(out).expanduser()))
    remove_stale(target)
    try:
        target.parent.mkdir(parents=True, exist_ok=True)
        folder = Path(tempfile.mkdtemp(prefix=_prefix(target), dir=target.parent))
        (folder / MARKER).write_text(
            json.dumps({"tool": "omnipipe", "kind": "scratch", "pid": os.getpid()}), encoding="utf-8"
        )
    except OSError:
        yield None
        return
    token = _base.set(folder)
    try:
        yield folder
    finally:
        _base.reset(token)
        shutil.rmtree(folder, ignore_errors=True)


def remove_stale(out: Path) -> None:
    """Remove the scratch folders beside ``out`` whose run is gone (omnipipe's marker, a
    process id that no longer runs)."""
    try:
        names = [n for n in os.listdir(out.parent) if n.startswith(_prefix(out))]
    except OSError:
        return
    for name in names:
        folder = out.parent / name
        if folder.is_symlink() or not folder.is_dir():
            continue
        try:
            data = json.loads((folder / MARKER).read_text(encoding="utf-8"))
            pid = int(data["pid"]) if data.get("tool") == "omnipipe" else None
        except (OSError, ValueError, KeyError, TypeError, AttributeError):
            continue
        if pid is not None and not _running(pid):
            shutil.rmtree(folder, ignore_errors=True)


def _running(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except OSError:  # another user's process: it runs
        return True
    return True
