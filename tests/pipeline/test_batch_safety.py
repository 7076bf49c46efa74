"""omnipipe batch keeps what it had (issue 27): a run's earlier folder is replaced only by
a successful new one, no success leaves OUT untouched, and a SIGKILL, Ctrl-C or SIGTERM
leaves the earlier batch, no worker process and (after the next start-up) no debris.

Two tiny simulated runs (6 frames, 320x240); the file lists (with contents) of OUT are
compared before and after.
"""

from __future__ import annotations

import json
import os
import shutil
import signal
import subprocess
import sys
import textwrap
import time
from collections.abc import Callable
from pathlib import Path

import pytest

from omnipipe.cli import main
from omnipipe.output import prepare_output_dir

Snapshot = Callable[[Path], dict[str, bytes | None]]  # the ``snapshot`` fixture (conftest)


@pytest.fixture(scope="module")
def runs(two_tiny_runs: list[Path]) -> list[Path]:
    """The two tiny runs (read only here: the tests work on :func:`_copies`)."""
    return two_tiny_runs


@pytest.fixture(scope="module")
def good_batch(runs: list[Path], tmp_path_factory: pytest.TempPathFactory) -> Path:
    """A batch output in which both runs succeeded (kept pristine: tests copy it)."""
    out = tmp_path_factory.mktemp("good") / "batch"
    assert main(["batch", *map(str, runs), "--out", str(out), "--workers", "2", "--quiet"]) == 0
    return out


def _copies(runs: list[Path], good: Path, work: Path) -> tuple[list[Path], Path]:
    """Writable copies of the runs and of the good batch in ``work``."""
    copies = []
    for r in runs:
        shutil.copytree(r, work / r.name)
        copies.append(work / r.name)
    shutil.copytree(good, work / "batch")
    return copies, work / "batch"


def _break(run: Path) -> None:
    (run / "rig.yaml").rename(run / "rig.yaml.bak")


def _rows(out: Path) -> list[dict]:
    return json.loads((out / "index.json").read_text())["runs"]


def test_no_success_leaves_the_earlier_batch_untouched(
    snapshot: Snapshot,
    runs: list[Path], good_batch: Path, tmp_path: Path, capsys
) -> None:
    """The issue's reproducer: both runs unreadable, batch --force: nothing replaced."""
    (a, b), out = _copies(runs, good_batch, tmp_path)
    before = snapshot(tmp_path / "batch")
    _break(a)
    _break(b)
    capsys.readouterr()
    assert main(["batch", str(a), str(b), "--out", str(out), "--force", "--quiet"]) == 1
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "2 of 2 runs failed; nothing replaced" in err[0], err
    assert snapshot(tmp_path / "batch") == before  # every file, byte for byte
    assert sorted(p.name for p in tmp_path.iterdir()) == ["batch", a.name, b.name]


def test_a_failed_run_keeps_its_earlier_folder_marked_stale(
    snapshot: Snapshot,
    runs: list[Path], good_batch: Path, tmp_path: Path, capsys
) -> None:
    (a, b), out = _copies(runs, good_batch, tmp_path)
    earlier_a = snapshot(out / a.name)
    earlier_rows = {r["name"]: r for r in _rows(out)}
    _break(a)
    capsys.readouterr()
    assert main(["batch", str(a), str(b), "--out", str(out), "--force"]) == 1
    captured = capsys.readouterr()
    assert f"STALE   {a.name}: failed (" in captured.out and "kept its earlier output" in captured.out
    assert captured.err.strip().endswith(f"1 of 2 runs failed: {a.name}")
    # a's folder is the earlier one, every file identical; b's is the new one.
    assert snapshot(out / a.name) == earlier_a
    rows = {r["name"]: r for r in _rows(out)}
    assert rows[a.name]["status"] == "stale" and "rig.yaml" in rows[a.name]["error"]
    assert rows[a.name]["written_utc"] == earlier_rows[a.name]["written_utc"]
    assert rows[a.name]["inner_diameter_mm"] == earlier_rows[a.name]["inner_diameter_mm"]
    assert rows[b.name]["status"] == "ok" and rows[b.name]["error"] is None
    assert rows[b.name]["written_utc"] >= earlier_rows[b.name]["written_utc"]
    page = (out / "index.html").read_text()
    assert 'class="stale"' in page and "STALE: the output of" in page
    assert f'href="{a.name}/report.html"' in page  # the kept report is still linked
    # Still one omnipipe output: a later --force may replace it, and a now-good run
    # replaces its stale folder.
    assert sorted(p.name for p in tmp_path.iterdir()) == ["batch", a.name, b.name]
    (a / "rig.yaml.bak").rename(a / "rig.yaml")
    _break(b)
    assert main(["batch", str(a), str(b), "--out", str(out), "--force", "--quiet"]) == 1
    rows = {r["name"]: r for r in _rows(out)}
    assert rows[a.name]["status"] == "ok" and rows[b.name]["status"] == "stale"


