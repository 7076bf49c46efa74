"""Does reconstruct's cost grow with the length of the run? frames/s and peak RSS per run length.

    python benchmarks/bench_scaling.py [--frames 150 600 2400] [--scenario paper]
        [--size 400x300] [--workers N] [--cache DIR] [--video [--decoded-png]] [--rest N]
        [--write] [--steps]

Simulates one run per length (small images; ``--cache`` keeps them for the next call),
reconstructs each in a fresh process (``omnipipe.pipeline.run``, nothing written) and
prints, per run: frames, wall time, frames/s of the whole run and of each stage, the
CPU seconds of the reconstructing process and its workers (frames per CPU second: the
comparison of the run lengths that a shared machine moves least), and
the peak resident memory of the reconstructing process and of its largest worker.
With ``--video`` each run is also made into an MJPG video (cv2.VideoWriter, from its
PNG frames) and reconstructed too; ``--decoded-png`` adds the video's frames decoded
back to PNGs (the same pixels as the video: the fair comparison of the two inputs,
JPEG's artefacts change the reconstruction's work). ``--rest N``
replaces the scenario's gait by 6-frame strokes each followed by N frames at rest. The
last lines compare each longer run of each input with its shortest (issue 13's
acceptance: frames/s within 20 %, peak RSS within 30 % from 600 to 2400 frames; issue
27: within 20 % and 10 % from 1,000 to 10,000). ``--steps`` also prints the peak
resident memory of the reconstructing process during each step (VmRSS sampled every
10 ms by a thread; the steps are the functions of :data:`STEPS`, timed by wrapping them)
per run length: where the memory that grows with the run is held. A run in which numba
compiled omnipipe's kernels (its cache cold for them, as after a checkout or an edit of a
kernels module) is measured again: the compiler's memory stays in the process (the
windowed bundle adjustment of a long run, which a short run does not use, compiled its
kernels at the camera motion's high-water mark). It only measures.
"""

from __future__ import annotations

import argparse
import json
import resource
import shutil
import subprocess
import sys
import tempfile
import time
from pathlib import Path


def _peak_rss_mb() -> float:
    """This process's peak resident memory (MiB): VmHWM, its own since its exec.
    (``ru_maxrss`` keeps the forking parent's: a bench that had just simulated a run
    passed its own 585 MB on to a 24-frame child that peaked at 263 MB.)"""
    with open("/proc/self/status", encoding="ascii") as fh:
        for line in fh:
            if line.startswith("VmHWM:"):
                return int(line.split()[1]) / 1024.0
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0  # KiB -> MiB


STEPS = (
    ("omnipipe.pipeline.run_state", ("decode", "camera_motion", "analyse", "build_model")),
    ("omnipipe.pipeline.reconstruct", ("report_summary", "_defect_views")),
    (
        "omnipipe.sfm.pipeline",
        ("follow_keyframes", "chain_steps", "_adjusted_and_checked", "run_length", "resect_pending", "_result"),
    ),
    ("omnipipe.analysis", ("run",)),
    (
        "omnipipe.analysis.stage",
        ("fit_axis", "recentred_line", "find_features", "measure_wall", "with_ring_terms", "with_water",
         "sections_and_headline"),
    ),
    ("omnipipe.model.stage", ("mesh_unrolled", "orient_towards_axis", "choose_sources", "flat_field", "textured_mesh")),
    ("omnipipe.model.export", ("write_ply", "write_laz", "write_e57", "write_glb", "write_obj")),
    ("omnipipe.report", ("run",)),
)
"""(module, functions) whose calls ``--steps`` measures: the pipeline's stages, the camera
motion's passes, the analysis (``analysis.run``), the model stage's steps, the writers and the report (``report.run``)."""


