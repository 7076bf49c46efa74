"""Output safety: omnipipe never deletes what it did not write, and a kill at any step
of the write phase leaves the previous or the new complete output (issue 15).

Fast: a fake dataset folder (the refusals happen before the dataset is read) and the
output functions driven directly; the kill tests run the swap in a subprocess that is
SIGKILLed at a named step.
"""

from __future__ import annotations

import json
import signal
import subprocess
import sys
import textwrap
import time
from collections.abc import Callable
from pathlib import Path

import pytest

from omnipipe.cli import main
from omnipipe.errors import OutputError
from omnipipe.output import (
    MANIFEST_NAME,
    atomic_output_dir,
    check_output_dir,
    prepare_output_dir,
    read_manifest,
)

Snapshot = Callable[[Path], dict[str, bytes | None]]  # the ``snapshot`` fixture (conftest)


def fake_dataset(root: Path) -> Path:
    """A folder that looks like a dataset; never read (refusals come first)."""
    root.mkdir(parents=True)
    (root / "rig.yaml").write_text("camera: {}\n")
    (root / "frames").mkdir()
    (root / "frames" / "000000.png").write_bytes(b"\x89PNG not really")
    (root / "ground_truth").mkdir()
    (root / "ground_truth" / "poses.txt").write_text("0 0 0 0 0 0 0 1\n")
    return root


def write_own(out: Path, version: str, *, force: bool = True) -> None:
    """An omnipipe output (with manifest) whose every file says ``version``."""
    with atomic_output_dir(out, force=force, command=f"test {version}") as tmp:
        for i in range(4):
            (tmp / f"f{i}.txt").write_text(version)
        (tmp / "sub").mkdir()
        (tmp / "sub" / "g.txt").write_text(version)


def versions(out: Path) -> set[str]:
    return {
        p.read_text() for p in out.rglob("*") if p.is_file() and p.name != MANIFEST_NAME
    }


def refused(capsys, argv: list[str], expected: str) -> None:
    assert main(argv) == 1
    err = capsys.readouterr().err.strip()
    assert expected in err, err
    assert len(err.splitlines()) == 1, err


# --- refusals through the CLI: file lists before and after ---------------------------


def test_out_equal_to_dataset_is_refused(snapshot: Snapshot, tmp_path: Path, capsys) -> None:
    ds = fake_dataset(tmp_path / "D")
    before = snapshot(tmp_path)
    refused(capsys, ["reconstruct", str(ds), "--out", str(ds), "--force", "--quiet"], "is the input")
    assert snapshot(tmp_path) == before
    # Inside the dataset only a fresh folder (or omnipipe's own output) may be written.
    argv = ["reconstruct", str(ds), "--out", str(ds / "frames"), "--force", "--quiet"]
    refused(capsys, argv, "was not written by omnipipe")
    assert snapshot(tmp_path) == before


def test_out_dot_from_the_folder_holding_the_dataset_is_refused(
    snapshot: Snapshot,
    tmp_path: Path, capsys, monkeypatch: pytest.MonkeyPatch
) -> None:
    fake_dataset(tmp_path / "D")
    (tmp_path / "notes.txt").write_text("mine")
    (tmp_path / "other").mkdir()
    (tmp_path / "other" / "x.csv").write_text("1,2")
    before = snapshot(tmp_path)
    monkeypatch.chdir(tmp_path)
    refused(capsys, ["reconstruct", "D", "--out", ".", "--force", "--quiet"], "current folder")
    assert snapshot(tmp_path) == before


def test_out_parent_of_the_dataset_is_refused(snapshot: Snapshot, tmp_path: Path, capsys) -> None:
    ds = fake_dataset(tmp_path / "work" / "D")
    (tmp_path / "work" / "notes.txt").write_text("mine")
    before = snapshot(tmp_path)
    argv = ["reconstruct", str(ds), "--out", f"{ds}/..", "--force", "--quiet"]
    refused(capsys, argv, "holds the input")
    assert snapshot(tmp_path) == before


def test_out_symlink_to_the_dataset_is_refused(snapshot: Snapshot, tmp_path: Path, capsys) -> None:
    ds = fake_dataset(tmp_path / "D")
    (tmp_path / "link").symlink_to(ds, target_is_directory=True)
    before = snapshot(tmp_path)
    argv = ["reconstruct", str(ds), "--out", str(tmp_path / "link"), "--force", "--quiet"]
    refused(capsys, argv, "is the input")
    assert snapshot(tmp_path) == before


