"""Worker processes, command-line values and one-line errors (issue 27).

- a SIGKILLed ``reconstruct`` leaves no worker process behind (the issue's reproducer);
- ``--workers`` is 1 .. 4 x cores for every command and never more than the tasks;
- every bad ``--scheduler`` is one line within 5 s (no traceback, no Client.__del__);
- every number on the command line is refused while parsing, one line, exit 1;
- a ROS 2 bag with a broken metadata.yaml is one line, from reconstruct and batch;
- an OUT in a folder that cannot be written is refused before any work.
"""

from __future__ import annotations

import os
import signal
import socket
import subprocess
import sys
import time
from pathlib import Path

import pytest

from omnipipe.cli import main
from omnipipe.executor import max_workers, open_executor, parallelism


@pytest.fixture(scope="module")
def tiny(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """`omnipipe simulate --scenario paper-small --frames 24 --size 200x150`."""
    from omnipipe.sim import make_scenario, run

    out = tmp_path_factory.mktemp("tiny") / "ds"
    run(make_scenario("paper-small", frames=24, size=(200, 150), seed=1), out, workers=1)
    return out


def one_line_error(capsys: pytest.CaptureFixture[str], argv: list[str], *needles: str) -> str:
    capsys.readouterr()
    assert main(argv) == 1
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and err.startswith("omnipipe "), err
    assert "Traceback" not in err
    for needle in needles:
        assert needle in err, err
    return err


def _children(pid: int) -> list[int]:
    kids = []
    for entry in Path("/proc").iterdir():
        if entry.name.isdigit():
            try:
                fields = (entry / "stat").read_text().rsplit(")", 1)[1].split()
            except OSError:
                continue
            if int(fields[1]) == pid and fields[0] != "Z":
                kids.append(int(entry.name))
    return kids


def _alive(pid: int) -> bool:
    try:
        return Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()[0] != "Z"
    except OSError:
        return False


# --- 2: workers die with their parent ---------------------------------------------------


@pytest.mark.skipif(not Path("/proc/self/stat").exists(), reason="needs Linux /proc")
def test_sigkill_of_reconstruct_leaves_no_worker(tiny: Path, tmp_path: Path) -> None:
    """`omnipipe reconstruct ds --out o & kill -9 $!`: the pool's workers follow it."""
    proc = subprocess.Popen(
        [sys.executable, "-m", "omnipipe.cli", "reconstruct", str(tiny), "--out",
         str(tmp_path / "o"), "--workers", "2", "--quiet"],
        stdout=subprocess.DEVNULL,
        stderr=subprocess.PIPE,
    )
    deadline = time.monotonic() + 120
    while len(workers := _children(proc.pid)) < 2:
        assert proc.poll() is None and time.monotonic() < deadline, proc.communicate()
        time.sleep(0.02)
    os.kill(proc.pid, signal.SIGKILL)
    proc.wait(timeout=30)
    deadline = time.monotonic() + 5.0
    while any(_alive(w) for w in workers) and time.monotonic() < deadline:
        time.sleep(0.05)
    assert not [w for w in workers if _alive(w)], "workers outlived the killed run"
    assert not (tmp_path / "o").exists()


@pytest.mark.skipif(not hasattr(os, "fork"), reason="needs fork")
def test_the_parent_watch_alone_ends_an_orphaned_worker() -> None:
    """The fallback of PR_SET_PDEATHSIG (systems without prctl): a worker whose parent
    exits notices within about a second and kills itself."""
    script = (
        "import os, time\n"
        "from omnipipe import executor\n"
        "executor._die_with_parent = lambda: False  # the watch alone\n"
        "parent = os.getpid()\n"
        "pid = os.fork()\n"
        "if pid == 0:\n"
        "    executor.worker_init(parent)\n"
        "    time.sleep(30)\n"
        "    os._exit(0)\n"
        "print(pid, flush=True)\n"
        "time.sleep(0.5)\n"
        "os._exit(0)  # the parent dies; its worker is orphaned\n"
    )
    done = subprocess.run([sys.executable, "-c", script], capture_output=True, text=True,
                          timeout=60)
    child = int(done.stdout.split()[0])
    deadline = time.monotonic() + 5.0
    while _alive(child) and time.monotonic() < deadline:
        time.sleep(0.05)
    assert not _alive(child), "the orphaned worker is still running"


# --- 4: worker counts -------------------------------------------------------------------


def test_workers_are_capped_at_the_task_count() -> None:
    with open_executor(max_workers(), tasks=3) as pool:
        assert parallelism(pool) == 3
        assert sorted(pool.map(abs, [-1, -2, -3, -4, -5, -6])) == [1, 2, 3, 4, 5, 6]
        assert len(pool._processes) == 3  # processes started, not only a number
    with open_executor(max_workers(), tasks=1) as pool:
        assert parallelism(pool) == 1  # one task: inline, no pool at all


@pytest.mark.parametrize("command", ["reconstruct", "batch", "simulate"])
@pytest.mark.parametrize("value", ["0", "-1", "999", "two"])
def test_workers_out_of_bounds_are_refused_alike(
    tiny: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str], command: str, value: str
) -> None:
    """`--workers 999` (1000 processes for a 24-frame run before) and `simulate
    --workers 0` (all cores before) are refused like every other command's."""
    out = tmp_path / "out"
    argv = {
        "reconstruct": ["reconstruct", str(tiny), "--out", str(out)],
        "batch": ["batch", str(tiny), "--out", str(out)],
        "simulate": ["simulate", "--scenario", "paper-small", "--out", str(out)],
    }[command]
    one_line_error(capsys, [*argv, "--workers", value, "--quiet"], "--workers:",
                   f"{command}: error:")
    assert not out.exists()


