"""Output directories written the way a database commits: never lose what was there.

Every directory omnipipe writes (``reconstruct``, ``demo``, ``simulate``) is built in a
temporary sibling ``.NAME.partial-XXXX`` and carries a manifest
(``.omnipipe-manifest.json``: omnipipe version, command, every file and folder it
wrote, as relative POSIX paths). Rules:

- OUT may not be the filesystem root, the home folder or one of its ancestors, the
  current folder or one of its ancestors, an input (the dataset, a config file) or an
  ancestor of one. Paths are compared after resolving symbolic links.
- An existing OUT is replaced (``force``) only if it is empty, or holds a valid manifest
  and nothing that the manifest does not list. Anything else is refused with one line
  (:class:`~omnipipe.errors.OutputError`) and nothing is touched.
- The swap keeps a complete output at OUT at every instant: on Linux the temporary
  directory and the old OUT trade places in one atomic ``renameat2(RENAME_EXCHANGE)``,
  the old one is renamed to ``.NAME.old-XXXX`` and deleted (only the files its manifest
  lists). Elsewhere (or on a file system without the exchange) the old OUT is renamed
  aside first, then the temporary directory to OUT: a kill between the two leaves OUT
  missing until the next run restores it.
- On start-up (:func:`prepare_output_dir`, also run by :func:`atomic_output_dir`) an
  interrupted swap of OUT is finished or rolled back: OUT missing and a complete
  ``.NAME.old-*`` present -> the old one is renamed back; OUT present -> leftover
  ``.NAME.old-*`` are deleted; ``.NAME.partial-*`` whose owner process is dead (its pid
  is in ``.omnipipe-pid``) are deleted. Directories without omnipipe's markers are
  never deleted.
- Start-up also refuses an OUT whose folder cannot be written (read-only, ``/proc``),
  before any work.

Swaps and recovery of one parent folder are serialised by an advisory ``flock`` on
that folder (POSIX), and SIGINT/SIGTERM are deferred during the few renames of a swap.
"""

from __future__ import annotations

import json
import os
import secrets
import shutil
import signal
import sys
import threading
import time
from collections.abc import Callable, Iterable, Iterator
from contextlib import contextmanager
from dataclasses import dataclass
from pathlib import Path, PurePosixPath

from omnipipe.errors import OutputError

MANIFEST_NAME = ".omnipipe-manifest.json"
PID_NAME = ".omnipipe-pid"
DELETING_NAME = ".omnipipe-deleting"
MARKER_NAMES = frozenset({MANIFEST_NAME, PID_NAME, DELETING_NAME})

# Test hook: called with the name of each step of the write phase (kill tests).
_step_hook: Callable[[str], None] | None = None


def _step(name: str) -> None:
    if _step_hook is not None:
        _step_hook(name)


@dataclass(frozen=True)
class Manifest:
    """What omnipipe wrote into one output directory.

    Attributes:
        files: relative POSIX paths of every file written (markers excluded).
        dirs: relative POSIX paths of every folder written.
        version: omnipipe version that wrote it.
        command: the command line that wrote it.
        written_utc: ISO time of writing.
    """

    files: frozenset[str]
    dirs: frozenset[str]
    version: str
    command: str
    written_utc: str


# --- paths ---------------------------------------------------------------------------


def _resolve(path: str | Path) -> Path:
    return Path(os.path.abspath(Path(path).expanduser())).resolve()


def _relation(target: Path, other: Path) -> str | None:
    """'is' if target == other, 'holds' if target is an ancestor of other, else None."""
    if target == other:
        return "is"
    if target in other.parents:
        return "holds"
    return None


def _check_location(out: Path, target: Path, protect: Iterable[str | Path]) -> None:
    """Refuse an OUT whose replacement could destroy something omnipipe did not write."""
    if target == Path(target.anchor):
        raise OutputError(f"{out}: is the filesystem root; choose another output folder")
    try:
        home = _resolve(Path.home())
    except (RuntimeError, KeyError):
        home = None
    rel = _relation(target, home) if home is not None else None
    if rel:
        raise OutputError(f"{out}: {rel} the home folder; choose another output folder")
    rel = _relation(target, _resolve(Path.cwd()))
    if rel:
        raise OutputError(f"{out}: {rel} the current folder; choose another output folder")
    for p in protect:
        rel = _relation(target, _resolve(p))
        if rel:
            raise OutputError(f"{out}: {rel} the input {p}; choose another output folder")


