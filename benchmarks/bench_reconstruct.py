"""End to end on simulated scenarios: simulate, reconstruct, evaluate; print errors and times.

    python benchmarks/bench_reconstruct.py --scenario bend|continuous|random[,...] [--frames N]
        [--size WxH] [--seed S] [--random-seeds S ...] [--dataset NAME=DIR ...] [--keep DIR]
        [--reuse] [--workers N] [--scheduler tcp://HOST:PORT]

Prints the trajectory errors, Table I (diameter, defects) against ground truth, the
wall time and frames/s of each stage (report.json's ``timings_s``: the computation), the
time writing the outputs takes on top (model files, report.html; what ``omnipipe
reconstruct`` also does), and the time it takes merely to decode the same frames on the
same workers (the floor of the laser stage, which decodes and extracts; the median of
:data:`DECODE_REPEATS` runs, in wall time and in CPU seconds: the laser stage's CPU
seconds over decode-only's is the ratio that does not move with the machine); and, on
workers of its own, the time to decode them and hand the moving ones on as the laser
stage does (:class:`omnipipe.laser.DecodeHandOn`: the writes that spare
the later stages decoding them again). The frames'
files are read once before either is timed, so that both find them in the OS's file
cache: otherwise the laser stage, the first to read them, also paid for the disk
(a reused dataset read after other work: 1.38 against 1.13-1.17 once cached).
Each stage is also reported per moving frame (``continuous``: every frame moves; bend
has 245 stationary frames of 330, which cost little), and the cores the reconstruction
kept busy on average (CPU seconds of this process and its workers over the wall time),
and each stage's CPU seconds (this process and its workers, sampled from /proc every
0.2 s on Linux; this process's own share beside them: the frame-by-frame chain of the
camera motion runs there, the rest in the workers): on a machine shared with other work
they, unlike the times, hardly depend on that work.
Nothing is tuned here: the defaults of ``omnipipe reconstruct``.

Several scenarios (``--scenario continuous,bend``, ``--random-seeds 0 1 2`` for members
of the random family) are run one after the other and summed up in one table at the
end. ``--dataset NAME=DIR`` reconstructs a dataset rendered before (read only; e.g.
``continuous=/tmp/bench/continuous``) instead of simulating scenario NAME. ``--reuse``
with ``--keep DIR`` reconstructs the dataset an earlier ``--keep DIR`` run simulated
there (when its frame count and image size are the scenario's) instead of simulating
again.
"""

from __future__ import annotations

import argparse
import os
import resource
import shutil
import tempfile
import threading
import time
from dataclasses import dataclass, replace
from pathlib import Path

from omnipipe.dataset import open_dataset
from omnipipe.errors import OmnipipeError
from omnipipe.evaluation import EvaluationConfig, EvaluationInputs
from omnipipe.evaluation import run as evaluate
from omnipipe.evaluation.cli import format_result
from omnipipe.executor import describe, map_frames, open_executor
from omnipipe.laser import DecodeHandOn, decode_only
from omnipipe.pipeline import ReconstructConfig, run, table_one, write
from omnipipe.pipeline.cli import format_table_one
from omnipipe.sim import make_scenario
from omnipipe.sim import run as simulate