def test_a_run_never_good_before_is_listed_failed_without_a_folder(
    runs: list[Path], good_batch: Path, tmp_path: Path, capsys
) -> None:
    (a, b), out = _copies(runs, good_batch, tmp_path)
    new = tmp_path / "new-run"
    shutil.copytree(a, new)
    _break(new)
    assert main(["batch", str(new), str(b), "--out", str(out), "--force", "--quiet"]) == 1
    rows = {r["name"]: r for r in _rows(out)}
    assert rows["new-run"]["status"] == "failed" and not (out / "new-run").exists()
    assert rows[b.name]["status"] == "ok"
    assert not (out / a.name).exists()  # not asked for: --force replaced the batch


# --- kills and signals ------------------------------------------------------------------

SCRIPT = textwrap.dedent(
    """
    import signal, sys, time
    from omnipipe.cli import main
    from omnipipe.pipeline import batch

    # As from a terminal (a background job inherits SIGINT ignored).
    signal.signal(signal.SIGINT, signal.default_int_handler)
    if sys.argv[1] == "slow":
        real = batch.reconstruct_task

        def slow_task(task):  # the run of a long inspection: a minute
            print("task started", flush=True)
            time.sleep(60)
            return real(task)

        slow_task.__qualname__ = "slow_task"
        sys.modules["__main__"].slow_task = slow_task
        batch.reconstruct_task = slow_task
    sys.exit(main(sys.argv[2:]))
    """
)


def children(pid: int) -> list[int]:
    """Processes whose parent is ``pid`` and that are not zombies (Linux /proc)."""
    found = []
    for entry in Path("/proc").iterdir():
        if not entry.name.isdigit():
            continue
        try:
            stat = (entry / "stat").read_text()
        except OSError:
            continue
        fields = stat.rsplit(")", 1)[1].split()
        if int(fields[1]) == pid and fields[0] != "Z":
            found.append(int(entry.name))
    return found


def alive(pid: int) -> bool:
    try:
        stat = Path(f"/proc/{pid}/stat").read_text()
    except OSError:
        return False
    return stat.rsplit(")", 1)[1].split()[0] != "Z"


def start(tmp_path: Path, mode: str, argv: list[str]) -> subprocess.Popen:
    script = tmp_path / "batch_script.py"
    script.write_text(SCRIPT)
    return subprocess.Popen(
        [sys.executable, str(script), mode, *argv],
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
        start_new_session=True,  # its own process group, as a terminal's job
    )


def wait_for_workers(proc: subprocess.Popen, n: int, timeout: float = 120.0) -> list[int]:
    end = time.monotonic() + timeout
    while time.monotonic() < end:
        kids = children(proc.pid)
        if len(kids) >= n:
            return kids
        assert proc.poll() is None, proc.communicate()
        time.sleep(0.05)
    raise AssertionError(f"no {n} workers after {timeout} s")


needs_proc = pytest.mark.skipif(not Path("/proc/self/stat").exists(), reason="needs Linux /proc")


