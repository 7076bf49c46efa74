"""Stage checkpoints of ``omnipipe reconstruct``: a rerun resumes where a run stopped.

After each long stage (the frame pass, the camera motion, the analysis, the model) the
run saves that stage's result in a checkpoint folder beside OUT,
``.OUT.resume-KEY/`` (KEY: 16 hex digits of :func:`run_key`, a SHA-256 of the
dataset's listing (frame names, sizes, modification times, the timestamps), the rig,
every setting of the configuration that changes a result, the omnipipe version and
:data:`FORMAT`). A rerun into the same OUT with the same dataset, rig and settings finds
the folder and loads the latest stage saved instead of computing it again; a changed
input or setting gives another KEY, so a stale checkpoint is never read.

Files: ``checkpoint.json`` (the marker: tool, format, key, the stages saved) and per
stage ``STAGE.json`` (the result's structure, :func:`encode`) with ``STAGE.npz`` (its
arrays, loaded without pickle) and, for a result holding a
:class:`~omnipipe.laser.store.RingStore` (the frame pass's rings), ``STAGE.rings``: a
copy of the store's file, copied a block at a time both ways, so neither saving nor
resuming reads every ring into memory. Results are rebuilt field by field into their
dataclasses (only classes of the ``omnipipe`` package), so a loaded stage is equal, bit
for bit, to the one saved. A checkpoint that cannot be read (damaged, written by
another format) is ignored: the stage is computed again.

Safety: the folder is not OUT and not the run's temporary output, so the swap of OUT
(:mod:`omnipipe.output`) never sees it; it is removed after the run's output is in
place, and only the files its marker lists are deleted (then the folder, if empty).
"""

from __future__ import annotations

import dataclasses
import hashlib
import importlib
import json
import os
import pickle
import secrets
from collections.abc import Callable, Iterator, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from omnipipe.laser.store import RingStore

if TYPE_CHECKING:
    from omnipipe.dataset import Dataset

FORMAT = 4  # 2: rings hold centroid_shift_px (a RingStore record has one more array); 3: one header per RingStore record; 4: rings hold gap_edges (one more array)
MARKER = "checkpoint.json"
STAGES = ("frames", "sfm", "analysis", "model")

# Test hook: called with the stage's name after each checkpoint is saved (kill tests).
_saved_hook: Callable[[str], None] | None = None


class CheckpointFormatError(ValueError):
    """A value that cannot be saved, or a saved structure that cannot be rebuilt."""


# --- the key -------------------------------------------------------------------------


def _stat_line(path: Path) -> str:
    try:
        st = path.stat()
    except OSError:
        return f"{path.name} missing"
    return f"{path.name} {st.st_size} {st.st_mtime_ns}"


def run_key(dataset: Dataset, settings: object) -> str:
    """SHA-256 (hex) of what a run's result depends on: the dataset's listing, its rig,
    ``settings`` (the configuration without its executor choice), the omnipipe version
    and the checkpoint format. File contents are represented by size and modification
    time (reading a kilometre of frames to hash them would cost a pass of its own)."""
    from omnipipe import __version__

    h = hashlib.sha256()
    h.update(f"omnipipe {__version__} checkpoint format {FORMAT}\n".encode())
    h.update(str(Path(dataset.root).resolve()).encode() + b"\n")
    for path in dataset.frame_paths:
        h.update(_stat_line(Path(path)).encode() + b"\n")
    for extra in (dataset.video, getattr(dataset.source, "path", None)):
        if extra is not None:
            h.update(_stat_line(Path(extra)).encode() + b"\n")
    h.update(str(getattr(dataset.source, "topic", "")).encode() + b"\n")
    h.update(np.ascontiguousarray(dataset.timestamps, float).tobytes())
    # Pickled only to be hashed (never stored nor loaded): the values of the dataclasses.
    h.update(pickle.dumps(dataset.rig, protocol=4))
    h.update(pickle.dumps(settings, protocol=4))
    return h.hexdigest()