@dataclass(frozen=True)
class _Row:
    """One scenario's line of the closing table."""

    name: str
    frames: int
    moving: int
    timings: dict[str, float]
    decode_s: float
    cores_busy: float
    cpu_ratio: float | None


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--scenario", default="bend", help="one or more, comma-separated")
    parser.add_argument("--frames", type=int, default=None)
    parser.add_argument("--size", default=None, help="WxH (default: the scenario's)")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--random-seeds", type=int, nargs="*", default=[], help="random-family members")
    parser.add_argument("--dataset", action="append", default=[], help="NAME=DIR: reconstruct DIR for scenario NAME")
    parser.add_argument("--keep", default=None, help="keep dataset and reconstruction in this directory")
    parser.add_argument("--reuse", action="store_true", help="with --keep: reuse the dataset simulated there")
    parser.add_argument("--workers", type=int, default=None, help="local processes (default: every core)")
    parser.add_argument("--scheduler", default=None, help="Dask scheduler tcp://HOST:PORT")
    args = parser.parse_args()
    size = tuple(int(v) for v in args.size.split("x")) if args.size else None
    given = dict(item.split("=", 1) for item in args.dataset)
    runs = [(name, args.seed) for name in args.scenario.split(",") if name]
    runs += [("random", seed) for seed in args.random_seeds]
    rows = []
    for name, seed in runs:
        scenario = make_scenario(name, frames=args.frames, size=size, seed=seed)
        keep = Path(args.keep) / f"{name}-{seed}" if args.keep and len(runs) > 1 else args.keep
        rows.append(_bench(args, scenario, seed, Path(given[name]) if name in given else None, keep))
    if len(rows) > 1:
        print()
        print(_table(rows))


def _bench(args: argparse.Namespace, scenario, seed: int, dataset_dir: Path | None, keep) -> _Row:
    """Simulate (unless ``dataset_dir`` is given), reconstruct, evaluate and print one run."""
    root = Path(keep) if keep else Path(tempfile.mkdtemp(prefix="omnipipe-bench-"))
    try:
        t0 = time.perf_counter()
        data = dataset_dir or root / "dataset"
        if dataset_dir is None and not (args.reuse and _same_run(data, scenario)):
            simulate(scenario, data, force=True, workers=2)
        t_sim = time.perf_counter() - t0
        config = replace(ReconstructConfig.default(), workers=args.workers, scheduler=args.scheduler)
        dataset = open_dataset(data)
        for path in dataset.frame_paths:  # into the OS's file cache, for both timings
            path.read_bytes()
        cpu0 = _cpu_s()
        t0 = t_run = time.perf_counter()
        with _TreeCpu() as tree:
            rec = run(config, dataset)
        busy = (_cpu_s() - cpu0) / max(time.perf_counter() - t0, 1e-9)
        # The floor of the laser stage: decode the same frames on the same kind of executor;
        # and decode them and hand the moving ones on, as the laser stage does for the
        # later stages (which then decode none again).
        # Each on workers of its own, started as the run's were, the two alternating.
        (t_decode, cpu_decode), (t_handing, cpu_handing), where = _decode_floor(args, dataset, rec.summary)
        t0 = time.perf_counter()
        write(rec, root / "reconstruction", force=True)
        t_write = time.perf_counter() - t0
        ev = evaluate(EvaluationConfig(), EvaluationInputs(root / "reconstruction", data))
        cam = dataset.rig.camera
        n = len(dataset)
        source = f"dataset {data}" if dataset_dir else f"seed {seed}"
        print(f"scenario {scenario.name}, {n} frames at {cam.width}x{cam.height}, {source}")
        print(format_result(ev))
        print(format_table_one(table_one(rec.summary, ev.to_dict())))
        t = rec.summary["timings_s"]
        fps = rec.summary["frames_per_s"]
        sim = "given" if dataset_dir else f"{t_sim:.1f} s (2 workers{'; reused' if t_sim < 5 else ''})"
        print(
            f"time: simulate {sim}; reconstruct {t['total']:.1f} s (laser {t['laser']:.1f}, "
            f"sfm {t['sfm']:.1f}, analysis {t['analysis']:.1f}, model {t['model']:.1f}); "
            f"{n / t['total']:.2f} frames/s; keyframes {rec.summary['keyframes']}; "
            f"cores busy {busy:.2f} on average"
        )
        print(
            f"writing the outputs (model files, report.html): {t_write:.1f} s; reconstruct and write "
            f"{t['total'] + t_write:.1f} s, {n / (t['total'] + t_write):.2f} frames/s"
        )
        print(
            "frames/s per stage: "
            + ", ".join(f"{k} {v:.2f}" for k, v in fps.items() if v is not None)
            + f" (executor {where['kind']}, {where['workers']} workers)"
        )
        stationary = int(rec.summary.get("stationary_frames", 0))
        print(_per_stage(t, n, stationary))
        print(tree.per_stage(t_run, t))
        cpu_laser = tree.stage_cpu(t_run, t).get("laser")
        cpu_ratio = None if cpu_laser is None or cpu_decode is None else cpu_laser / cpu_decode
        print(
            f"laser stage {t['laser']:.2f} s ({n / t['laser']:.1f} frames/s) vs decode only "
            f"{t_decode:.2f} s ({n / t_decode:.1f} frames/s; median of {DECODE_REPEATS}) on the same workers: "
            f"ratio {t['laser'] / t_decode:.2f}"
            + ("" if cpu_ratio is None else f", in CPU seconds {cpu_laser:.2f} / {cpu_decode:.2f} = {cpu_ratio:.2f}")
            + (
                ""
                if t_handing is None
                else f"; vs decode and hand the moving frames on {t_handing:.2f} s: ratio {t['laser'] / t_handing:.2f}"
            )
        )
        if cpu_ratio is not None and cpu_handing is not None:
            print(_hand_on_share(cpu_laser, cpu_decode, cpu_handing))
        for w in rec.summary["warnings"][:10]:
            print("warning:", w)
        return _Row(f"{scenario.name}" + (f" (seed {seed})" if scenario.name.startswith("random") else ""),
                    n, n - stationary, dict(t), t_decode, busy, cpu_ratio)
    finally:
        if not keep:
            shutil.rmtree(root, ignore_errors=True)