class _StepPeaks:
    """Peak VmRSS (MiB) of this process while each of :data:`STEPS` runs (a step inside
    another counts for both; between the outermost ones as ``after STEP``), sampled every
    10 ms by a daemon thread, the part of it that was file-backed pages (RssFile: the
    run's scratch mapped) at that peak, and where the main thread was then; and the steps
    running when the process's high-water mark (VmHWM) was last seen to rise (a peak
    shorter than a sample's interval, or while the sampler waited for the GIL, is caught
    there; the step is the one running at the next sample)."""

    def __init__(self, held: tuple[str, ...] = ()) -> None:
        import functools
        import importlib
        import threading

        self.peaks: dict[str, float] = {}
        self.files: dict[str, float] = {}
        self.where: dict[str, str] = {}
        self.hwm: dict[str, float] = {}  # the process's high-water mark (VmHWM) when it last rose within the step
        self._last_hwm = 0.0
        self.held_at = held
        self.held: dict[str, list[str]] = {}
        self.tag = "start"
        self.active: tuple[str, ...] = ()  # the steps running, outermost first (nested: each)
        self._main = threading.get_ident()
        for module, names in STEPS:
            mod = importlib.import_module(module)
            for name in names:
                label = f"{module.rsplit('.', 1)[-1]}.{name}" if name == "run" else name
                setattr(mod, name, functools.wraps(getattr(mod, name))(self._wrap(getattr(mod, name), label)))
        threading.Thread(target=self._sample, daemon=True).start()

    def _wrap(self, f, label: str):
        def wrapped(*a, **k):
            if label in self.held_at and label not in self.held:
                self.held[label] = _held_arrays()
            self.active = (*self.active, label)
            try:
                return f(*a, **k)
            finally:
                self.active = self.active[:-1]
                if not self.active:
                    self.tag = f"after {label}"

        return wrapped

    def _sample(self) -> None:
        while True:
            with open("/proc/self/status", encoding="ascii") as fh:
                kb = {k: int(v.split()[0]) for k, v in (line.split(":", 1) for line in fh) if k in ("VmRSS", "RssFile", "VmHWM")}
            tags, rss = self.active or (self.tag,), kb["VmRSS"] / 1024.0
            hwm = kb.get("VmHWM", 0) / 1024.0
            if hwm > self._last_hwm:  # risen since the last sample (a peak between two samples too)
                self._last_hwm = hwm
                for tag in tags:
                    self.hwm[tag] = hwm
            for tag in tags:
                if rss > self.peaks.get(tag, 0.0):
                    self.peaks[tag], self.files[tag] = rss, kb.get("RssFile", 0) / 1024.0
                    self.where[tag] = self._main_at()
            time.sleep(0.01)

    def _main_at(self) -> str:
        """The main thread's innermost omnipipe lines (at most 3, innermost first) when
        the sample was taken: where a step's peak is held."""
        frame = sys._current_frames().get(self._main)
        out = []
        while frame is not None and len(out) < 3:
            name = frame.f_code.co_filename
            if "omnipipe" in name and "bench_scaling" not in name:
                out.append(f"{name.rsplit('omnipipe/', 1)[-1]}:{frame.f_lineno} {frame.f_code.co_name}")
            frame = frame.f_back
        return " < ".join(out)


def _held_arrays(top: int = 12) -> list[str]:
    """The arrays in this process's memory (not in the run's scratch) that some object
    refers to: their total and the ``top`` largest (MB, dtype, shape, the referrer's type)."""
    import gc

    import numpy as np

    from omnipipe.spill import is_on_disk

    found: dict[int, tuple[int, str]] = {}
    for obj in gc.get_objects():
        for ref in gc.get_referents(obj):
            if not isinstance(ref, np.ndarray) or is_on_disk(ref):
                continue
            base = ref
            while isinstance(base, np.ndarray) and base.base is not None:
                base = base.base
            if isinstance(base, np.ndarray) and id(base) not in found:
                found[id(base)] = (base.nbytes, f"{base.dtype}{base.shape} in {type(obj).__name__}")
    items = sorted(found.values(), reverse=True)
    total = sum(n for n, _ in items) / 2**20
    return [f"total {total:.1f} MB in {len(items)} arrays"] + [f"{n / 2**20:6.1f} MB {what}" for n, what in items[:top]]


