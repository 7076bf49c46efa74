"""The executor: inline, local processes and a Dask LocalCluster give the same results, in
submission order; the frame-parallel laser stage equals the serial one."""

from __future__ import annotations

import sys
import time
from pathlib import Path

import numpy as np
import pytest

from omnipipe.cli import main
from omnipipe.errors import ConfigError, DatasetError
from omnipipe.executor import (
    InlineExecutor,
    chunks,
    describe,
    open_executor,
    ordered_map,
    parallelism,
)


def _late_square(x: int) -> int:
    """x^2, finishing in the reverse order of submission (earlier items sleep longer)."""
    time.sleep(0.002 * (10 - x))
    return x * x


def _fail_on_three(x: int) -> int:
    if x == 3:
        raise DatasetError(f"frame {x}: broken")
    return x


@pytest.fixture(scope="module")
def dask_address():
    distributed = pytest.importorskip("distributed")
    cluster = distributed.LocalCluster(
        host="127.0.0.1",
        protocol="tcp",
        processes=False,
        n_workers=1,
        threads_per_worker=2,
        dashboard_address=None,
    )
    try:
        yield cluster.scheduler_address
    finally:
        cluster.close()


@pytest.fixture(scope="module")
def tiny_dataset(tmp_path_factory: pytest.TempPathFactory) -> Path:
    from omnipipe.sim import make_scenario, run

    out = tmp_path_factory.mktemp("exec") / "ds"
    run(make_scenario("paper-small", frames=7, seed=8), out, workers=1)
    return out


def _executors(dask_address: str):
    return [
        {"workers": 1},
        {"workers": 2},
        {"scheduler": dask_address},
    ]


def test_results_in_submission_order_on_every_executor(dask_address: str) -> None:
    for kwargs in _executors(dask_address):
        with open_executor(**kwargs) as ex:
            got = list(ordered_map(ex, _late_square, range(10), max_pending=4))
        assert got == [x * x for x in range(10)], kwargs


def test_a_task_error_is_raised_in_its_turn(dask_address: str) -> None:
    for kwargs in _executors(dask_address):
        seen = []
        with open_executor(**kwargs) as ex, pytest.raises(DatasetError, match="frame 3: broken"):
            for value in ordered_map(ex, _fail_on_three, range(8)):
                seen.append(value)
        assert seen == [0, 1, 2], kwargs


def test_kinds_and_parallelism(dask_address: str) -> None:
    with open_executor(workers=1) as ex:
        assert isinstance(ex, InlineExecutor) and describe(ex) == {"kind": "inline", "workers": 1}
    with open_executor(workers=3) as ex:
        assert describe(ex) == {"kind": "processes", "workers": 3}
    with open_executor(scheduler=dask_address) as ex:
        assert describe(ex) == {"kind": "dask", "workers": 2}
        parts = chunks(37, ex)
    assert [i for part in parts for i in part] == list(range(37))
    assert max(len(p) for p in parts) <= 16 and parallelism(InlineExecutor()) == 1


def _assert_same_rings(a, b) -> None:
    assert len(a.rings) == len(b.rings) and a.warnings == b.warnings
    for ra, rb in zip(a.rings, b.rings, strict=True):
        for name in ("pixels", "angle_rad", "confidence", "radius_sigma_px", "points_in_rig", "sigma_mm"):
            assert np.array_equal(getattr(ra, name), getattr(rb, name), equal_nan=True), name
        assert ra.scanned == rb.scanned and ra.warnings == rb.warnings


def test_parallel_laser_stage_equals_serial(tiny_dataset: Path, dask_address: str) -> None:
    from omnipipe import laser
    from omnipipe.dataset import open_dataset

    dataset = open_dataset(tiny_dataset)
    serial = laser.run(laser.LaserConfig(), dataset.rig, (dataset.read_frame(i) for i in range(len(dataset))))
    assert sum(len(r.pixels) > 100 for r in serial.rings) == len(dataset)  # rings were found
    for kwargs in _executors(dask_address):
        done: list[int] = []
        with open_executor(**kwargs) as ex:
            result = laser.run_dataset(laser.LaserConfig(), dataset, ex, progress=done.append)
        _assert_same_rings(serial, result)
        assert done[-1] == len(dataset) and done == sorted(done), kwargs