def test_out_holding_the_config_file_is_refused(snapshot: Snapshot, tmp_path: Path, capsys) -> None:
    ds = fake_dataset(tmp_path / "D")
    (tmp_path / "cfg").mkdir()
    (tmp_path / "cfg" / "c.yaml").write_text("sfm: {}\n")
    before = snapshot(tmp_path)
    argv = ["reconstruct", str(ds), "--out", str(tmp_path / "cfg"), "--force", "--quiet",
            "--config", str(tmp_path / "cfg" / "c.yaml")]
    refused(capsys, argv, "holds the input")
    assert snapshot(tmp_path) == before


def test_force_onto_a_user_folder_is_refused(snapshot: Snapshot, tmp_path: Path, capsys) -> None:
    ds = fake_dataset(tmp_path / "D")
    user = tmp_path / "results"
    user.mkdir()
    (user / "thesis.tex").write_text("years of work")
    before = snapshot(tmp_path)
    argv = ["reconstruct", str(ds), "--out", str(user), "--force", "--quiet"]
    refused(capsys, argv, "was not written by omnipipe")
    assert snapshot(tmp_path) == before
    # Without --force it is not suggested: the folder is not omnipipe's.
    refused(capsys, [*argv[:-2], "--quiet"], "choose another output folder")
    assert snapshot(tmp_path) == before


def test_force_onto_own_output_with_an_added_user_file_is_refused(snapshot: Snapshot, tmp_path: Path, capsys) -> None:
    ds = fake_dataset(tmp_path / "D")
    out = tmp_path / "out"
    write_own(out, "v1")
    (out / "sub" / "my notes.txt").write_text("mine")
    before = snapshot(tmp_path)
    argv = ["reconstruct", str(ds), "--out", str(out), "--force", "--quiet"]
    refused(capsys, argv, "holds 'sub/my notes.txt', which omnipipe did not write")
    assert snapshot(tmp_path) == before
    with pytest.raises(OutputError, match=r"sub/my notes\.txt"):
        write_own(out, "v2")
    assert snapshot(tmp_path) == before


def test_simulate_force_replaces_only_its_own_output(snapshot: Snapshot, tmp_path: Path, capsys) -> None:
    user = tmp_path / "data"
    user.mkdir()
    (user / "frames").mkdir()
    (user / "frames" / "recorded.png").write_bytes(b"real data")
    before = snapshot(tmp_path)
    argv = ["simulate", "--scenario", "paper-small", "--frames", "2", "--out", str(user),
            "--force", "--quiet", "--workers", "1"]
    refused(capsys, argv, "was not written by omnipipe")
    assert snapshot(tmp_path) == before


@pytest.mark.parametrize("which", ["home", "root"])
def test_home_and_root_are_refused(tmp_path: Path, monkeypatch: pytest.MonkeyPatch, which) -> None:
    home = tmp_path / "home"
    home.mkdir()
    monkeypatch.setenv("HOME", str(home))
    target = home if which == "home" else Path("/")
    with pytest.raises(OutputError, match=which if which == "home" else "filesystem root"):
        check_output_dir(target, force=True)


# --- the manifest and --force ---------------------------------------------------------


def test_force_replaces_own_output_and_the_manifest_lists_everything(tmp_path: Path) -> None:
    out = tmp_path / "out"
    write_own(out, "v1")
    manifest = read_manifest(out)
    assert manifest is not None and manifest.command == "test v1"
    assert manifest.files == {"f0.txt", "f1.txt", "f2.txt", "f3.txt", "sub/g.txt"}
    assert manifest.dirs == {"sub"}
    with pytest.raises(OutputError, match="already exists"):
        write_own(out, "v2", force=False)
    write_own(out, "v2")
    assert versions(out) == {"v2"}
    assert sorted(p.name for p in tmp_path.iterdir()) == ["out"]  # no debris


def test_force_onto_an_empty_folder_is_allowed(tmp_path: Path) -> None:
    out = tmp_path / "out"
    out.mkdir()
    write_own(out, "v1")
    assert versions(out) == {"v1"}


@pytest.mark.parametrize(
    "manifest",
    [
        "not json",
        json.dumps({"tool": "other", "files": ["f0.txt"]}),
        json.dumps({"tool": "omnipipe", "files": ["../outside.txt"]}),
        json.dumps({"tool": "omnipipe", "files": "f0.txt"}),
    ],
)
def test_damaged_or_forged_manifest_is_refused(snapshot: Snapshot, tmp_path: Path, manifest: str) -> None:
    out = tmp_path / "out"
    out.mkdir()
    (out / "f0.txt").write_text("user")
    (out / MANIFEST_NAME).write_text(manifest)
    before = snapshot(tmp_path)
    with pytest.raises(OutputError, match="refusing to replace it"):
        check_output_dir(out, force=True)
    with pytest.raises(OutputError):
        write_own(out, "v2")
    assert snapshot(tmp_path) == before


