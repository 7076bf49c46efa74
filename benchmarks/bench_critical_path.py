"""Who waits for whom in one reconstruct: each stage's and camera-motion step's CPU by thread, and the bounds on 2 cores.

    python benchmarks/bench_critical_path.py DATASET [--workers N] [--every 0.2]

Runs ``omnipipe reconstruct``'s computation (:func:`omnipipe.pipeline.run`, nothing
written) on DATASET and prints, for each stage and each step of the camera motion
(:func:`omnipipe.sfm.pipeline.run`'s frame loop, adjustment, resection, ...), its wall
time and the CPU seconds of this process's main thread, of its other threads (the
views' threads, the pool's feeder and manager) and of the executor's workers, sampled
from /proc (Linux) every ``--every`` s; with each thread's time waiting for a core
(``runq``, /proc/.../schedstat: the machine's other load) and the main thread's time
blocked (neither running nor runnable: waiting for its view threads, a worker's
result, the next frame).

For the frame loop it also prints the two lower bounds of its wall time on an idle
2-core machine, from CPU seconds alone (so they hold under other load):

- the **chain**: the main thread's own CPU plus, for every call that runs the views on
  threads (:func:`omnipipe.executor.thread_map`: SIFT, optical flow), the longest
  thread's share of the views' CPU when two threads take them in order;
- the **work**: the CPU seconds of the loop (main thread, other threads, workers) over
  2 cores.

Whichever is larger bounds the loop: when it is the work, handing the main thread's
work to the workers shortens nothing (only less CPU does); when it is the chain,
it does. The same for the whole run: CPU seconds over 2 cores against the wall.

The functions are timed by wrapping them where they are looked up (the stage calls of
:mod:`omnipipe.pipeline.run_state`, the steps of :mod:`omnipipe.sfm.pipeline`,
``thread_map`` in :mod:`omnipipe.sfm.features` and :mod:`omnipipe.sfm.tracking`): the
results are the run's own.
"""

from __future__ import annotations

import argparse
import os
import resource
import threading
import time
from collections import defaultdict
from collections.abc import Callable
from dataclasses import replace
from pathlib import Path
from typing import Any

import numpy as np

from omnipipe.dataset import open_dataset
from omnipipe.pipeline import ReconstructConfig, run

TICK = os.sysconf("SC_CLK_TCK") if hasattr(os, "sysconf") else 100
ME = os.getpid()
SFM_STEPS = (
    "follow_keyframes", "run_scale", "chain_steps", "_adjusted_and_checked", "run_length", "resect_pending", "_result",
)
STAGES = ("decode", "camera_motion", "analyse", "build_model")


def _cpu_of(path: str) -> tuple[int, float]:
    """(parent pid, CPU s) of /proc/PID[/task/TID]."""
    fields = Path(path, "stat").read_text().rsplit(")", 1)[1].split()
    return int(fields[1]), (int(fields[11]) + int(fields[12])) / TICK


def _sched_of(path: str) -> tuple[float, float]:
    """(s on a core, s waiting for one) of /proc/PID/task/TID."""
    run_ns, wait_ns = Path(path, "schedstat").read_text().split()[:2]
    return int(run_ns) / 1e9, int(wait_ns) / 1e9


class Sampler:
    """CPU seconds of this process's main thread, its other threads (this sampler's own
    left out) and its child processes, with the main thread's and the workers' schedstat,
    every ``every`` s on a thread while the block runs."""

    def __init__(self, every: float) -> None:
        self.every = every
        self.rows: list[tuple[float, ...]] = []
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._loop, daemon=True)

    def __enter__(self) -> Sampler:
        self._thread.start()
        return self

    def __exit__(self, *exc: object) -> None:
        self._stop.set()
        self._thread.join()

    def _loop(self) -> None:
        while True:
            self.rows.append(self._now())
            if self._stop.wait(self.every):
                self.rows.append(self._now())
                return

    def _now(self) -> tuple[float, ...]:
        main = other = main_q = workers = workers_q = 0.0
        own = threading.get_native_id()
        for task in os.scandir(f"/proc/{ME}/task"):
            try:
                _, cpu = _cpu_of(task.path)
                if int(task.name) == ME:
                    main = cpu
                    main_q = _sched_of(task.path)[1]
                elif int(task.name) != own:
                    other += cpu
            except OSError:
                continue
        for entry in os.scandir("/proc"):
            if not entry.name.isdigit() or int(entry.name) == ME:
                continue
            try:
                parent, cpu = _cpu_of(entry.path)
                if parent != ME:
                    continue
                workers += cpu
                for task in os.scandir(f"{entry.path}/task"):
                    workers_q += _sched_of(task.path)[1]
            except OSError:
                continue
        gone = resource.getrusage(resource.RUSAGE_CHILDREN)
        return time.perf_counter(), main, main_q, other, workers + gone.ru_utime + gone.ru_stime, workers_q

    def between(self, t0: float, t1: float) -> list[float]:
        """[main, main runq, other, workers, workers runq] seconds between ``t0`` and ``t1``."""
        cols = list(zip(*self.rows, strict=True))
        ts = np.array(cols[0])
        return [float(np.interp(t1, ts, c) - np.interp(t0, ts, c)) for c in map(np.array, cols[1:])]