def test_unreadable_frame_named_from_a_worker(tiny_dataset: Path, tmp_path: Path) -> None:
    import shutil

    from omnipipe import laser
    from omnipipe.dataset import open_dataset

    ds = tmp_path / "ds"
    shutil.copytree(tiny_dataset, ds)
    data = (ds / "frames" / "000005.png").read_bytes()
    (ds / "frames" / "000005.png").write_bytes(data[: len(data) // 2])
    with open_executor(workers=2) as ex, pytest.raises(DatasetError, match=r"000005\.png"):
        laser.run_dataset(laser.LaserConfig(), open_dataset(ds), ex)


def test_scheduler_without_dask_is_one_line(
    tiny_dataset: Path, tmp_path: Path, monkeypatch: pytest.MonkeyPatch, capsys
) -> None:
    monkeypatch.setitem(sys.modules, "distributed", None)  # import distributed fails
    with pytest.raises(ConfigError, match=r"pip install 'omnipipe\[dask\]'"):
        with open_executor(scheduler="tcp://127.0.0.1:8786"):
            pass
    out = tmp_path / "out"
    args = ["reconstruct", str(tiny_dataset), "--out", str(out), "--quiet"]
    assert main([*args, "--scheduler", "tcp://127.0.0.1:8786"]) == 1
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "--scheduler" in err[0] and "omnipipe[dask]" in err[0]
    assert not out.exists()


@pytest.mark.parametrize(
    ("option", "value", "message"),
    [("--workers", "0", "--workers: must be a whole number from 1 to"), ("--scheduler", "localhost", "tcp://HOST:8786")],
)
def test_bad_execution_options_are_one_line(
    tiny_dataset: Path, tmp_path: Path, capsys, option: str, value: str, message: str
) -> None:
    out = tmp_path / "out"
    assert main(["reconstruct", str(tiny_dataset), "--out", str(out), "--quiet", option, value]) == 1
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and message in err[0]
    assert not out.exists()


def _checksums(source) -> list[tuple[int, int]]:
    return [(int(source.frames[k]), int(source.read(k).sum())) for k in range(len(source))]


def test_map_frames_on_a_subset_keeps_its_order(tiny_dataset: Path) -> None:
    from omnipipe.dataset import open_dataset
    from omnipipe.executor import map_frames

    dataset = open_dataset(tiny_dataset)
    truth = [(i, int(dataset.read_frame(i).sum())) for i in range(len(dataset))]
    done: list[int] = []
    with open_executor(workers=2) as ex:
        subset = map_frames(ex, _checksums, dataset, progress=done.append, frames=[5, 1, 4, 6])
        everything = map_frames(ex, _checksums, dataset)
    assert subset == [truth[5], truth[1], truth[4], truth[6]] and done[-1] == 4
    assert everything == truth


def test_worker_cached_builds_once_per_key_and_keeps_the_last() -> None:
    from omnipipe.executor import worker_cached

    built: list[tuple[int, ...]] = []

    def build(key: tuple[int, ...]) -> list[int]:
        built.append(key)
        return list(key)

    a = worker_cached("test.cache", (1, 2), lambda: build((1, 2)))
    assert worker_cached("test.cache", (1, 2), lambda: build((1, 2))) is a  # same key: kept
    b = worker_cached("test.cache", (3,), lambda: build((3,)))
    assert b == [3] and b is not a
    assert worker_cached("test.cache", (1, 2), lambda: build((1, 2))) is not a  # only the last kept
    assert worker_cached("test.other", (3,), lambda: build((3,))) is not b  # names are separate
    assert built == [(1, 2), (3,), (1, 2), (3,)]


def test_thread_map_keeps_the_order_of_the_serial_loop() -> None:
    from omnipipe.executor import thread_map

    items = list(range(20))
    assert thread_map(lambda a, b: a * b, items, items[::-1], threads=3) == [a * b for a, b in zip(items, items[::-1], strict=True)]
    assert thread_map(lambda a: a + 1, items, threads=1) == [a + 1 for a in items]
    assert thread_map(lambda a: a, [], threads=2) == []


def test_opencv_threads_limits_the_block_and_restores_the_count() -> None:
    import cv2

    from omnipipe.executor import opencv_threads

    before = cv2.getNumThreads()
    try:
        cv2.setNumThreads(2)
        with opencv_threads(1):
            assert cv2.getNumThreads() == 1
        assert cv2.getNumThreads() == 2
        with pytest.raises(RuntimeError), opencv_threads(1):
            raise RuntimeError("inside")
        assert cv2.getNumThreads() == 2
    finally:
        cv2.setNumThreads(before)


def _threads_inside_a_limit() -> tuple[int, int]:
    import cv2

    from omnipipe.executor import opencv_threads

    outside = cv2.getNumThreads()
    with opencv_threads(outside + 1):
        return outside, cv2.getNumThreads()


def test_opencv_threads_leaves_a_forked_worker_alone() -> None:
    with open_executor(2, None) as pool:
        outside, inside = pool.submit(_threads_inside_a_limit).result(timeout=60)
    assert inside == outside


def _opencv_thread_count() -> int:
    import cv2

    return int(cv2.getNumThreads())


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="forked pools on Linux only")
def test_forked_workers_run_opencv_serially_and_the_parent_keeps_its_threads() -> None:
    """Forked with OpenCV's pool stopped: a worker's OpenCV calls never wait on a pool mutex
    a parent's thread held at the fork; the parent's own setting is back after the fork."""
    import cv2

    before = cv2.getNumThreads()
    cv2.setNumThreads(2)
    cv2.remap(  # the parent's pool threads have run just before the fork
        np.zeros((64, 64), np.uint8),
        np.zeros((64, 64), np.float32),
        np.zeros((64, 64), np.float32),
        cv2.INTER_LINEAR,
    )
    try:
        with open_executor(2, None) as pool:
            parent_inside = cv2.getNumThreads()
            counts = [
                f.result(timeout=60) for f in [pool.submit(_opencv_thread_count) for _ in range(4)]
            ]
    finally:
        cv2.setNumThreads(before)
    assert parent_inside == 2
    assert counts == [1, 1, 1, 1]  # OpenCV reports 0 threads (serial) as 1


def _length(a: np.ndarray) -> int:
    return len(a)


def _feeder_bytes() -> int:
    """Bytes still allocated by the pickling of a multiprocessing queue's feeder thread."""
    import tracemalloc

    snap = tracemalloc.take_snapshot().filter_traces(
        [tracemalloc.Filter(True, "*multiprocessing/reduction.py")]
    )
    return sum(s.size for s in snap.statistics("filename"))


def test_a_pool_does_not_keep_the_last_task_pickled() -> None:
    """The feeder thread's last pickle (a task's 8 MB array) is not held after the map."""
    import tracemalloc

    big = np.arange(1 << 20, dtype=np.float64)  # 8 MB
    tracemalloc.start(1)
    try:
        with open_executor(workers=2) as pool:
            assert list(ordered_map(pool, _length, [big, big])) == [len(big)] * 2
            held = _feeder_bytes()
            for _ in range(200):  # the empty task is pickled by the feeder thread
                if held < 1 << 20:
                    break
                time.sleep(0.01)
                held = _feeder_bytes()
    finally:
        tracemalloc.stop()
    assert held < 1 << 20, f"{held / 1e6:.1f} MB of pickled tasks still held"


def test_shared_fields_are_equal_and_by_reference_only_on_a_local_pool() -> None:
    from dataclasses import dataclass

    from omnipipe.executor import shared_fields
    from omnipipe.spill import is_on_disk

    @dataclass(frozen=True)
    class Samples:
        z: np.ndarray
        ring: np.ndarray
        scale: float

    rng = np.random.default_rng(7)
    s = Samples(rng.random(500), rng.integers(0, 9, 500), 2.5)
    assert shared_fields(s, InlineExecutor()) is s
    with open_executor(workers=2) as pool:
        sent = shared_fields(s, pool)
        assert list(ordered_map(pool, _length, [sent.z, sent.ring])) == [500, 500]
    assert sent.scale == 2.5 and np.array_equal(sent.z, s.z) and np.array_equal(sent.ring, s.ring)
    assert is_on_disk(sent.z) and not sent.z.flags.writeable and not is_on_disk(s.z)


def _half_a_result_then_wait(marker: str) -> int:
    """In a pool worker: write the start of a result message (a length header and a few of
    its bytes) into the pool's result pipe, as a worker killed mid-write leaves it, then
    wait to be killed."""
    import struct

    frame = sys._getframe()
    while frame is not None and frame.f_code.co_name != "_process_worker":
        frame = frame.f_back
    assert frame is not None, "not running in a ProcessPoolExecutor worker"
    writer = frame.f_locals["result_queue"]._writer
    writer._send(struct.pack("!i", 1 << 20) + b"\0" * 16)
    Path(marker).touch()
    time.sleep(120)
    return 0


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="forked local pool")
def test_a_worker_killed_mid_result_does_not_hang_the_pool(tmp_path: Path) -> None:
    """A run that stops while a worker is writing its result ends the pool at once: the
    manager thread does not wait for the rest of a message nobody will write."""
    marker = tmp_path / "written"
    manager = None
    with pytest.raises(KeyboardInterrupt):
        with open_executor(workers=2) as pool:
            pool.submit(_half_a_result_then_wait, str(marker))
            deadline = time.monotonic() + 30
            while not marker.exists() and time.monotonic() < deadline:
                time.sleep(0.01)
            assert marker.exists()
            time.sleep(0.2)  # the manager is now inside recv(), waiting for the rest
            manager = pool._executor_manager_thread
            raise KeyboardInterrupt
    assert manager is not None
    manager.join(timeout=10)
    assert not manager.is_alive()