def test_a_symlink_inside_own_output_is_foreign(tmp_path: Path) -> None:
    out = tmp_path / "out"
    write_own(out, "v1")
    keep = tmp_path / "keep"
    keep.mkdir()
    (keep / "k.txt").write_text("keep")
    (out / "sub" / "link").symlink_to(keep, target_is_directory=True)
    with pytest.raises(OutputError, match="sub/link"):
        write_own(out, "v2")
    assert (keep / "k.txt").read_text() == "keep"


def test_failure_inside_the_block_keeps_previous_output_and_leaves_no_partial(
    tmp_path: Path,
) -> None:
    out = tmp_path / "out"
    write_own(out, "v1")
    with pytest.raises(RuntimeError), atomic_output_dir(out, force=True) as tmp:
        (tmp / "f0.txt").write_text("v2")
        raise RuntimeError("stage failed")
    assert versions(out) == {"v1"}
    assert sorted(p.name for p in tmp_path.iterdir()) == ["out"]


# --- kills at each step of the write phase -------------------------------------------

KILL_SCRIPT = textwrap.dedent(
    """
    import os, signal, sys
    from omnipipe import output

    out, version, kill_at, mode = sys.argv[1:5]

    def hook(step):
        if step == kill_at:
            os.kill(os.getpid(), signal.SIGKILL)

    output._step_hook = hook
    if mode == "renames":  # a system or file system without renameat2's exchange
        output._exchange = lambda a, b: False
    with output.atomic_output_dir(out, force=True) as tmp:
        for i in range(4):
            (tmp / f"f{i}.txt").write_text(version)
        (tmp / "sub").mkdir()
        (tmp / "sub" / "g.txt").write_text(version)
    """
)

# step -> which output the next run must find (before "new-in": the previous one).
# "renames": the fallback without renameat2's exchange (old OUT aside, then new in).
STEPS = {
    "partial-created": "v1",
    "files-written": "v1",
    "manifest-written": "v1",
    "pid-removed": "v1",
    "old-aside": "v1",
    "new-in": "v2",
    "synced": "v2",
    "old-marked": "v2",
    "old-partly-deleted": "v2",
}
# With the exchange (Linux): the new output is in first, then the old one renamed aside.
EXCHANGE_STEPS = {**STEPS, "old-aside": "v2"}


def run_killed(tmp_path: Path, out: Path, version: str, step: str, mode: str = "exchange") -> None:
    script = tmp_path / "kill.py"
    script.write_text(KILL_SCRIPT)
    proc = subprocess.run(
        [sys.executable, str(script), str(out), version, step, mode],
        capture_output=True,
        text=True,
        timeout=60,
    )
    assert proc.returncode == -signal.SIGKILL, proc.stderr


@pytest.mark.parametrize("mode", ["exchange", "renames"])
@pytest.mark.parametrize("step", list(STEPS))
def test_kill_at_any_step_keeps_a_complete_output(tmp_path: Path, step: str, mode: str) -> None:
    from omnipipe.output import _renameat2

    if mode == "exchange" and _renameat2() is None:
        pytest.skip("no renameat2 on this system: the renames are the only swap")
    work = tmp_path / "work"
    work.mkdir()
    out = work / "out"
    write_own(out, "v1")
    run_killed(tmp_path, out, "v2", step, mode)
    # Right after the kill OUT is complete; only the two renames' swap leaves it missing
    # (between them).
    if mode == "exchange":
        assert out.is_dir(), sorted(p.name for p in work.iterdir())
    if out.exists():
        assert versions(out) in ({"v1"}, {"v2"})
        assert len(versions(out)) == 1 and len(list(out.rglob("*.txt"))) == 5
    # The next run's start-up finishes or rolls back the swap and removes the debris.
    prepare_output_dir(out, force=True)
    assert versions(out) == {(EXCHANGE_STEPS if mode == "exchange" else STEPS)[step]}
    assert len(list(out.rglob("*.txt"))) == 5
    assert read_manifest(out) is not None
    assert sorted(p.name for p in work.iterdir()) == ["out"]
    write_own(out, "v3")
    assert versions(out) == {"v3"}
    assert sorted(p.name for p in work.iterdir()) == ["out"]


def test_kill_during_a_first_write_leaves_nothing_after_the_next_run(tmp_path: Path) -> None:
    work = tmp_path / "work"
    work.mkdir()
    out = work / "out"
    run_killed(tmp_path, out, "v1", "files-written")
    assert [p.name.split("-")[0] for p in work.iterdir()] == [".out.partial"]
    prepare_output_dir(out)
    assert list(work.iterdir()) == []


