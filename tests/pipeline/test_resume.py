"""A rerun of ``omnipipe reconstruct`` resumes after the last completed stage and writes
what an uninterrupted run writes, byte for byte (timings aside); checkpoints never
weaken the output's safety."""

from __future__ import annotations

import json
import os
import re
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest

from omnipipe.cli import main
from omnipipe.executor import FrameSource
from omnipipe.output import MANIFEST_NAME
from omnipipe.pipeline import checkpoint


class _Killed(BaseException):
    """Stands for a kill right after a checkpoint was saved."""


@pytest.fixture(scope="module")
def tiny_run(two_tiny_runs: list[Path]) -> Path:
    """paper-small at 320x240, 6 frames (the smallest that reconstructs; read only)."""
    return two_tiny_runs[0]


def _reconstruct(ds: Path, out: Path, *extra: str) -> int:
    return main(["reconstruct", str(ds), "--out", str(out), "--workers", "1", "--quiet", *extra])


@pytest.fixture(scope="module")
def uninterrupted(tiny_run: Path, tmp_path_factory: pytest.TempPathFactory) -> Path:
    out = tmp_path_factory.mktemp("whole") / "out"
    assert _reconstruct(tiny_run, out) == 0
    return out


def _contents(out: Path) -> dict[str, bytes]:
    """Every file of ``out``, timings (report.json's, report.html's row) and the
    manifest's time of writing taken out."""
    files: dict[str, bytes] = {}
    for path in sorted(p for p in out.rglob("*") if p.is_file()):
        rel = path.relative_to(out).as_posix()
        data = path.read_bytes()
        if rel == "report.json":
            summary = json.loads(data)
            del summary["timings_s"], summary["frames_per_s"]
            data = json.dumps(summary).encode()
        elif rel == "report.html":
            data = re.sub(rb"<td>processing time</td><td>[^<]*</td>", b"", data)
        elif rel == MANIFEST_NAME:
            manifest = json.loads(data)
            del manifest["written_utc"], manifest["command"]  # when, and by which process
            data = json.dumps(manifest).encode()
        files[rel] = data
    return files


def _checkpoint_dirs(out: Path) -> list[Path]:
    return sorted(out.parent.glob(f".{out.name}.resume-*"))