def _compiled() -> list[str]:
    """omnipipe's numba kernels this process compiled rather than loaded from numba's
    cache (``module.function``). A compile leaves LLVM's memory in the process (a
    windowed bundle adjustment's first call compiling its kernels: ~60-80 MB more under
    the camera motion's high-water mark, benchmarks/RESULTS.md): such a run's peak is the
    cold cache's, not the run length's."""
    from numba.core.registry import CPUDispatcher

    out = set()
    for name, mod in list(sys.modules.items()):
        if not name.startswith("omnipipe"):
            continue
        for value in list(vars(mod).values()):
            if isinstance(value, CPUDispatcher) and sum(value.stats.cache_misses.values()):
                out.add(f"{value.py_func.__module__}.{value.py_func.__name__}")
    return sorted(out)


def _cpu_s() -> float:
    """CPU seconds (user + system) of this process and its finished child processes."""
    own = resource.getrusage(resource.RUSAGE_SELF)
    kids = resource.getrusage(resource.RUSAGE_CHILDREN)
    return own.ru_utime + own.ru_stime + kids.ru_utime + kids.ru_stime


def _child(
    dataset: str, workers: int | None, write_to: str | None, steps: bool = False, held: tuple[str, ...] = ()
) -> None:
    """Reconstruct ``dataset`` in this process (and write its outputs into ``write_to``)
    and print one JSON line of measurements (``steps``: with each step's peak RSS)."""
    from dataclasses import replace

    peaks = _StepPeaks(held) if steps else None

    from omnipipe.dataset import open_dataset
    from omnipipe.pipeline import ReconstructConfig, run, write

    config = replace(ReconstructConfig.default(), workers=workers)
    t0 = time.perf_counter()
    rec = run(config, open_dataset(dataset))
    wall = time.perf_counter() - t0
    cpu = _cpu_s()  # the run's pool has shut down: its workers are counted
    own = _peak_rss_mb()
    write_s = written = None
    if write_to is not None:
        t1 = time.perf_counter()
        write(rec, Path(write_to) / "out")
        write_s = time.perf_counter() - t1
        written = _peak_rss_mb()
    workers_rss = resource.getrusage(resource.RUSAGE_CHILDREN).ru_maxrss / 1024.0
    s = rec.summary
    print(
        json.dumps(
            {
                "frames": s["frames"],
                "wall_s": wall,
                "cpu_s": cpu,
                "timings_s": s["timings_s"],
                "frames_per_s": s["frames_per_s"],
                "keyframes": s["keyframes"],
                "rss_mb": own,
                "write_s": write_s,
                "rss_with_write_mb": written,
                "worker_rss_mb": workers_rss,
                "executor": s.get("executor"),
                "steps": None if peaks is None else dict(peaks.peaks),
                "steps_file": None if peaks is None else dict(peaks.files),
                "steps_where": None if peaks is None else dict(peaks.where),
                "steps_hwm": None if peaks is None else dict(peaks.hwm),
                "held": None if peaks is None else dict(peaks.held),
                "compiled": _compiled(),
            }
        )
    )


def _dataset(
    cache: Path, scenario: str, frames: int, size: tuple[int, int], seed: int, rest: int | None = None
) -> Path:
    """The simulated run (made once into ``cache``); ``rest``: the gait's frames at rest
    after each stroke of :data:`STROKE_FRAMES` frames (None: the scenario's own gait)."""
    from dataclasses import replace

    from omnipipe.sim import make_scenario
    from omnipipe.sim import run as simulate

    gait = "" if rest is None else f"-rest{rest}"
    path = cache / f"{scenario}{gait}-{frames}-{size[0]}x{size[1]}-s{seed}"
    if not (path / "rig.yaml").is_file():
        t0 = time.perf_counter()
        scene = make_scenario(scenario, frames=frames, size=size, seed=seed)
        if rest is not None:
            scene.motion = replace(
                scene.motion, moving_frames=STROKE_FRAMES, frames_per_cycle=STROKE_FRAMES + rest
            )
        simulate(scene, path, force=True, workers=2)
        print(f"simulated {path.name} in {time.perf_counter() - t0:.0f} s", flush=True)
    return path