# --- manifests -----------------------------------------------------------------------


def _valid_rel(text: object) -> bool:
    if not isinstance(text, str) or not text or "\\" in text or "\0" in text:
        return False
    p = PurePosixPath(text)
    return not p.is_absolute() and ".." not in p.parts and "." not in p.parts and str(p) == text


def read_manifest(root: str | Path) -> Manifest | None:
    """The manifest of ``root``, or None if it has none or it is not omnipipe's."""
    path = Path(root) / MANIFEST_NAME
    try:
        if not path.is_file() or path.stat().st_size > 256 * 1024 * 1024:
            return None
        data = json.loads(path.read_text(encoding="utf-8"))
    except (OSError, ValueError):
        return None
    if not isinstance(data, dict) or data.get("tool") != "omnipipe":
        return None
    files, dirs = data.get("files"), data.get("dirs", [])
    if not isinstance(files, list) or not isinstance(dirs, list):
        return None
    if not all(_valid_rel(f) for f in files) or not all(_valid_rel(d) for d in dirs):
        return None
    return Manifest(
        files=frozenset(files),
        dirs=frozenset(dirs),
        version=str(data.get("version", "")),
        command=str(data.get("command", "")),
        written_utc=str(data.get("written_utc", "")),
    )


def _default_command() -> str:
    import shlex

    argv = list(sys.argv) or ["omnipipe"]
    if Path(argv[0]).name in ("omnipipe", "__main__.py", "cli.py"):
        argv[0] = "omnipipe"
    return shlex.join(argv)


def _walk(root: Path) -> tuple[list[str], list[str]]:
    """(files, dirs) under root as relative POSIX paths, top-level markers excluded."""
    files: list[str] = []
    dirs: list[str] = []
    for here, dirnames, filenames in os.walk(root, followlinks=False):
        rel_here = Path(here).relative_to(root)
        for d in list(dirnames):
            rel = (rel_here / d).as_posix()
            if os.path.islink(os.path.join(here, d)):
                dirnames.remove(d)
                files.append(rel)
            else:
                dirs.append(rel)
        for f in filenames:
            if rel_here == Path(".") and f in MARKER_NAMES:
                continue
            files.append((rel_here / f).as_posix())
    return sorted(files), sorted(dirs)


def write_manifest(root: str | Path, command: str | None = None) -> Manifest:
    """List everything under ``root`` in ``root/.omnipipe-manifest.json`` (fsynced)."""
    from omnipipe import __version__

    root = Path(root)
    files, dirs = _walk(root)
    data = {
        "tool": "omnipipe",
        "version": __version__,
        "command": command if command is not None else _default_command(),
        "written_utc": time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime()),
        "files": files,
        "dirs": dirs,
    }
    path = root / MANIFEST_NAME
    with open(path, "w", encoding="utf-8") as fh:
        json.dump(data, fh, indent=1)
        fh.flush()
        os.fsync(fh.fileno())
    return read_manifest(root)  # type: ignore[return-value]


def _foreign_entry(root: Path, manifest: Manifest) -> str | None:
    """The first entry under ``root`` that ``manifest`` does not list, or None."""
    implied = {str(p) for f in manifest.files for p in PurePosixPath(f).parents if str(p) != "."}
    own_dirs = manifest.dirs | implied
    for here, dirnames, filenames in os.walk(root, followlinks=False):
        rel_here = Path(here).relative_to(root)
        for d in sorted(dirnames):
            rel = (rel_here / d).as_posix()
            if os.path.islink(os.path.join(here, d)):
                if rel not in manifest.files:
                    return rel
            elif rel not in own_dirs:
                return rel
        dirnames[:] = [d for d in dirnames if not os.path.islink(os.path.join(here, d))]
        for f in sorted(filenames):
            if rel_here == Path(".") and f in MARKER_NAMES:
                continue
            rel = (rel_here / f).as_posix()
            if rel not in manifest.files:
                return rel
    return None