@pytest.mark.parametrize(
    ("argv", "option"),
    [
        (["simulate", "--scenario", "paper-small", "--frames", "0"], "--frames"),
        (["simulate", "--scenario", "paper-small", "--frames", "99999999"], "--frames"),
        (["simulate", "--scenario", "paper-small", "--size", "99999x99999"], "--size"),
        (["simulate", "--scenario", "paper-small", "--size", "abc"], "--size"),
        (["simulate", "--scenario", "paper-small", "--seed", "-1"], "--seed"),
        (["demo", "--seed", "1.5"], "--seed"),
        (["reconstruct", "DS", "--features", "0"], "--features"),
        (["reconstruct", "DS", "--keyframe-parallax", "nan"], "--keyframe-parallax"),
        (["batch", "DS", "--keyframe-parallax", "1e9"], "--keyframe-parallax"),
        (["baseline", "--rig", "R", "--distance", "100", "-5"], "--distance"),
        (["calibrate", "camera", "x.png", "--target", "checkerboard:8x6:12",
          "--mirror-a", "inf"], "--mirror-a"),
        (["calibrate", "camera", "x.png", "--target", "checkerboard:1x6:12"], "--target"),
        (["rig", "import-ocam", "c.txt", "--radius-max", "-3"], "--radius-max"),
    ],
)
def test_numbers_are_refused_while_parsing(
    tmp_path: Path, capsys: pytest.CaptureFixture[str], argv: list[str], option: str
) -> None:
    """Nothing is read (the dataset, rig and images named here do not exist) and
    nothing is written: the value is refused first, in one line naming the option."""
    out = tmp_path / "out"
    one_line_error(capsys, [*argv, "--out", str(out)], f"{option}:")
    assert not out.exists()


# --- 3: --scheduler -----------------------------------------------------------------------


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


@pytest.mark.parametrize(
    ("address", "needle"),
    [
        ("tcp://127.0.0.1", "has no port"),  # 21 s and a 59-line traceback before
        ("foo://127.0.0.1:8786", "unknown protocol 'foo://'"),  # 21 s, 50 lines before
        ("tcp://127.0.0.1:0", "port must be 1-65535"),
        ("tcp://[::1", "has no port"),
        ("tcp://bad host:8786", "not a host name"),
        ("tcp://127.0.0.1:{free}", "cannot reach the Dask scheduler"),  # nothing listens
        ("tcp://127.0.0.1:{silent}", "cannot reach the Dask scheduler"),  # not Dask
    ],
)
@pytest.mark.parametrize("command", ["reconstruct", "batch"])
def test_every_scheduler_error_is_one_line_within_5_s(
    tiny: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str], address: str,
    needle: str, command: str,
) -> None:
    if "{" in address:
        pytest.importorskip("distributed")
    # A socket that accepts connections and never says anything (not a scheduler).
    with socket.socket() as silent:
        silent.bind(("127.0.0.1", 0))
        silent.listen(8)
        address = address.format(free=_free_port(), silent=silent.getsockname()[1])
        out = tmp_path / "out"
        start = time.monotonic()
        err = one_line_error(capsys, [command, str(tiny), "--out", str(out), "--quiet",
                                      "--scheduler", address], needle)
        took = time.monotonic() - start
    assert took < 5.0, f"{took:.1f} s"
    assert "Exception ignored" not in err and not out.exists()


# --- 5: bags and YAML ---------------------------------------------------------------------


def _broken_bag(root: Path, tiny: Path) -> Path:
    """A ROS 2 bag folder whose metadata.yaml is not YAML (a bracket left open)."""
    bag = root / "bag"
    bag.mkdir()
    (bag / "metadata.yaml").write_text(
        "rosbag2_bagfile_information:\n  version: 8\n  storage_identifier: [sqlite3\n"
        "  duration: {nanoseconds: 1}\n"
    )
    (bag / "rig.yaml").write_bytes((tiny / "rig.yaml").read_bytes())
    return bag


def test_broken_bag_metadata_is_one_line(
    tiny: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """7 lines (the YAML parser's context) before; now the problem and its line."""
    pytest.importorskip("rosbags")
    bag = _broken_bag(tmp_path, tiny)
    one_line_error(capsys, ["reconstruct", str(bag), "--out", str(tmp_path / "o"), "--quiet"],
                   "not a readable ROS bag", "metadata.yaml: expected ',' or ']'", "(line 4,")
    capsys.readouterr()
    assert main(["batch", str(bag), "--out", str(tmp_path / "b")]) == 1
    captured = capsys.readouterr()
    assert "FAILED  bag: " in captured.out and "(line 4, column 11)" in captured.out
    assert captured.out.count("\n") == 2  # the run's line, the summary line


def test_yaml_errors_name_the_line(
    tiny: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    config = tmp_path / "c.yaml"
    config.write_text("sfm:\n  a: [1\n  b: 2\n")
    one_line_error(capsys, ["reconstruct", str(tiny), "--out", str(tmp_path / "o"), "--config",
                            str(config), "--quiet"], "c.yaml: config: not valid YAML", "(line 3,")


# --- 7: an OUT that cannot be written -----------------------------------------------------


@pytest.mark.skipif(not Path("/proc/self").is_dir(), reason="needs Linux /proc")
@pytest.mark.parametrize("out", ["/proc/x", "/proc/x/y/z"])
def test_unwritable_out_is_refused_before_any_work(
    tiny: Path, capsys: pytest.CaptureFixture[str], out: str
) -> None:
    """Refused after the whole run before; now at start-up (no run is even listed)."""
    for command in ("reconstruct", "batch", "simulate"):
        argv = [command, str(tiny)] if command != "simulate" else [command]
        err = one_line_error(capsys, [*argv, "--out", out, "--quiet"], out)
        assert "cannot" in err