STROKE_FRAMES = 6
"""Frames of each stroke with ``--rest`` (the paper gait's head moves for 6 of its 24)."""


def _video(png: Path, decoded_png: bool) -> tuple[Path, Path]:
    """An MJPG video of the PNG dataset ``png`` (rig.yaml beside it) and (``decoded_png``)
    a PNG dataset of the video's decoded frames (made once, kept with the cache)."""
    import cv2

    folder = png.parent / f"{png.name}-mjpg"
    video, decoded = folder / "run.avi", png.parent / f"{png.name}-mjpg-png"
    if not video.is_file():
        folder.mkdir(exist_ok=True)
        shutil.copy(png / "rig.yaml", folder / "rig.yaml")
        names = sorted((png / "frames").glob("*.png"))
        h, w = cv2.imread(str(names[0])).shape[:2]
        part = folder / "run.part.avi"
        # OpenCV's own MJPG writer at quality 100 (the default 95 leaves block artefacts
        # that make every frame a station: 4x the points, another run's work).
        writer = cv2.VideoWriter(
            str(part), cv2.CAP_OPENCV_MJPEG, cv2.VideoWriter_fourcc(*"MJPG"), 8.0, (w, h),
            [cv2.VIDEOWRITER_PROP_QUALITY, 100],
        )
        for name in names:
            writer.write(cv2.imread(str(name)))
        writer.release()
        part.rename(video)
    if decoded_png and not (decoded / "rig.yaml").is_file():
        (decoded / "frames").mkdir(parents=True, exist_ok=True)
        cap = cv2.VideoCapture(str(video))
        lines = []
        for i in range(10**9):
            ok, frame = cap.read()
            if not ok:
                break
            cv2.imwrite(str(decoded / "frames" / f"{i:06d}.png"), frame)
            lines.append(f"{i:06d}.png {i / 8.0:.6f}")
        cap.release()
        (decoded / "timestamps.txt").write_text("\n".join(lines) + "\n", encoding="utf-8")
        shutil.copy(png / "rig.yaml", decoded / "rig.yaml")
    return video, decoded


def _measure(
    path: Path, workers: int | None, write: bool, steps: bool = False, held: tuple[str, ...] = ()
) -> dict | None:
    """Reconstruct ``path`` in a fresh process (``write``: and write its outputs, into a
    temporary folder removed after); its JSON line of measurements, or None."""
    cmd = [sys.executable, __file__, "--child", str(path)]
    if workers is not None:
        cmd += ["--workers", str(workers)]
    if steps:
        cmd += ["--steps"] + (["--held", ",".join(held)] if held else [])
    with tempfile.TemporaryDirectory(prefix="omnipipe-scaling-out-") as out:
        done = subprocess.run(
            cmd + (["--write-to", out] if write else []), capture_output=True, text=True, check=False
        )
    if done.returncode != 0:
        print(f"{path.name}: reconstruct failed: {done.stderr.strip().splitlines()[-1:]}")
        return None
    return json.loads(done.stdout.strip().splitlines()[-1])


def _measure_warm(
    path: Path, workers: int | None, write: bool, steps: bool = False, held: tuple[str, ...] = ()
) -> dict | None:
    """:func:`_measure`, again when numba compiled kernels in that process (its cache was
    cold for them: their compiler's memory is in its peak); the second run loads them."""
    row = _measure(path, workers, write, steps, held)
    if row is not None and row.get("compiled"):
        print(f"{path.name}: numba compiled {len(row['compiled'])} kernels in this run (cold cache: "
              f"peak RSS {row['rss_mb']:.0f} MB; {', '.join(row['compiled'][:4])}...): measured again", flush=True)
        row = _measure(path, workers, write, steps, held)
    return row