DECODE_REPEATS = 3
"""Times the decode-only floor (and the decode-and-hand-on one) is measured, each on
workers of its own, the two alternating: their wall time moves with the machine from
run to run; the median wall time and the median CPU seconds are what the laser stage is
compared with."""


def _decode_floor(args: argparse.Namespace, dataset, summary: dict) -> tuple[tuple, tuple, dict]:
    """(wall, CPU) seconds of decoding every frame of ``dataset`` on a fresh executor, and
    of decoding them and handing the moving ones on (:func:`_decode_hand_on`; (None,
    None) without a local process pool): medians of :data:`DECODE_REPEATS` runs each,
    alternating; CPU seconds of this process and its workers, counted once each pool
    has shut down (None on a Dask cluster, whose workers are not this process's); and
    the executor's description."""
    import statistics

    runs: dict[str, list[tuple[float, float]]] = {"decode": [], "hand_on": []}
    for _ in range(DECODE_REPEATS):
        for kind in runs:
            cpu0 = _cpu_s()
            with open_executor(args.workers, args.scheduler) as ex:
                t0 = time.perf_counter()
                if kind == "decode":
                    map_frames(ex, decode_only, dataset)
                    wall: float | None = time.perf_counter() - t0
                else:
                    wall = _decode_hand_on(ex, dataset, summary)
                where = describe(ex)
            if wall is not None:
                runs[kind].append((wall, _cpu_s() - cpu0))

    def medians(kind: str) -> tuple[float | None, float | None]:
        got = runs[kind]
        if not got:
            return None, None
        return statistics.median(w for w, _ in got), None if args.scheduler else statistics.median(c for _, c in got)

    return medians("decode"), medians("hand_on"), where