def checkpoint_dir(out: str | Path, key: str) -> Path:
    """The checkpoint folder of a run into ``out`` with key ``key``."""
    target = Path(os.path.abspath(Path(out).expanduser()))
    return target.parent / f".{target.name}.resume-{key[:16]}"


def checkpoint_dirs(out: str | Path) -> list[Path]:
    """Every checkpoint folder of runs into ``out`` (any key) that carries omnipipe's
    marker."""
    target = Path(os.path.abspath(Path(out).expanduser()))
    prefix = f".{target.name}.resume-"
    try:
        names = sorted(n for n in os.listdir(target.parent) if n.startswith(prefix))
    except OSError:
        return []
    return [target.parent / n for n in names if _read_marker(target.parent / n) is not None]


# --- encoding ------------------------------------------------------------------------


class _Encoder:
    """A value -> JSON-able structure, its arrays collected under generated names."""

    def __init__(self) -> None:
        self.arrays: dict[str, np.ndarray] = {}
        self.store: RingStore | None = None  # the one ring store of the value, if any

    def array(self, a: np.ndarray) -> str:
        if a.dtype.hasobject:
            raise CheckpointFormatError("an array of Python objects cannot be saved")
        name = f"a{len(self.arrays)}"
        self.arrays[name] = a
        return name

    def __call__(self, v: Any) -> Any:
        if v is None or isinstance(v, (bool, str)) or type(v) in (int, float):
            return v
        if isinstance(v, np.ndarray):
            return {"a": self.array(v)}
        if isinstance(v, np.generic):
            return {"s": self.array(np.asarray(v))}
        if dataclasses.is_dataclass(v) and not isinstance(v, type):
            return {"c": _class_name(type(v)), "f": self.fields(v)}
        if isinstance(v, Path):
            return {"p": str(v)}
        if isinstance(v, dict):
            if all(isinstance(k, str) for k in v):
                return {"d": {k: self(x) for k, x in v.items()}}
            return {"dp": [[self(k), self(x)] for k, x in v.items()]}
        if isinstance(v, tuple):
            return {"t": [self(x) for x in v]}
        if isinstance(v, RingStore):  # its file copied beside, not its rings read
            if self.store is not None:
                raise CheckpointFormatError("a value holds more than one ring store")
            self.store = v
            return {"rs": self(v.index())}
        if isinstance(v, (list, Sequence)) or (hasattr(v, "__len__") and hasattr(v, "__getitem__")):
            items = [v[i] for i in range(len(v))]
            kind = type(items[0]) if items else None
            if kind is not None and dataclasses.is_dataclass(kind) and all(
                type(x) is kind for x in items
            ):
                return self.columns(kind, items)
            return {"l": [self(x) for x in items]}
        raise CheckpointFormatError(f"a {type(v).__name__} cannot be saved in a checkpoint")

    def fields(self, v: Any) -> dict[str, Any]:
        return {f.name: self(getattr(v, f.name)) for f in dataclasses.fields(v)}

    def columns(self, kind: type, items: list[Any]) -> dict[str, Any]:
        """A list of one dataclass stored by field: array fields concatenated (one
        array and the lengths), the rest as lists."""
        cols: dict[str, Any] = {}
        for f in dataclasses.fields(kind):
            values = [getattr(x, f.name) for x in items]
            if all(isinstance(a, np.ndarray) and a.ndim >= 1 for a in values) and (
                len({(a.dtype.str, a.shape[1:]) for a in values}) == 1
            ):
                cols[f.name] = {
                    "cat": self.array(np.concatenate(values)),
                    "len": self.array(np.array([len(a) for a in values], np.int64)),
                }
            else:
                cols[f.name] = {"l": [self(x) for x in values]}
        return {"cols": _class_name(kind), "n": len(items), "f": cols}


def _class_name(kind: type) -> str:
    return f"{kind.__module__}:{kind.__qualname__}"