def _print_row(kind: str, row: dict) -> None:
    fps = row["frames_per_s"]
    print(
        f"{kind:9s} {row['frames']:5d} frames ({row['keyframes']} keyframes): {row['wall_s']:7.1f} s, "
        f"{fps['total']:6.2f} frames/s (laser {fps['laser']:.1f}, sfm {fps['sfm']:.2f}, "
        f"analysis {fps['analysis']:.1f}, model {fps['model']:.2f}); peak RSS "
        f"{row['rss_mb']:.0f} MB (largest worker {row['worker_rss_mb']:.0f} MB)"
        + (
            f", with writing {row['rss_with_write_mb']:.0f} MB ({row['write_s']:.0f} s); "
            if row.get("write_s") is not None
            else "; "
        )
        + f"{row['executor']}"
        + (f"; {row['cpu_s']:.1f} CPU-s, {row['frames'] / row['cpu_s']:.2f} frames per CPU-s" if row.get("cpu_s") else ""),
        flush=True,
    )


def _compare(kind: str, a: dict, b: dict) -> None:
    dfps = b["frames_per_s"]["total"] / a["frames_per_s"]["total"] - 1
    drss = b["rss_mb"] / a["rss_mb"] - 1
    if a.get("rss_with_write_mb") and b.get("rss_with_write_mb"):
        dw = b["rss_with_write_mb"] / a["rss_with_write_mb"] - 1
        print(f"{kind}: {a['frames']} -> {b['frames']} frames: peak RSS with writing {100 * dw:+.0f} % "
              f"({a['rss_with_write_mb']:.0f} -> {b['rss_with_write_mb']:.0f} MB)")
    print(
        f"{kind}: {a['frames']} -> {b['frames']} frames: frames/s {100 * dfps:+.0f} %, "
        f"peak RSS {100 * drss:+.0f} % ({a['rss_mb']:.0f} -> {b['rss_mb']:.0f} MB, "
        f"{(b['rss_mb'] - a['rss_mb']) / (b['frames'] - a['frames']) * 1024:.1f} KB per frame)"
    )
    if a.get("cpu_s") and b.get("cpu_s"):
        dcpu = (b["frames"] / b["cpu_s"]) / (a["frames"] / a["cpu_s"]) - 1
        print(f"{kind}: {a['frames']} -> {b['frames']} frames: frames per CPU-s {100 * dcpu:+.0f} % "
              f"({a['frames'] / a['cpu_s']:.2f} -> {b['frames'] / b['cpu_s']:.2f}; the wall's frames/s "
              "moves with what else the machine runs, the CPU seconds hardly)")
    for stage in ("laser", "sfm", "analysis", "model"):
        fa, fb = a["frames_per_s"][stage], b["frames_per_s"][stage]
        print(f"  {stage:9s} frames/s {fa:8.2f} -> {fb:8.2f} ({100 * (fb / fa - 1):+.0f} %)")