def test_a_live_runs_partial_and_foreign_lookalikes_are_left_alone(tmp_path: Path) -> None:
    out = tmp_path / "out"
    foreign = tmp_path / ".out.partial-user"
    foreign.mkdir()
    (foreign / "data.txt").write_text("not omnipipe's")
    with atomic_output_dir(out) as tmp:
        prepare_output_dir(tmp_path / "out")  # a second run starting meanwhile
        assert tmp.is_dir()
        (tmp / "a.txt").write_text("v1")
    assert (foreign / "data.txt").read_text() == "not omnipipe's"
    assert sorted(p.name for p in tmp_path.iterdir()) == [".out.partial-user", "out"]


# --- SIGTERM / SIGINT through the real CLI --------------------------------------------

SIGNAL_SCRIPT = textwrap.dedent(
    """
    import signal, sys, time
    import omnipipe.sim.writer as writer
    from omnipipe.cli import main

    # As from a terminal: a shell's background job (e.g. CI started with &) inherits
    # SIGINT ignored, and Python would then never raise KeyboardInterrupt.
    signal.signal(signal.SIGINT, signal.default_int_handler)

    out, workers, render = sys.argv[1:4]
    original = writer._render_all

    def render_all(renderer, scenario, poses, tmp, names, workers, progress):
        def slow(done, total):
            if done == 1 or done == total:
                print("ready", flush=True)
                time.sleep(60)
        original(renderer, scenario, poses, tmp, names, workers, slow)

    def no_render(scenario):
        print("ready", flush=True)
        time.sleep(60)

    writer._render_all = render_all
    if render == "no":
        writer.build_renderer = no_render
    sys.exit(main(["simulate", "--scenario", "paper-small", "--frames", "3", "--quiet",
                   "--workers", workers, "--out", out]))
    """
)


@pytest.mark.parametrize(
    ("sig", "code", "word", "workers", "render"),
    [
        # SIGTERM while render worker processes run: they die quietly, one line.
        (signal.SIGTERM, 143, "terminated", "2", "yes"),
        (signal.SIGINT, 130, "interrupted", "1", "no"),
    ],
)
def test_signal_during_the_run_removes_the_temporary_folder(
    tmp_path: Path, sig: int, code: int, word: str, workers: str, render: str
) -> None:
    work = tmp_path / "work"
    work.mkdir()
    script = tmp_path / "sig.py"
    script.write_text(SIGNAL_SCRIPT)
    proc = subprocess.Popen(
        [sys.executable, str(script), str(work / "ds"), workers, render],
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
    )
    try:
        assert proc.stdout.readline().strip() == "ready"
        assert [p.name.split("-")[0] for p in work.iterdir()] == [".ds.partial"]
        proc.send_signal(sig)
        _, err = proc.communicate(timeout=60)
    finally:
        if proc.poll() is None:
            proc.kill()
    assert proc.returncode == code, err
    assert err.strip() == f"omnipipe simulate: {word}"
    assert list(work.iterdir()) == []


STUCK_WORKER_SCRIPT = textwrap.dedent(
    """
    import os, signal, sys, time
    import omnipipe.sim.writer as writer
    from omnipipe.cli import main

    parent = os.getpid()
    original = writer._render_station

    def stuck(args):
        # A render worker that SIGTERM cannot end (as one whose main thread is in a long
        # C call, or blocked on a lock another thread held at the fork).
        if os.getpid() != parent and args[4][0] != 0:
            signal.pthread_sigmask(signal.SIG_BLOCK, {signal.SIGTERM})
            time.sleep(120)
        return original(args)

    def ready(done, total):
        print("ready", flush=True)
        time.sleep(60)

    original_all = writer._render_all
    writer._render_station = stuck
    writer._render_all = lambda *a: original_all(*a[:-1], ready)
    sys.exit(main(["simulate", "--scenario", "paper-small", "--frames", "6", "--quiet",
                   "--workers", "2", "--out", sys.argv[1]]))
    """
)


def test_sigterm_ends_simulate_whose_render_worker_ignores_it(tmp_path: Path) -> None:
    # The flake: a multiprocessing.Pool's terminate() sent its workers SIGTERM and waited
    # for them without a timeout; the workers are now killed, as reconstruct's are.
    work = tmp_path / "work"
    work.mkdir()
    script = tmp_path / "stuck.py"
    script.write_text(STUCK_WORKER_SCRIPT)
    proc = subprocess.Popen(
        [sys.executable, str(script), str(work / "ds")],
        stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
    )
    try:
        assert proc.stdout.readline().strip() == "ready"
        time.sleep(0.5)  # the other worker is in its stuck station
        proc.send_signal(signal.SIGTERM)
        _, err = proc.communicate(timeout=30)  # a hang: TimeoutExpired
    finally:
        if proc.poll() is None:
            proc.kill()
    assert proc.returncode == 143, err
    assert err.strip() == "omnipipe simulate: terminated"
    assert list(work.iterdir()) == []