def _replace_refusal(out: Path, target: Path) -> str | None:
    """Why the existing directory ``target`` may not be replaced, or None if it may."""
    try:
        if _is_empty(target):
            return None
    except OSError as exc:
        return f"{out}: cannot read ({exc.strerror})"
    manifest = read_manifest(target)
    if manifest is None:
        if (target / MANIFEST_NAME).exists():
            return f"{out}: its {MANIFEST_NAME} is damaged; refusing to replace it"
        return f"{out}: was not written by omnipipe (no {MANIFEST_NAME}); refusing to replace it"
    foreign = _foreign_entry(target, manifest)
    if foreign is not None:
        return f"{out}: holds {foreign!r}, which omnipipe did not write; refusing to replace it"
    return None


# --- checks --------------------------------------------------------------------------


def check_output_dir(
    out: str | Path, *, force: bool = False, protect: Iterable[str | Path] = ()
) -> None:
    """Refuse an output folder that omnipipe may not (re)place. Touches nothing.

    Args:
        out: the output folder asked for.
        force: replace an existing folder (only an empty one or omnipipe's own output).
        protect: inputs (dataset directory or video, config file) OUT may not be or hold.

    Raises:
        OutputError: one line naming the path and the reason.
    """
    out = Path(out)
    target = _resolve(out)
    _check_location(out, target, protect)
    if not os.path.lexists(target):
        return
    if not target.is_dir():
        raise OutputError(f"{out}: exists and is not a directory")
    reason = _replace_refusal(out, target)
    if not force:
        if reason is None:
            raise OutputError(f"{out}: already exists (use --force to replace it)")
        raise OutputError(reason.replace("refusing to replace it", "choose another output folder"))
    if reason is not None:
        raise OutputError(reason)


def prepare_output_dir(
    out: str | Path, *, force: bool = False, protect: Iterable[str | Path] = ()
) -> None:
    """Start-up of a writing command: recover an interrupted swap of OUT, then check it.

    Raises:
        OutputError: as :func:`check_output_dir`.
    """
    out = Path(out)
    protect = tuple(protect)
    target = _resolve(out)
    _check_location(out, target, protect)
    if target.parent.is_dir():
        with _deferred_signals(), _locked(target.parent):
            recover_output_dir(target)
    check_output_dir(out, force=force, protect=protect)
    check_writable(out)


def check_writable(out: str | Path) -> None:
    """Refuse an OUT that could not be written at the end of a run: its folder (or the
    nearest existing ancestor, which would hold the folders created) must let omnipipe
    create a directory. The probe is an empty directory removed at once (beside OUT:
    ``.NAME.partial-*``, which the next run removes should a kill come in between).

    Raises:
        OutputError: one line naming OUT, the folder and the reason.
    """
    target = _resolve(out)
    parent = folder = target.parent
    while not folder.is_dir() and folder != folder.parent:
        if os.path.lexists(folder):
            raise OutputError(f"{out}: {folder} is not a folder")
        folder = folder.parent
    name = f".{target.name}.partial-" if folder == parent else ".omnipipe-probe-"
    probe = folder / f"{name}{secrets.token_hex(4)}"
    try:
        os.mkdir(probe)
        os.rmdir(probe)
    except OSError as exc:
        where = "in" if folder == parent else f"{parent}: cannot create folders in"
        raise OutputError(f"{out}: cannot write {where} {folder} ({exc.strerror})") from None


# --- recovery ------------------------------------------------------------------------


def _process_start(pid: int) -> str:
    """Start time of a process (clock ticks since boot, Linux), or '' where unknown."""
    try:
        with open(f"/proc/{pid}/stat", encoding="ascii", errors="replace") as fh:
            return fh.read().rsplit(")", 1)[1].split()[19]
    except (OSError, IndexError):
        return ""


def _alive(pid: int, start: str) -> bool:
    if pid <= 0:
        return False
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:
        return True
    except OSError:
        return False
    now = _process_start(pid)
    return not (start and now and now != start)


def _is_empty(path: Path) -> bool:
    with os.scandir(path) as it:
        return not any(True for _ in it)


def _only_markers(path: Path) -> bool:
    try:
        with os.scandir(path) as it:
            return all(e.name in MARKER_NAMES and e.is_file(follow_symlinks=False) for e in it)
    except OSError:
        return False


def _remove_markers_and_dir(path: Path) -> None:
    for name in (MANIFEST_NAME, DELETING_NAME, PID_NAME):  # the pid file goes last
        try:
            (path / name).unlink()
        except FileNotFoundError:
            pass
    try:
        path.rmdir()
    except FileNotFoundError:
        pass