@pytest.mark.parametrize("stage", checkpoint.STAGES)
def test_resume_after_a_kill_at_each_stage_gives_the_same_output(
    stage: str,
    tiny_run: Path,
    uninterrupted: Path,
    tmp_path: Path,
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    out = tmp_path / "runs" / "out"  # its folder made by the run (the checkpoints' first)
    saved: list[str] = []

    def kill(name: str) -> None:
        saved.append(name)
        if name == stage:
            raise _Killed()

    monkeypatch.setattr(checkpoint, "_saved_hook", kill)
    with pytest.raises(_Killed):
        _reconstruct(tiny_run, out)
    assert not out.exists()  # an interrupted run writes no OUT
    (folder,) = _checkpoint_dirs(out)
    marker = json.loads((folder / checkpoint.MARKER).read_text())
    assert marker["stages"] == saved and saved[-1] == stage

    computed: list[str] = []
    monkeypatch.setattr(checkpoint, "_saved_hook", computed.append)
    assert _reconstruct(tiny_run, out) == 0
    # Only the stages after the kill ran again.
    assert computed == list(checkpoint.STAGES[checkpoint.STAGES.index(stage) + 1 :])
    assert _contents(out) == _contents(uninterrupted)
    assert _checkpoint_dirs(out) == []  # removed once OUT is in place


def test_resume_inside_the_frame_pass_decodes_only_the_frames_after_its_last_part(
    tiny_run: Path, uninterrupted: Path, tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    from omnipipe.pipeline import frame_pass

    monkeypatch.setattr(frame_pass, "PART_FRAMES", 2)
    out = tmp_path / "out"

    def kill(name: str) -> None:
        if name == "frames-part-00001":  # frames 0-3 saved in two parts
            raise _Killed()

    monkeypatch.setattr(checkpoint, "_saved_hook", kill)
    with pytest.raises(_Killed):
        _reconstruct(tiny_run, out)
    decoded: list[int] = []
    task_call = frame_pass._FrameTask.__call__

    def spy(self: frame_pass._FrameTask, source: FrameSource) -> list:
        decoded.extend(source.frames)
        return task_call(self, source)

    monkeypatch.setattr(frame_pass._FrameTask, "__call__", spy)
    computed: list[str] = []
    monkeypatch.setattr(checkpoint, "_saved_hook", computed.append)
    assert _reconstruct(tiny_run, out) == 0
    assert decoded == [4, 5]
    assert computed == list(checkpoint.STAGES)
    assert _contents(out) == _contents(uninterrupted)


def test_checkpoint_round_trip_is_exact(tiny_run: Path, tmp_path: Path) -> None:
    """Arrays keep dtype, shape and bits; NaN, numpy scalars, tuples, nested dataclasses
    and lists of one dataclass (stored by column) come back as they were."""
    from omnipipe.laser.extract import LaserRing

    rng = np.random.default_rng(0)
    rings = [
        LaserRing(rng.normal(size=(k, 2)), rng.normal(size=k), rng.normal(size=k),
                  rng.normal(size=k), scanned=k, warnings=["w"] * (k % 2))
        for k in (0, 3, 5)
    ]
    value = {"rings": rings, "t": (np.float32(1.5), float("nan"), None), "n": np.int64(7)}
    cp = checkpoint.Checkpoints.open(tmp_path / "out", "ab" * 32)
    cp.save("frames", value)
    back = checkpoint.Checkpoints.open(tmp_path / "out", "ab" * 32).load("frames")
    assert type(back["n"]) is np.int64 and back["n"] == 7
    assert type(back["t"][0]) is np.float32 and np.isnan(back["t"][1]) and back["t"][2] is None
    for a, b in zip(rings, back["rings"], strict=True):
        assert type(b) is LaserRing and b.scanned == a.scanned and b.warnings == a.warnings
        for name in ("pixels", "angle_rad", "confidence", "points_in_rig", "sigma_mm"):
            x, y = getattr(a, name), getattr(b, name)
            assert x.dtype == y.dtype and x.shape == y.shape and x.tobytes() == y.tobytes()


def test_a_changed_setting_or_input_never_reuses_a_checkpoint(
    tiny_run: Path, tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    import shutil

    ds = tmp_path / "ds"
    shutil.copytree(tiny_run, ds)
    out = tmp_path / "out"

    def kill(name: str) -> None:
        if name == "sfm":
            raise _Killed()

    monkeypatch.setattr(checkpoint, "_saved_hook", kill)
    with pytest.raises(_Killed):
        _reconstruct(ds, out)
    assert len(_checkpoint_dirs(out)) == 1
    computed: list[str] = []
    monkeypatch.setattr(checkpoint, "_saved_hook", computed.append)
    # Another setting: every stage computed again (and the old checkpoint removed at the end).
    assert _reconstruct(ds, out, "--features", "400") == 0
    assert computed == list(checkpoint.STAGES)
    assert _checkpoint_dirs(out) == []

    monkeypatch.setattr(checkpoint, "_saved_hook", kill)
    with pytest.raises(_Killed):
        _reconstruct(ds, out, "--force")
    frame = ds / "frames" / sorted(os.listdir(ds / "frames"))[2]
    os.utime(frame, ns=(frame.stat().st_atime_ns, frame.stat().st_mtime_ns + 10**9))  # touched
    computed.clear()
    monkeypatch.setattr(checkpoint, "_saved_hook", computed.append)
    assert _reconstruct(ds, out, "--force") == 0
    assert computed == list(checkpoint.STAGES)


def test_fresh_computes_again_and_keeps_files_omnipipe_did_not_write(
    tiny_run: Path, tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    out = tmp_path / "out"

    def kill(name: str) -> None:
        raise _Killed()

    monkeypatch.setattr(checkpoint, "_saved_hook", kill)
    with pytest.raises(_Killed):
        _reconstruct(tiny_run, out)
    (folder,) = _checkpoint_dirs(out)
    (folder / "notes.txt").write_text("mine")
    computed: list[str] = []
    monkeypatch.setattr(checkpoint, "_saved_hook", computed.append)
    assert _reconstruct(tiny_run, out, "--fresh") == 0
    assert computed == list(checkpoint.STAGES)  # the saved frame pass not used
    assert sorted(os.listdir(folder)) == ["notes.txt"]


@pytest.mark.slow  # 4 s: a real SIGTERM to a subprocess; resuming stays covered by the in-process kills above
def test_sigterm_then_rerun_resumes(tiny_run: Path, uninterrupted: Path, tmp_path: Path) -> None:
    """A real SIGTERM to ``omnipipe reconstruct`` once its camera motion is saved: OUT
    is not written, the rerun computes only the later stages, the output is the same."""
    out = tmp_path / "out"
    env = dict(os.environ, PYTHONPATH=str(Path(checkpoint.__file__).parents[2]))
    cmd = [sys.executable, "-m", "omnipipe.cli", "reconstruct", str(tiny_run), "--out",
           str(out), "--workers", "1", "--quiet"]
    proc = subprocess.Popen(cmd, env=env, stderr=subprocess.PIPE, text=True)
    deadline = time.monotonic() + 120
    while time.monotonic() < deadline and proc.poll() is None:
        markers = list(out.parent.glob(f".{out.name}.resume-*/{checkpoint.MARKER}"))
        if markers and "sfm" in json.loads(markers[0].read_text() or "{}").get("stages", []):
            proc.send_signal(signal.SIGTERM)
            break
        time.sleep(0.05)
    _, err = proc.communicate(timeout=60)
    if proc.returncode == 0:
        pytest.skip("the run ended before the signal could be sent")
    assert proc.returncode == 143, err
    assert not out.exists()
    rerun = subprocess.run(cmd, env=env, capture_output=True, text=True, timeout=300)
    assert rerun.returncode == 0, rerun.stderr
    assert "resuming: frames, sfm" in rerun.stderr
    assert _contents(out) == _contents(uninterrupted)


def test_a_ring_store_is_saved_and_loaded_without_reading_its_rings(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """The frame pass's rings (a RingStore on disk) go into the checkpoint as a copy of
    the store's file: neither the save nor the load reads every ring into memory."""
    from omnipipe.laser.extract import LaserRing
    from omnipipe.laser.store import RingStore

    rng = np.random.default_rng(1)
    rings = [
        LaserRing(rng.normal(size=(k, 2)), rng.normal(size=k), rng.normal(size=k),
                  rng.normal(size=k), scanned=k + 1, warnings=["w"] * (k % 2))
        for k in (4, 0, 7, 0, 3)
    ]
    store = RingStore(len(rings))
    for i, ring in enumerate(rings):
        store.put(i, ring)
    read: list[int] = []
    getitem = RingStore.__getitem__

    def spy(self: RingStore, index: int) -> LaserRing:
        read.append(index)
        return getitem(self, index)

    monkeypatch.setattr(RingStore, "__getitem__", spy)
    cp = checkpoint.Checkpoints.open(tmp_path / "out", "cd" * 32)
    cp.save("frames", {"rings": store, "n": 5})
    back = checkpoint.Checkpoints.open(tmp_path / "out", "cd" * 32).load("frames")
    assert read == [] and isinstance(back["rings"], RingStore)
    monkeypatch.setattr(RingStore, "__getitem__", getitem)
    for a, b in zip(back["rings"], rings, strict=True):
        assert a.scanned == b.scanned and a.warnings == b.warnings
        assert np.array_equal(a.pixels, b.pixels) and a.pixels.dtype == b.pixels.dtype
    folder = checkpoint.checkpoint_dir(tmp_path / "out", "cd" * 32)
    assert (folder / "frames.rings").is_file()
    cp.remove()
    assert not folder.exists()  # the copy is among the files the marker lists