class Marks:
    """Start and end times of wrapped calls, the main thread's CPU in the frame loop and
    the views' thread calls' CPU (summed, and the longer of two threads taking them in
    order)."""

    def __init__(self) -> None:
        self.spans: list[tuple[str, float, float]] = []
        self.sums: dict[str, float] = defaultdict(float)

    def wrap(self, module: Any, name: str) -> None:
        fn = getattr(module, name)

        def timed(*args: Any, **kwargs: Any) -> Any:
            t0, c0 = time.perf_counter(), time.thread_time()
            try:
                return fn(*args, **kwargs)
            finally:
                self.spans.append((name, t0, time.perf_counter()))
                if name == "follow_keyframes":
                    self.sums["loop main"] += time.thread_time() - c0

        setattr(module, name, timed)

    def thread_map(self, original: Callable[..., list]) -> Callable[..., list]:
        def timed_map(fn: Callable[..., Any], *iterables: Any, threads: int = 1) -> list:
            costs: list[float] = []

            def one(*args: Any) -> Any:
                c0 = time.thread_time()
                try:
                    return fn(*args)
                finally:
                    costs.append(time.thread_time() - c0)

            try:
                return original(one, *iterables, threads=threads)
            finally:
                if threading.get_ident() == threading.main_thread().ident:
                    free = [0.0, 0.0]
                    for c in costs:  # the pool's threads take the calls in order
                        free[int(free[1] < free[0])] += c
                    self.sums["views"] += sum(costs)
                    self.sums["views on 2 threads"] += max(free)

        return timed_map


def _instrument(marks: Marks) -> None:
    import omnipipe.pipeline.run_state as run_state
    import omnipipe.sfm.features as features
    import omnipipe.sfm.pipeline as sfm_pipeline
    import omnipipe.sfm.tracking as tracking

    for name in STAGES:
        marks.wrap(run_state, name)
    for name in SFM_STEPS:
        marks.wrap(sfm_pipeline, name)
    for module in (features, tracking):
        module.thread_map = marks.thread_map(module.thread_map)  # type: ignore[attr-defined]


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("dataset")
    parser.add_argument("--workers", type=int, default=None)
    parser.add_argument("--every", type=float, default=0.2, help="sampling period, s")
    args = parser.parse_args()
    marks = Marks()
    _instrument(marks)
    dataset = open_dataset(Path(args.dataset))
    for path in dataset.frame_paths:  # into the OS's file cache
        path.read_bytes()
    config = replace(ReconstructConfig.default(), workers=args.workers)
    t0 = time.perf_counter()
    with Sampler(args.every) as sampler:
        rec = run(config, dataset)
    t1 = time.perf_counter()
    print(f"dataset {args.dataset}: {len(dataset)} frames, keyframes {rec.summary.get('keyframes')}")
    print("| step | start s | wall s | main CPU | main runq | main blocked | other threads CPU | workers CPU | workers runq |")
    print("|---|---|---|---|---|---|---|---|---|")
    for name, a, b in sorted([("run", t0, t1), *marks.spans], key=lambda s: s[1]):
        m, mq, o, w, wq = sampler.between(a, b)
        print(
            f"| {name} | {a - t0:.1f} | {b - a:.1f} | {m:.2f} | {mq:.1f} | {b - a - m - mq:.1f} | {o:.2f} | "
            f"{w:.2f} | {wq:.1f} |"
        )
    _bounds(marks, sampler, t0, t1)


def _bounds(marks: Marks, sampler: Sampler, t0: float, t1: float) -> None:
    """The frame loop's and the run's lower bounds on an idle 2-core machine."""
    loop = [s for s in marks.spans if s[0] == "follow_keyframes"]
    if loop:
        m, _, o, w, _ = sampler.between(loop[0][1], loop[0][2])
        views, views2 = marks.sums["views"], marks.sums["views on 2 threads"]
        chain = marks.sums["loop main"] + views2
        work = (m + o + w) / 2
        print(
            f"frame loop: main thread {marks.sums['loop main']:.2f} CPU-s, views on threads {views:.2f} CPU-s "
            f"({views2:.2f} s on 2 threads), other threads {o:.2f}, workers {w:.2f}; on 2 idle cores at least: "
            f"the chain {chain:.2f} s, the work {work:.2f} s -> bound by the {'chain' if chain > work else 'work'}"
        )
    m, _, o, w, _ = sampler.between(t0, t1)
    print(f"run: {m + o + w:.1f} CPU-s (main {m:.1f}, other threads {o:.1f}, workers {w:.1f}); over 2 cores "
          f"{(m + o + w) / 2:.1f} s against {t1 - t0:.1f} s wall")


if __name__ == "__main__":
    main()