def _remove_partial(path: Path) -> None:
    """Delete a temporary directory of ours; its markers go last (a kill mid-way leaves
    a directory the next run still recognises)."""
    with os.scandir(path) as it:
        entries = list(it)
    for entry in entries:
        if entry.name in MARKER_NAMES:
            continue
        if entry.is_dir(follow_symlinks=False):
            shutil.rmtree(entry.path, ignore_errors=True)
        else:
            try:
                os.unlink(entry.path)
            except FileNotFoundError:
                pass
    _remove_markers_and_dir(path)


def _remove_own(path: Path) -> None:
    """Delete what the manifest of ``path`` lists, then the folder if nothing else is left.

    Files omnipipe did not write are kept (with a warning line naming the folder).
    """
    manifest = read_manifest(path)
    if manifest is None:
        if _only_markers(path):
            _remove_markers_and_dir(path)
        return
    (path / DELETING_NAME).touch()
    _step("old-marked")
    for i, rel in enumerate(sorted(manifest.files)):
        try:
            os.unlink(path / rel)
        except OSError:
            pass
        if i == 0:
            _step("old-partly-deleted")
    implied = {str(p) for f in manifest.files for p in PurePosixPath(f).parents if str(p) != "."}
    for rel in sorted(manifest.dirs | implied, key=lambda d: d.count("/"), reverse=True):
        try:
            (path / rel).rmdir()
        except OSError:
            pass
    if _only_markers(path):
        _remove_markers_and_dir(path)
    else:
        print(f"omnipipe: kept {path}: it holds files omnipipe did not write", file=sys.stderr)


def _complete(path: Path) -> Manifest | None:
    """The manifest of a complete output directory, or None."""
    if (path / DELETING_NAME).exists() or (path / PID_NAME).exists():
        return None
    manifest = read_manifest(path)
    if manifest is None:
        return None
    if not all(os.path.lexists(path / f) for f in manifest.files):
        return None
    return manifest


def recover_output_dir(out: str | Path) -> list[str]:
    """Finish or roll back an interrupted swap of ``out``; delete dead temporaries.

    Call with the parent folder locked (:func:`prepare_output_dir` does). Only
    directories named ``.NAME.partial-*`` / ``.NAME.old-*`` that carry omnipipe's
    markers are touched.

    Returns:
        what was done, one short phrase per action (for logs and tests).
    """
    target = _resolve(out)
    parent, name = target.parent, target.name
    done: list[str] = []
    try:
        with os.scandir(parent) as it:
            entries = [
                e for e in it
                if e.name.startswith(f".{name}.") and e.is_dir(follow_symlinks=False)
            ]
    except OSError:
        return done
    olds = sorted(Path(e.path) for e in entries if e.name.startswith(f".{name}.old-"))
    partials = sorted(Path(e.path) for e in entries if e.name.startswith(f".{name}.partial-"))
    for p in partials:
        pid_file = p / PID_NAME
        if pid_file.is_file():
            try:
                fields = pid_file.read_text(encoding="ascii").split()
                pid, start = int(fields[0]), (fields[1] if len(fields) > 1 else "")
            except (OSError, ValueError, IndexError):
                pid, start = -1, ""
            if _alive(pid, start):
                continue
        elif read_manifest(p) is not None:
            # Complete but never swapped in, or the old OUT just exchanged out of place:
            # only what its manifest lists is deleted.
            _remove_own(p)
            done.append(f"removed {p.name}")
            continue
        elif not _only_markers(p):
            continue  # not recognisably ours: leave it alone
        _remove_partial(p)
        done.append(f"removed {p.name}")
    if not os.path.lexists(target):
        complete = [(m.written_utc, o) for o in olds if (m := _complete(o)) is not None]
        if complete:
            _, newest = max(complete)
            os.rename(newest, target)
            _fsync_dir(parent)
            olds.remove(newest)
            done.append(f"restored {target.name} from {newest.name}")
    if os.path.lexists(target):
        for o in olds:
            _remove_own(o)
            done.append(f"removed {o.name}")
    elif olds:
        for o in olds:
            if _only_markers(o):
                _remove_markers_and_dir(o)
                done.append(f"removed {o.name}")
    return done


# --- the swap --------------------------------------------------------------------------