def _decode_hand_on(ex, dataset, summary: dict) -> float | None:
    """Seconds to decode every frame of ``dataset`` on ``ex`` and hand its moving frames
    (the stations of ``summary``, report.json's) on to a scratch folder, as the laser
    stage's decoding pass does (:class:`omnipipe.handoff.FrameHandoff`: only with a local
    process pool); None without one."""
    from concurrent.futures import ProcessPoolExecutor

    import numpy as np

    from omnipipe.handoff import FrameHandoff

    if not isinstance(ex, ProcessPoolExecutor):
        return None
    moving = np.zeros(len(dataset), bool)
    moving[[int(s["frame"]) for s in summary.get("stations", []) if "frame" in s]] = True
    with FrameHandoff(len(dataset)) as handoff:
        # The pass hands frames on up to its budget of bytes (the first ones).
        cam = dataset.rig.camera
        per_frame = cam.width * cam.height * (3 if dataset.rig.laser.channel != "red" else 1.5)  # planar
        moving[np.flatnonzero(moving)[int(-(-handoff.budget_bytes // per_frame)) :]] = False
        t0 = time.perf_counter()
        map_frames(ex, DecodeHandOn(handoff.folder, moving), dataset)
        return time.perf_counter() - t0


class _TreeCpu:
    """CPU seconds of this process and its child processes (live and finished), and of
    this process alone, sampled every 0.2 s on a thread while the block runs (Linux
    /proc; elsewhere nothing)."""

    def __init__(self) -> None:
        self.samples: list[tuple[float, float, float]] = []
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._loop, daemon=True)
        self._tick = os.sysconf("SC_CLK_TCK") if hasattr(os, "sysconf") else 100

    def __enter__(self) -> _TreeCpu:
        if Path("/proc/self/stat").exists():
            self._thread.start()
        return self

    def __exit__(self, *exc: object) -> None:
        self._stop.set()
        if self._thread.is_alive():
            self._thread.join()

    def _loop(self) -> None:
        while True:
            self.samples.append((time.perf_counter(), *self._now()))
            if self._stop.wait(0.2):
                self.samples.append((time.perf_counter(), *self._now()))
                return

    def _now(self) -> tuple[float, float]:
        """(CPU s of the tree, CPU s of this process alone)."""
        me = os.getpid()
        ticks = own = 0
        for entry in os.scandir("/proc"):
            if not entry.name.isdigit():
                continue
            try:
                fields = Path(entry.path, "stat").read_text().rsplit(")", 1)[1].split()
            except OSError:
                continue
            if int(entry.name) == me or int(fields[1]) == me:  # fields[1]: the parent's id
                ticks += int(fields[11]) + int(fields[12])  # utime, stime
                own += (int(fields[11]) + int(fields[12])) if int(entry.name) == me else 0
        kids = resource.getrusage(resource.RUSAGE_CHILDREN)  # children already gone
        return ticks / self._tick + kids.ru_utime + kids.ru_stime, own / self._tick

    def at(self, t: float, parent: bool = False) -> float:
        """CPU seconds (of this process alone with ``parent``) at time ``t``
        (perf_counter), interpolated between samples."""
        import numpy as np

        ts, cpu, own = zip(*self.samples, strict=True)
        return float(np.interp(t, ts, own if parent else cpu))

    def stage_cpu(self, t0: float, timings: dict[str, float]) -> dict[str, float]:
        """Each stage's CPU seconds (this process and its workers), timed as
        :meth:`per_stage` does; empty when not measured."""
        if len(self.samples) < 2:
            return {}
        t, out = t0 + timings.get("startup", 0.0), {}
        for stage in ("laser", "sfm", "analysis", "model"):
            dt = timings.get(stage, 0.0)
            out[stage] = self.at(t + dt) - self.at(t)
            t += dt
        return out

    def per_stage(self, t0: float, timings: dict[str, float]) -> str:
        """One line: each stage's CPU seconds (and this process's share of them, the
        rest being the workers'), its start taken as the run's start (``t0``) plus the
        stages' times before it (report.json's ``timings_s``)."""
        if len(self.samples) < 2:
            return "CPU seconds per stage: not measured (no /proc)"
        t = t0 + timings.get("startup", 0.0)
        parts = []
        for stage in ("laser", "sfm", "analysis", "model"):
            dt = timings.get(stage, 0.0)
            cpu = self.at(t + dt) - self.at(t)
            own = self.at(t + dt, parent=True) - self.at(t, parent=True)
            parts.append(f"{stage} {cpu:.1f} ({cpu / max(dt, 1e-9):.2f} cores, this process {own:.1f})")
            t += dt
        total = self.at(t0 + timings["total"]) - self.at(t0)
        own = self.at(t0 + timings["total"], parent=True) - self.at(t0, parent=True)
        return (
            "CPU seconds per stage (this process and its workers): " + ", ".join(parts)
            + f"; total {total:.1f} (this process {own:.1f})"
        )


def _hand_on_share(cpu_laser: float, cpu_decode: float, cpu_handing: float) -> str:
    """The line that splits the laser stage's CPU seconds: the hand-on (the moving frames
    written for the camera motion's and the model's workers, which then decode none
    again: their input, done where the frame is decoded) measured as decoding and
    handing on minus decoding alone (a little more than the pass's own share: the pass
    splits a red laser's frame once for its station signature and its hand-on), and the
    rest (decode, ring, station signature) over decode-only. The stage's column keeps
    all of it."""
    hand_on = cpu_handing - cpu_decode
    return (
        f"laser stage in CPU seconds {cpu_laser:.2f}: of it handing the moving frames on ~{hand_on:.2f} "
        f"(decode and hand on {cpu_handing:.2f} - decode only {cpu_decode:.2f}); the rest "
        f"{cpu_laser - hand_on:.2f} = {(cpu_laser - hand_on) / cpu_decode:.2f} x decode-only"
    )


def _cpu_s() -> float:
    """CPU seconds (user + system) of this process and its finished child processes (the
    executor's workers are counted once the run's pool has shut down)."""
    own = resource.getrusage(resource.RUSAGE_SELF)
    kids = resource.getrusage(resource.RUSAGE_CHILDREN)
    return own.ru_utime + own.ru_stime + kids.ru_utime + kids.ru_stime


def _table(rows: list[_Row]) -> str:
    """The scenarios side by side: frames/s overall and per moving frame, each stage's
    share of the total, the laser stage over decode-only, the cores kept busy."""
    head = (
        "| scenario | frames (moving) | total s | frames/s | moving frames/s | laser | sfm | "
        "analysis | model | laser / decode (CPU) | cores busy |"
    )
    lines = [head, "|" + "---|" * 11]
    for r in rows:
        t = r.timings
        share = [f"{100 * t[k] / t['total']:.0f} %" for k in ("laser", "sfm", "analysis", "model")]
        lines.append(
            f"| {r.name} | {r.frames} ({r.moving}) | {t['total']:.1f} | {r.frames / t['total']:.2f} | "
            f"{r.moving / t['total']:.2f} | " + " | ".join(share)
            + f" | {t['laser'] / r.decode_s:.2f} ({'-' if r.cpu_ratio is None else f'{r.cpu_ratio:.2f}'})"
            + f" | {r.cores_busy:.2f} |"
        )
    return "\n".join(lines)


def _per_stage(t: dict[str, float], n: int, stationary: int) -> str:
    """Each stage's seconds, share of the total and seconds per moving frame (the frames
    a run pays for: a stationary frame costs little, so bend's rest frames flatter it)."""
    moving = max(n - stationary, 1)
    parts = [
        f"{k} {t[k]:.1f} s ({100 * t[k] / t['total']:.0f} %, {t[k] / moving:.3f} s/moving frame)"
        for k in ("laser", "sfm", "analysis", "model")
    ]
    return (
        f"per stage ({n} frames, {stationary} stationary, {moving} moving): " + "; ".join(parts)
        + f"; total {t['total'] / moving:.3f} s/moving frame, {moving / t['total']:.2f} moving frames/s"
    )


def _same_run(path: Path, scenario) -> bool:
    """Whether ``path`` holds a dataset of ``scenario``'s frame count and image size."""
    if not (path / "rig.yaml").is_file():
        return False
    try:
        dataset = open_dataset(path)
    except OmnipipeError:  # anything unreadable is simulated again
        return False
    cam = scenario.rig.camera
    same = len(dataset) == scenario.frames
    return same and (dataset.rig.camera.width, dataset.rig.camera.height) == (cam.width, cam.height)


if __name__ == "__main__":
    main()