def _class(name: str) -> type:
    module, _, qualname = name.partition(":")
    if module != "omnipipe" and not module.startswith("omnipipe."):
        raise CheckpointFormatError(f"{name}: not an omnipipe class")
    obj: Any = importlib.import_module(module)
    for part in qualname.split("."):
        obj = getattr(obj, part)
    if not (isinstance(obj, type) and dataclasses.is_dataclass(obj)):
        raise CheckpointFormatError(f"{name}: not a dataclass")
    return obj


def _build(kind: type, values: dict[str, Any]) -> Any:
    """An instance of the dataclass ``kind`` with exactly these field values (no
    ``__init__``: nothing is recomputed or validated again)."""
    names = {f.name for f in dataclasses.fields(kind)}
    if set(values) != names:
        raise CheckpointFormatError(f"{kind.__name__}: saved fields differ from the class's")
    obj = object.__new__(kind)
    for k, v in values.items():
        object.__setattr__(obj, k, v)
    return obj


def decode(node: Any, arrays: dict[str, np.ndarray], rings: Path | None = None) -> Any:
    """The value :class:`_Encoder` turned into ``node`` (arrays from ``arrays``, a ring
    store's file copied from ``rings``)."""
    if node is None or isinstance(node, (bool, int, float, str)):
        return node
    if not isinstance(node, dict) or len(node) not in (1, 2, 3):
        raise CheckpointFormatError("unknown node")
    if "a" in node:
        return arrays[node["a"]]
    if "s" in node:
        return arrays[node["s"]][()]
    if "c" in node:
        kind = _class(node["c"])
        return _build(kind, {k: decode(v, arrays, rings) for k, v in node["f"].items()})
    if "p" in node:
        return Path(node["p"])
    if "d" in node:
        return {k: decode(v, arrays, rings) for k, v in node["d"].items()}
    if "dp" in node:
        return {decode(k, arrays, rings): decode(v, arrays, rings) for k, v in node["dp"]}
    if "t" in node:
        return tuple(decode(x, arrays, rings) for x in node["t"])
    if "l" in node:
        return [decode(x, arrays, rings) for x in node["l"]]
    if "cols" in node:
        return _decode_columns(node, arrays)
    if "rs" in node:
        if rings is None:
            raise CheckpointFormatError("a ring store without its file")
        return RingStore.restore(rings, decode(node["rs"], arrays))
    raise CheckpointFormatError("unknown node")


def _decode_columns(node: dict[str, Any], arrays: dict[str, np.ndarray]) -> list[Any]:
    kind, n = _class(node["cols"]), int(node["n"])
    columns: dict[str, list[Any]] = {}
    for name, col in node["f"].items():
        if "cat" in col:
            cat, lens = arrays[col["cat"]], arrays[col["len"]]
            columns[name] = np.split(cat, np.cumsum(lens)[:-1]) if n else []
        else:
            columns[name] = decode(col, arrays)
        if len(columns[name]) != n:
            raise CheckpointFormatError(f"{kind.__name__}.{name}: wrong length")
    # np.split gives views of one array: each item its own copy, as it was saved.
    return [
        _build(kind, {k: (v[i].copy() if isinstance(v[i], np.ndarray) and "cat" in node["f"][k]
                          else v[i]) for k, v in columns.items()})
        for i in range(n)
    ]


# --- the folder ----------------------------------------------------------------------


def _savez(fh: Any, arrays: dict[str, np.ndarray]) -> None:
    """``np.savez(fh, **arrays)`` (the same archive), the pages of the arrays kept in the
    run's scratch (:mod:`omnipipe.spill`) unmapped after each: the save holds one
    array's, not the stage's."""
    import zipfile

    from omnipipe.spill import drop_pages

    with zipfile.ZipFile(fh, mode="w", compression=zipfile.ZIP_STORED, allowZip64=True) as zf:
        for key, value in arrays.items():
            with zf.open(key + ".npy", "w", force_zip64=True) as member:
                np.lib.format.write_array(member, np.asanyarray(value), allow_pickle=False)
            drop_pages()