@needs_proc
def test_sigkill_of_batch_kills_its_workers_and_keeps_the_earlier_batch(
    snapshot: Snapshot,
    runs: list[Path], good_batch: Path, tmp_path: Path
) -> None:
    """SIGKILL while both runs are being reconstructed (real runs, 2 workers): within a
    few seconds no worker survives; OUT is the earlier batch; the next start-up removes
    the temporary folder."""
    (a, b), out = _copies(runs, good_batch, tmp_path)
    before = snapshot(out)
    argv = ["batch", str(a), str(b), "--out", str(out), "--force", "--workers", "2", "--quiet"]
    proc = start(tmp_path, "real", argv)
    workers = wait_for_workers(proc, 2)
    os.kill(proc.pid, signal.SIGKILL)
    proc.wait(timeout=30)
    deadline = time.monotonic() + 5.0  # PR_SET_PDEATHSIG: at once; the watch: 0.5 s
    while any(alive(w) for w in workers) and time.monotonic() < deadline:
        time.sleep(0.05)
    assert not [w for w in workers if alive(w)], "workers outlived the killed batch"
    assert snapshot(out) == before
    prepare_output_dir(out, force=True)  # the next run's start-up
    assert sorted(p.name for p in tmp_path.iterdir() if p.name.startswith(".batch")) == []


@needs_proc
@pytest.mark.parametrize(("sig", "code", "word"), [(signal.SIGINT, 130, "interrupted"),
                                                  (signal.SIGTERM, 143, "terminated")])
def test_ctrl_c_and_sigterm_stop_a_batch_promptly(
    snapshot: Snapshot,
    runs: list[Path], good_batch: Path, tmp_path: Path, sig: int, code: int, word: str
) -> None:
    """Runs that would take a minute each: Ctrl-C (SIGINT to the process group, as a
    terminal sends it) or SIGTERM (to the batch, as `timeout` does) ends the batch and
    its workers within seconds, one line, the earlier batch intact, no debris."""
    (a, b), out = _copies(runs, good_batch, tmp_path)
    before = snapshot(out)
    argv = ["batch", str(a), str(b), "--out", str(out), "--force", "--workers", "2", "--quiet"]
    proc = start(tmp_path, "slow", argv)
    workers = wait_for_workers(proc, 2)
    assert proc.stdout is not None
    assert "task started" in proc.stdout.readline()  # a run is in progress (two workers may print on one line)
    sent = time.monotonic()
    if sig == signal.SIGINT:
        os.killpg(proc.pid, sig)
    else:
        os.kill(proc.pid, sig)
    _, err = proc.communicate(timeout=30)
    took = time.monotonic() - sent
    assert proc.returncode == code, err
    assert err.strip() == f"omnipipe batch: {word}", err
    assert took < 15.0, f"{took:.1f} s: the batch waited for its runs (60 s each)"
    assert not [w for w in workers if alive(w)]
    assert snapshot(out) == before
    assert sorted(p.name for p in tmp_path.iterdir() if p.name.startswith(".batch")) == []


def test_the_batch_pool_has_no_more_workers_than_runs(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """--workers 4 x cores for 2 runs starts 2 processes."""
    from concurrent.futures import ProcessPoolExecutor

    from omnipipe.executor import max_workers
    from omnipipe.pipeline import batch

    sizes: list[int] = []
    real = batch._write_runs

    def spy(executor, *args):
        if isinstance(executor, ProcessPoolExecutor):
            sizes.append(executor._max_workers)
        yield from real(executor, *args)

    monkeypatch.setattr(batch, "_write_runs", spy)
    broken = tmp_path / "broken"
    broken.mkdir()  # fails at once: the pool, not the runs, is what is counted here
    argv = ["batch", str(broken), str(broken), "--out", str(tmp_path / "o"), "--quiet"]
    assert main([*argv, "--workers", str(max_workers())]) == 1
    assert sizes == [2]