def _print_steps(kind: str, done: list[dict]) -> None:
    """Each step's peak RSS per run length (MB; in brackets its file-backed part at that
    peak), and the growth per 1,000 frames."""
    if len(done) < 1 or not done[0].get("steps"):
        return
    order = list(done[-1]["steps"])
    print(f"{kind}: peak RSS per step (MB)")
    print(f"  {'step':28s}" + "".join(f"{r['frames']:>13d}" for r in done) + "   MB per 1,000 frames")
    for step in order:
        vals = [r["steps"].get(step) for r in done]
        per = ""
        if len(done) > 1 and vals[0] is not None and vals[-1] is not None:
            per = f"{1000 * (vals[-1] - vals[0]) / (done[-1]['frames'] - done[0]['frames']):+9.1f}"
        files = [(r.get("steps_file") or {}).get(step) for r in done]
        cells = "".join(
            "            -" if v is None else f"{v:7.0f} ({f or 0:3.0f})" for v, f in zip(vals, files, strict=True)
        )
        print(f"  {step:28s}" + cells + "   " + per)
    for step, lines in (done[-1].get("held") or {}).items():
        print(f"{kind}: arrays in memory when {step} began ({done[-1]['frames']} frames)")
        for line in lines:
            print(f"  {line}")
    hwm = done[-1].get("steps_hwm") or {}
    if hwm:  # VmHWM rises within a step between two samples too (a short peak the samples miss)
        top = sorted(hwm.items(), key=lambda kv: -kv[1])[:6]
        print(f"{kind}: steps running when the high-water mark last rose ({done[-1]['frames']} frames): "
              + ", ".join(f"{k} {v:.0f}" for k, v in top))
    where = done[-1].get("steps_where") or {}
    if where:
        print(f"{kind}: where each step peaked ({done[-1]['frames']} frames; innermost omnipipe lines)")
        for step in order:
            print(f"  {step:28s} {where.get(step, '')}")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--frames", type=int, nargs="+", default=[150, 600, 2400])
    parser.add_argument("--scenario", default="paper")
    parser.add_argument("--size", default="400x300", help="WxH")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument(
        "--rest", type=int, default=None,
        help=f"gait: {STROKE_FRAMES}-frame strokes, each followed by REST frames at rest "
        "(default: the scenario's gait)",
    )
    parser.add_argument("--workers", type=int, default=None, help="local processes (default: every core)")
    parser.add_argument("--cache", default=None, help="keep the simulated runs here")
    parser.add_argument("--video", action="store_true", help="also an MJPG video of each run")
    parser.add_argument("--no-png", action="store_true", help="with --video: the video only")
    parser.add_argument(
        "--decoded-png", action="store_true", help="with --video: also the video's frames as PNGs"
    )
    parser.add_argument(
        "--write", action="store_true",
        help="also write each run's outputs (omnipipe.pipeline.write) and its peak RSS with it",
    )
    parser.add_argument(
        "--steps", action="store_true",
        help="also the reconstructing process's peak RSS during each step (pipeline stages, "
        "model steps, writers, report)",
    )
    parser.add_argument(
        "--held", default="",
        help="with --steps: list the arrays in memory when these steps (comma-separated) begin",
    )
    parser.add_argument("--child", default=None, help=argparse.SUPPRESS)
    parser.add_argument("--write-to", default=None, help=argparse.SUPPRESS)
    args = parser.parse_args()
    if args.child:
        _child(args.child, args.workers, args.write_to, args.steps, tuple(filter(None, args.held.split(","))))
        return
    size = tuple(int(v) for v in args.size.split("x"))
    cache = Path(args.cache) if args.cache else Path(tempfile.mkdtemp(prefix="omnipipe-scaling-"))
    cache.mkdir(parents=True, exist_ok=True)
    rows: dict[str, list[dict]] = {"png": [], "mjpg": [], "mjpg-png": []}
    try:
        for n in args.frames:
            path = _dataset(cache, args.scenario, n, size, args.seed, args.rest)  # type: ignore[arg-type]
            inputs = [] if args.no_png else [("png", path)]
            if args.video:
                video, decoded = _video(path, args.decoded_png)
                inputs += [("mjpg", video)] + ([("mjpg-png", decoded)] if args.decoded_png else [])
            for kind, source in inputs:
                row = _measure_warm(source, args.workers, args.write, args.steps, tuple(filter(None, args.held.split(","))))
                if row is not None:
                    rows[kind].append(row)
                    _print_row(kind, row)
        for kind, done in rows.items():
            for later in done[1:]:  # each longer run against the shortest
                _compare(kind, done[0], later)
            _print_steps(kind, done)
    finally:
        if not args.cache:
            shutil.rmtree(cache, ignore_errors=True)


if __name__ == "__main__":
    main()