def _fsync_dir(path: Path) -> None:
    try:
        fd = os.open(path, os.O_RDONLY)
    except OSError:
        return
    try:
        os.fsync(fd)
    except OSError:
        pass
    finally:
        os.close(fd)


def _fsync_tree(root: Path) -> None:
    """Flush every file and folder under ``root`` to disk (before it is renamed in)."""
    for here, _dirnames, filenames in os.walk(root):
        for f in filenames:
            try:
                fd = os.open(os.path.join(here, f), os.O_RDONLY)
            except OSError:
                continue
            try:
                os.fsync(fd)
            except OSError:
                pass
            finally:
                os.close(fd)
        _fsync_dir(Path(here))


@contextmanager
def _locked(folder: Path) -> Iterator[None]:
    """Exclusive advisory lock on ``folder`` (POSIX flock; a no-op where unsupported)."""
    try:
        import fcntl
    except ImportError:
        yield
        return
    try:
        fd = os.open(folder, os.O_RDONLY)
    except OSError:
        yield
        return
    try:
        try:
            fcntl.flock(fd, fcntl.LOCK_EX)
        except OSError:
            pass
        yield
    finally:
        os.close(fd)  # releases the lock


@contextmanager
def _deferred_signals() -> Iterator[None]:
    """Hold SIGINT/SIGTERM until the block is done, then deliver them."""
    if threading.current_thread() is not threading.main_thread():
        yield
        return
    pending: list[int] = []
    saved: dict[int, object] = {}

    def record(signum: int, frame: object) -> None:
        pending.append(signum)

    for sig in (signal.SIGINT, signal.SIGTERM):
        try:
            saved[sig] = signal.signal(sig, record)
        except (ValueError, OSError):
            pass
    try:
        yield
    finally:
        for sig, handler in saved.items():
            signal.signal(sig, handler)  # type: ignore[arg-type]
        for sig in dict.fromkeys(pending):
            signal.raise_signal(sig)


def _make_partial(parent: Path, name: str) -> Path:
    for _ in range(100):
        tmp = parent / f".{name}.partial-{secrets.token_hex(4)}"
        try:
            os.mkdir(tmp)
        except FileExistsError:
            continue
        pid = os.getpid()
        try:
            with open(tmp / PID_NAME, "w", encoding="ascii") as fh:
                fh.write(f"{pid} {_process_start(pid)}\n")
                fh.flush()
                os.fsync(fh.fileno())
        except OSError:
            _remove_markers_and_dir(tmp)
            raise
        _fsync_dir(parent)
        return tmp
    raise OutputError(f"{parent / name}: cannot create a temporary folder beside it")


# renameat2(2)'s flag and "relative to the current folder" (Linux).
_RENAME_EXCHANGE = 2
_AT_FDCWD = -100
# The renameat2 system call's number where glibc < 2.28 lacks the function.
_SYS_RENAMEAT2 = {"x86_64": 316, "aarch64": 276, "riscv64": 276, "ppc64le": 357, "s390x": 347}
_renameat2_fn: list = []


def _renameat2():  # -> Callable[[int, bytes, int, bytes, int], int] | None
    """libc's renameat2 (or the raw system call), None where there is none."""
    if _renameat2_fn:
        return _renameat2_fn[0]
    fn = None
    if sys.platform.startswith("linux"):
        import ctypes
        import platform

        try:
            libc = ctypes.CDLL(None, use_errno=True)
        except OSError:
            libc = None
        if libc is not None and hasattr(libc, "renameat2"):
            fn = libc.renameat2
            fn.argtypes = [ctypes.c_int, ctypes.c_char_p, ctypes.c_int, ctypes.c_char_p,
                           ctypes.c_uint]
            fn.restype = ctypes.c_int
        elif libc is not None and platform.machine() in _SYS_RENAMEAT2:
            number = _SYS_RENAMEAT2[platform.machine()]
            syscall = libc.syscall
            syscall.restype = ctypes.c_long

            def fn(a: int, old: bytes, b: int, new: bytes, flags: int) -> int:
                return int(syscall(ctypes.c_long(number), ctypes.c_int(a), ctypes.c_char_p(old),
                                   ctypes.c_int(b), ctypes.c_char_p(new), ctypes.c_uint(flags)))
    _renameat2_fn.append(fn)
    return fn