def _write_atomic(path: Path, write: Callable[[Any], None], mode: str = "wb") -> None:
    tmp = path.with_name(f".{path.name}.{secrets.token_hex(4)}.tmp")
    try:
        with open(tmp, mode) as fh:
            write(fh)
            fh.flush()
            os.fsync(fh.fileno())
        os.replace(tmp, path)
    except BaseException:
        try:
            tmp.unlink()
        except FileNotFoundError:
            pass
        raise


@dataclass
class Checkpoints:
    """The checkpoint folder of one run (see the module's docstring).

    Attributes:
        folder: ``.OUT.resume-KEY`` beside OUT.
        key: the run's key (:func:`run_key`).
        saved: the stages saved so far (read from the marker when the folder exists).
        parts: per stage, how many parts of it are saved (a stage saved in parts as it
            goes, e.g. the frame pass; its parts are deleted once it is saved whole).
        problems: why a stage saved earlier could not be loaded or a stage not saved
            (one line each; the run goes on without it).
    """

    folder: Path
    key: str
    saved: list[str] = field(default_factory=list)
    parts: dict[str, int] = field(default_factory=dict)
    problems: list[str] = field(default_factory=list)

    @staticmethod
    def open(out: str | Path, key: str) -> Checkpoints:
        """The checkpoints of a run into ``out`` with ``key`` (the folder is created at
        the first save)."""
        cp = Checkpoints(checkpoint_dir(out, key), key)
        marker = _read_marker(cp.folder)
        if marker is not None and marker.get("key") == key:
            cp.saved = [s for s in marker.get("stages", []) if s in STAGES]
            parts = marker.get("parts", {})
            if isinstance(parts, dict):
                cp.parts = {s: int(k) for s, k in parts.items() if s in STAGES and isinstance(k, int)}
        return cp

    def load(self, stage: str) -> Any | None:
        """The result saved for ``stage``, or None (not saved, or unreadable: noted in
        ``problems`` and forgotten)."""
        if stage not in self.saved:
            return None
        try:
            return self._read(stage)
        except _READ_ERRORS as exc:
            self.problems.append(f"checkpoint of {stage} not usable ({exc}); computed again")
            self.saved = self.saved[: self.saved.index(stage)]
            return None

    def load_parts(self, stage: str) -> Iterator[Any]:
        """The parts saved of ``stage``, in order (up to the first unreadable one), each
        read when the one before it has been taken: memory holds one part, not all."""
        for k in range(self.parts.get(stage, 0)):
            try:
                part = self._read(_part_name(stage, k))
            except _READ_ERRORS as exc:
                self.problems.append(f"checkpoint of {stage} part {k} not usable ({exc})")
                self.parts[stage] = k
                return
            yield part

    def save(self, stage: str, value: Any) -> None:
        """Save ``value`` as the result of ``stage`` (its parts are deleted then); a
        failure to write is noted in ``problems``, and the run goes on."""
        if self._write(stage, value, lambda: self.saved.append(stage)):
            old = self.parts.pop(stage, 0)
            try:
                self._write_marker()
                for k in range(old):
                    for ext in _EXTENSIONS:
                        (self.folder / f"{_part_name(stage, k)}.{ext}").unlink(missing_ok=True)
            except OSError:
                pass
            _notify(stage)

    def save_part(self, stage: str, value: Any) -> None:
        """Save ``value`` as the next part of ``stage`` (see :meth:`save`)."""
        k = self.parts.get(stage, 0)
        if self._write(_part_name(stage, k), value, lambda: self.parts.__setitem__(stage, k + 1)):
            _notify(_part_name(stage, k))

    def _read(self, name: str) -> Any:
        node = json.loads((self.folder / f"{name}.json").read_text(encoding="utf-8"))
        with np.load(self.folder / f"{name}.npz", allow_pickle=False) as npz:
            arrays = {k: npz[k] for k in npz.files}
        return decode(node, arrays, self.folder / f"{name}.rings")

    def _write(self, name: str, value: Any, record: Callable[[], None]) -> bool:
        """Write ``name``'s files, then ``record()`` it and rewrite the marker; False
        (noted in ``problems``) when the file system refused."""
        enc = _Encoder()
        node = enc(value)  # CheckpointFormatError: a type the codec does not know (a bug)
        try:
            if self.folder.is_symlink():  # not a folder omnipipe made
                raise OSError(f"{self.folder} is a symbolic link")
            self.folder.mkdir(parents=True, exist_ok=True)  # as OUT's parent at the end
            if _read_marker(self.folder) is None:
                self._write_marker()
            _write_atomic(self.folder / f"{name}.npz", lambda fh: _savez(fh, enc.arrays))
            if enc.store is not None:
                _write_atomic(self.folder / f"{name}.rings", enc.store.copy_to)
            text = json.dumps(node, allow_nan=True)
            _write_atomic(self.folder / f"{name}.json", lambda fh: fh.write(text.encode()))
            record()
            self._write_marker()
        except OSError as exc:
            self.problems.append(f"checkpoint of {name} not saved ({exc.strerror or exc})")
            return False
        return True

    def _write_marker(self) -> None:
        names = list(self.saved) + [_part_name(s, k) for s, n in self.parts.items() for k in range(n)]
        files = [MARKER] + [f"{s}.{ext}" for s in names for ext in _EXTENSIONS]
        data = {"tool": "omnipipe", "kind": "checkpoint", "format": FORMAT, "key": self.key,
                "stages": self.saved, "parts": self.parts, "files": files}
        text = json.dumps(data, indent=1)
        _write_atomic(self.folder / MARKER, lambda fh: fh.write(text.encode()))

    def remove(self) -> None:
        """Delete the checkpoint folder: the files its marker lists, then the folder if
        nothing else is in it (files omnipipe did not write are kept)."""
        remove_checkpoint_dir(self.folder)


