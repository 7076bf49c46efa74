"""Shared fixtures: small rigs and simulated scenes made at run time."""

from __future__ import annotations

import os
import sys
import threading
from collections.abc import Callable, Iterator
from pathlib import Path

import pytest
from threadpoolctl import threadpool_limits

from omnipipe.camera import OmniCamera
from omnipipe.rig import Rig
from omnipipe.sim import make_scenario, paper_rig, run

# One BLAS thread in this process and in the commands the tests start: the tests' matrices
# are small, and a second OpenBLAS thread mostly spins (tests/analysis/test_point_features'
# first test on a loaded 2-core machine: 3.8x the CPU time and 3.6x the wall time of one
# thread); worker processes already run with one (omnipipe.executor). Results agree
# within the tests' tolerances either way.
os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")
threadpool_limits(limits=1, user_api="blas")


def _pool_managers() -> list[threading.Thread]:
    """The live manager threads of process pools (concurrent.futures.process)."""
    return [
        t
        for t in threading.enumerate()
        if type(t).__name__ == "_ExecutorManagerThread" and t.is_alive()
    ]


@pytest.fixture(autouse=True)
def _no_process_pool_outlives_its_test() -> Iterator[None]:
    """A process pool left running after a test hangs the interpreter's exit (its manager
    thread waits for results of workers that are gone): the test that left it fails (after
    60 s for it to end: a pool shutting down on a machine at load 40 took more than 15 s)."""
    before = set(_pool_managers())
    yield
    left = [t for t in _pool_managers() if t not in before]
    for thread in left:
        thread.join(timeout=60)
    left = [t for t in left if t.is_alive()]
    if left:
        pytest.fail(f"a process pool's manager thread outlived the test: {left}")


def pytest_unconfigure(config: pytest.Config) -> None:
    """Exit with status 1 instead of hanging when a process pool is still running."""
    if _pool_managers():
        sys.stderr.write(f"process pool still running at exit: {_pool_managers()}\n")
        sys.stderr.flush()
        os._exit(1)


@pytest.fixture(scope="session")
def small_rig() -> Rig:
    """The paper-like rig at 400x300 px."""
    return paper_rig(400, 300)


@pytest.fixture(scope="session")
def small_camera(small_rig: Rig) -> OmniCamera:
    return OmniCamera.from_rig(small_rig)


@pytest.fixture(scope="session")
def small_dataset(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """A paper-small simulated dataset (400x300, 24 frames) on disk, made once per session."""
    out = tmp_path_factory.mktemp("datasets") / "paper-small"
    run(make_scenario("paper-small", seed=3), out)
    return out


@pytest.fixture(scope="session")
def tiny_dataset(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """4 simulated paper-small frames of 64x48 px with timestamps.txt and ground truth,
    made once per session (tests that change it work on a copy)."""
    out = tmp_path_factory.mktemp("tiny") / "ds"
    run(make_scenario("paper-small", frames=4, size=(64, 48), seed=2), out, workers=1)
    return out


def _snapshot(root: Path) -> dict[str, bytes | None]:
    """Every file (content) and folder (None) under root, hidden ones included."""
    found: dict[str, bytes | None] = {}
    for here, dirnames, filenames in os.walk(root):
        for d in dirnames:
            found[str(Path(here, d).relative_to(root))] = None
        for f in filenames:
            found[str(Path(here, f).relative_to(root))] = Path(here, f).read_bytes()
    return found


@pytest.fixture(scope="session")
def snapshot() -> Callable[[Path], dict[str, bytes | None]]:
    """``snapshot(root)``: every file (content) and folder (None) under root, hidden ones
    included: equal snapshots before and after prove nothing there was touched."""
    return _snapshot


@pytest.fixture(scope="session")
def two_tiny_runs(tmp_path_factory: pytest.TempPathFactory) -> list[Path]:
    """Two paper-small runs of 6 frames at 320x240 (seeds 3 and 4), made once per session
    for the batch tests (tests that change them work on copies)."""
    root = tmp_path_factory.mktemp("two_runs")
    out = []
    for seed in (3, 4):
        path = root / f"pipe-{seed}"
        run(make_scenario("paper-small", frames=6, size=(320, 240), seed=seed), path, workers=1)
        out.append(path)
    return out


@pytest.fixture(scope="session")
def eight_frames(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """`omnipipe simulate --scenario paper-small --frames 8 --seed 0` (400x300), made once
    per session (tests that change it work on a copy)."""
    out = tmp_path_factory.mktemp("eight") / "images"
    run(make_scenario("paper-small", frames=8, seed=0), out, workers=1)
    return out