def _exchange(a: Path, b: Path) -> bool:
    """Swap the directories ``a`` and ``b`` in one atomic step
    (``renameat2(RENAME_EXCHANGE)``, Linux >= 3.15). False, with nothing done, where the
    system or the file system has no such exchange.

    Raises:
        OSError: the exchange is supported but failed.
    """
    import ctypes
    import errno

    fn = _renameat2()
    if fn is None:
        return False
    if fn(_AT_FDCWD, os.fsencode(a), _AT_FDCWD, os.fsencode(b), _RENAME_EXCHANGE) == 0:
        return True
    err = ctypes.get_errno()
    if err in (errno.EINVAL, errno.ENOSYS, errno.EOPNOTSUPP, errno.EPERM):
        return False
    raise OSError(err, os.strerror(err), str(b))


def _swap(tmp: Path, target: Path) -> Path | None:
    """Put ``tmp`` in place of ``target``; returns the old directory set aside (or None).

    With the atomic exchange OUT holds a complete output at every instant; without it,
    it is missing between the two renames (the next start-up restores it).
    """
    parent = target.parent
    old: Path | None = None
    if os.path.lexists(target):
        if _is_empty(target):
            target.rmdir()
        elif _exchange(tmp, target):
            _step("new-in")  # OUT is the new output; ``tmp`` the old one
            old = parent / f".{target.name}.old-{secrets.token_hex(4)}"
            os.rename(tmp, old)
            _step("old-aside")
            _fsync_dir(parent)
            _step("synced")
            return old
        else:
            old = parent / f".{target.name}.old-{secrets.token_hex(4)}"
            os.rename(target, old)
            _step("old-aside")
    try:
        os.rename(tmp, target)
    except OSError:
        if old is not None and not os.path.lexists(target):
            os.rename(old, target)
        raise
    _step("new-in")
    _fsync_dir(parent)
    _step("synced")
    return old


@contextmanager
def atomic_output_dir(
    out: str | Path,
    *,
    force: bool = False,
    protect: Iterable[str | Path] = (),
    command: str | None = None,
) -> Iterator[Path]:
    """A temporary sibling directory that becomes ``out`` only when the block succeeds.

    Before: an interrupted swap of ``out`` is recovered and ``out`` is checked
    (:func:`check_output_dir`). After the block: a manifest is written, everything is
    flushed to disk, ``out`` is checked again and swapped in (old output renamed aside,
    new renamed in, old deleted). On any exception (also KeyboardInterrupt and other
    BaseExceptions) the temporary directory is deleted and ``out`` is left as it was.

    Args:
        out: the output folder.
        force: replace an existing folder that omnipipe wrote (or an empty one).
        protect: inputs ``out`` may not be or hold.
        command: recorded in the manifest (default: this process's command line).

    Yields:
        the temporary directory to write into.

    Raises:
        OutputError: ``out`` may not be written or replaced, or the file system refuses.
    """
    out = Path(out)
    protect = tuple(protect)
    target = _resolve(out)
    parent = target.parent
    _check_location(out, target, protect)
    try:
        parent.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        raise OutputError(f"{out}: cannot write ({exc.strerror})") from None
    tmp: Path | None = None
    try:
        # A signal arriving here is delivered when the block ends, by then ``tmp`` is
        # known and removed by the handler below.
        with _deferred_signals(), _locked(parent):
            recover_output_dir(target)
            check_output_dir(out, force=force, protect=protect)
            try:
                tmp = _make_partial(parent, target.name)
            except OSError as exc:
                raise OutputError(f"{out}: cannot write ({exc.strerror})") from None
        _step("partial-created")
        yield tmp
        _step("files-written")
        write_manifest(tmp, command)
        _step("manifest-written")
        _fsync_tree(tmp)
        with _deferred_signals():
            with _locked(parent):
                check_output_dir(out, force=force, protect=protect)
                (tmp / PID_NAME).unlink()
                _step("pid-removed")
                try:
                    old = _swap(tmp, target)
                except OSError as exc:
                    raise OutputError(f"{out}: cannot replace ({exc.strerror})") from None
            if old is not None:
                _remove_own(old)
        _step("done")
    except BaseException:
        with _deferred_signals():
            if tmp is not None and tmp.is_dir():
                _remove_partial(tmp)
        raise