_EXTENSIONS = ("json", "npz", "rings")
"""A saved stage's (or part's) files; ``rings`` only where its value holds a ring store."""

_READ_ERRORS = (OSError, ValueError, KeyError, TypeError, AttributeError, ImportError)


def _part_name(stage: str, k: int) -> str:
    return f"{stage}-part-{k:05d}"


def _notify(name: str) -> None:
    if _saved_hook is not None:
        _saved_hook(name)


def _read_marker(folder: Path) -> dict[str, Any] | None:
    if folder.is_symlink():
        return None
    try:
        data = json.loads((folder / MARKER).read_text(encoding="utf-8"))
    except (OSError, ValueError):
        return None
    if not isinstance(data, dict) or data.get("tool") != "omnipipe" or data.get("format") != FORMAT:
        return None
    return data


def remove_checkpoint_dir(folder: Path) -> None:
    """Delete what omnipipe wrote in a checkpoint folder (marker last), and the folder
    when it is empty then. A folder without omnipipe's marker is left alone."""
    data = _read_marker(folder)
    if data is None:
        return
    names = [f for f in data.get("files", []) if isinstance(f, str) and "/" not in f
             and f not in (MARKER, "", ".", "..")]
    for name in names:
        try:
            (folder / name).unlink()
        except FileNotFoundError:
            pass
    for entry in _iter_tmp(folder):
        entry.unlink(missing_ok=True)
    (folder / MARKER).unlink(missing_ok=True)
    try:
        folder.rmdir()
    except OSError:
        pass


def _iter_tmp(folder: Path) -> Iterator[Path]:
    """Our own half-written files (``.NAME.XXXXXXXX.tmp``) left by a kill mid-save."""
    try:
        names = os.listdir(folder)
    except OSError:
        return
    for name in names:
        stem = name[1:].rsplit(".", 2)
        if name.startswith(".") and name.endswith(".tmp") and len(stem) == 3 and (
            stem[0] == MARKER or stem[0].split("-part-")[0].rsplit(".", 1)[0] in STAGES
        ):
            yield folder / name
