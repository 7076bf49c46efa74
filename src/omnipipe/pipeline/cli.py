"""``omnipipe reconstruct`` and ``omnipipe demo``."""

from __future__ import annotations

import argparse
import sys
import time
from collections.abc import Callable
from pathlib import Path
from typing import TYPE_CHECKING

from omnipipe import cli_values
from omnipipe.output import atomic_output_dir, prepare_output_dir
from omnipipe.pipeline import ReconstructConfig, run, table_one, write
from omnipipe.progress import HonestBar, ProgressFactory, RunEstimate

if TYPE_CHECKING:
    from omnipipe.dataset import Dataset
    from omnipipe.pipeline.checkpoint import Checkpoints

# Progress bars that are drawn and not yet finished, oldest first.
_OPEN_BARS: list[HonestBar] = []


def close_progress_bars() -> None:
    """Close every unfinished progress bar, so that the next line on stderr (an error
    message) starts on a line of its own instead of after a half-drawn bar."""
    while _OPEN_BARS:
        _OPEN_BARS.pop().close()


def _progress(quiet: bool) -> ProgressFactory:
    """Progress factory ``(stage, total) -> tick(done)`` drawing one bar per stage (or
    inner step: bundle windows, centreline stations, ...), whose rate and ETA are
    measured from its first tick on, and after it the whole run's elapsed and
    remaining time (:mod:`omnipipe.progress`).

    A new stage's bar first closes any bar still open (a stage that stopped early);
    :func:`close_progress_bars` closes the rest when a run fails.
    """
    run = RunEstimate()

    def factory(stage: str, total: int) -> Callable[[int], None]:
        close_progress_bars()
        run.bar_started(stage)
        bar = HonestBar(
            total=total,
            desc=f"{stage:>10}",
            unit=_UNITS.get(stage, "step"),
            disable=quiet,
            leave=True,
            file=sys.stderr,
            smoothing=0,
        )
        bar.set_postfix_str(run.line(None), refresh=False)
        _OPEN_BARS.append(bar)

        def tick(done: int) -> None:
            if bar.disable or bar not in _OPEN_BARS:  # quiet, or done already
                return
            bar.honest.update(done)  # (again in update: the same time, no change)
            bar.set_postfix_str(run.line(bar.honest.remaining_s()), refresh=False)
            bar.update(done - bar.n)
            if done >= total:
                bar.close()
                if bar in _OPEN_BARS:
                    _OPEN_BARS.remove(bar)

        return tick

    return factory


_UNITS = {
    "laser": "frame", "sfm": "frame", "bundle": "step", "centreline": "station",
    "mesh": "image", "model": "station", "defects": "pass",
}


def _add_knobs(p: argparse.ArgumentParser) -> None:
    p.add_argument("--config", help="YAML file with sections laser, sfm, model, analysis, report")
    p.add_argument(
        "--features",
        type=cli_values.whole("--features", 16, 100_000),
        help="SIFT features per frame (sfm.features.max_features, 16-100000)",
    )
    p.add_argument(
        "--keyframe-parallax",
        type=cli_values.number("--keyframe-parallax", 0.0, 90.0, open_lo=True, unit="deg"),
        metavar="DEG",
        help="sfm keyframe spacing as ray parallax (deg, > 0 and <= 90)",
    )
    p.add_argument("--mesher", help="model.mesher (default: unrolled-delaunay)")
    p.add_argument("--quiet", action="store_true", help="no progress bars")


def add_execution_options(p: argparse.ArgumentParser) -> None:
    """``--workers N`` and ``--scheduler ADDR`` (:mod:`omnipipe.executor`), both checked
    while the command line is parsed (:mod:`omnipipe.cli_values`)."""
    p.add_argument(
        "--workers",
        type=cli_values.workers(),
        metavar="N",
        help="local worker processes for the parallel work, 1 to 4 x the cores (default: "
        "every core; 1: serial; never more than there are tasks)",
    )
    p.add_argument(
        "--scheduler",
        type=cli_values.scheduler,
        metavar="ADDR",
        help="run the parallel work on the Dask cluster whose scheduler is at ADDR "
        "(tcp://HOST:PORT; needs pip install 'omnipipe[dask]')",
    )


def with_execution(config: ReconstructConfig, args: argparse.Namespace) -> ReconstructConfig:
    """``config`` with ``--workers`` / ``--scheduler`` applied (checked: one-line errors;
    a scheduler that does not answer is refused here, before any heavy work)."""
    from dataclasses import replace

    from omnipipe.executor import check_scheduler_reachable, check_workers

    workers = None if args.workers is None else check_workers(args.workers)
    scheduler = None if args.scheduler is None else check_scheduler_reachable(args.scheduler)
    return replace(config, workers=workers, scheduler=scheduler)


def _overrides(args: argparse.Namespace) -> dict[str, dict]:
    out: dict[str, dict] = {}
    if args.features is not None:
        out.setdefault("sfm", {})["features"] = {"max_features": args.features}
    if args.keyframe_parallax is not None:
        sfm = out.setdefault("sfm", {})  # the views' size chooses one of the two
        sfm["keyframe_min_parallax_deg"] = sfm["keyframe_min_parallax_large_deg"] = args.keyframe_parallax
    if args.mesher is not None:
        out.setdefault("model", {})["mesher"] = args.mesher
    return out


def register(sub: argparse._SubParsersAction) -> None:
    """Add the ``reconstruct`` and ``demo`` sub-commands."""
    p = sub.add_parser(
        "reconstruct",
        help="build the measured, textured pipe model from a dataset",
        description="Light section, camera motion, model and measurements of DATASET (a contract "
        "directory, or a video with rig.yaml beside it); writes to OUT: trajectory.txt, points.ply, "
        "points.laz, points.e57, mesh.ply, model.glb, model.obj (+ .mtl, texture), unrolled.png, "
        "report.json, report.html, defects.csv and defects/ (per defect: wall crop and camera "
        "view). Warnings go to stderr; the last line (stdout) says what was measured and what "
        "cannot be trusted.",
    )
    p.add_argument(
        "dataset",
        help="dataset directory, video file, ROS 1/2 bag or MCAP file (rig.yaml beside it)",
    )
    p.add_argument(
        "--topic",
        help="image topic of a ROS bag / MCAP file (sensor_msgs/Image or CompressedImage; "
        "default: its only image topic)",
    )
    p.add_argument(
        "--out", required=True, help="output directory (refused if it exists, unless --force)"
    )
    p.add_argument(
        "--force",
        action="store_true",
        help="replace an earlier omnipipe output in OUT (never a folder holding other files)",
    )
    p.add_argument(
        "--survey",
        metavar="FILE",
        help="survey header YAML (site, asset_id, start_node, direction, ...; default: "
        "survey.yaml beside the dataset if there is one; docs/inspection_coding.md)",
    )
    p.add_argument(
        "--fresh",
        action="store_true",
        help="compute every stage again: ignore (and delete) the checkpoints an interrupted "
        "earlier run into OUT left (by default a rerun with the same dataset, rig and "
        "settings resumes after its last completed stage)",
    )
    _add_knobs(p)
    add_execution_options(p)
    p.set_defaults(func=_reconstruct)

    d = sub.add_parser(
        "demo",
        help="simulate the paper's experiment, reconstruct it and print Table I",
        description="Simulates the paper scenario (1600x1200, ~100 frames), reconstructs it, prints "
        "the paper's Table I against ground truth and writes the report.",
    )
    d.add_argument(
        "--out",
        default="omnipipe-demo",
        help="output directory (default: ./omnipipe-demo); an earlier demo output there is "
        "replaced, any other folder is refused",
    )
    d.add_argument(
        "--quick", action="store_true", help="smaller images and fewer frames (under 2 minutes)"
    )
    d.add_argument("--seed", type=cli_values.seed(), default=0, help="simulation seed")
    d.add_argument("--quiet", action="store_true", help="no progress bars")
    d.set_defaults(func=_demo)


def _reconstruct(args: argparse.Namespace) -> int:
    out = Path(args.out)
    from omnipipe.dataset import open_dataset
    from omnipipe.survey import find_survey

    protect = [args.dataset] + ([args.config] if args.config else [])
    protect += [args.survey] if args.survey else []
    # Recover an interrupted earlier run and refuse before the long run, not after.
    prepare_output_dir(out, force=args.force, protect=protect)
    config = with_execution(ReconstructConfig.from_yaml(args.config, _overrides(args)), args)
    survey = find_survey(args.dataset, args.survey)
    dataset = open_dataset(args.dataset, topic=args.topic)
    bars = _progress(args.quiet)
    checkpoints = open_checkpoints(out, dataset, config, fresh=args.fresh)
    from omnipipe.scratch import scratch_beside

    with scratch_beside(out):  # what waits on disk during the run: beside OUT, removed
        rec = run(config, dataset, bars, checkpoints=checkpoints)
    if survey is not None:
        rec.survey = survey
        rec.summary["survey"] = survey.to_dict()
    write(rec, out, force=args.force, protect=protect, progress=bars)
    for problem in checkpoints.problems:
        print(f"note: {problem}", file=sys.stderr)
    remove_checkpoints(out)  # OUT is in place: nothing left to resume
    *warnings, last = closing_line(rec.summary, out).split("\n")
    for line in warnings:
        print(line, file=sys.stderr)
    print(last)
    return 0


def open_checkpoints(
    out: Path, dataset: Dataset, config: ReconstructConfig, *, fresh: bool
) -> Checkpoints:
    """The checkpoints of a run into ``out`` (:mod:`omnipipe.pipeline.checkpoint`); says
    on stderr which stages a rerun resumes from. ``fresh``: earlier ones deleted."""
    from dataclasses import replace

    from omnipipe.pipeline.checkpoint import Checkpoints, run_key

    # Where the work runs does not change the result: a rerun may choose other workers.
    key = run_key(dataset, replace(config, workers=None, scheduler=None))
    checkpoints = Checkpoints.open(out, key)
    if fresh:
        checkpoints.remove()
        checkpoints = Checkpoints.open(out, key)
    elif checkpoints.saved:
        print(
            f"resuming: {', '.join(checkpoints.saved)} done by an earlier run "
            f"(checkpoints in {checkpoints.folder}; --fresh computes them again)",
            file=sys.stderr,
        )
    return checkpoints


def remove_checkpoints(out: Path) -> None:
    """Delete every checkpoint folder of runs into ``out`` (only what omnipipe wrote)."""
    from omnipipe.pipeline.checkpoint import checkpoint_dirs, remove_checkpoint_dir

    for folder in checkpoint_dirs(out):
        remove_checkpoint_dir(folder)


def closing_line(s: dict, out: Path) -> str:
    """The CLI's last line: where, what was measured, and what cannot be trusted.

    Warnings come first (one line each), so the last line always carries the verdict.
    """
    lines = [f"warning: {w}" for w in s["warnings"]]
    q = s.get("trajectory_quality") or {}
    bad = q.get("unreliable") or []
    if bad:
        frames = sum(u["last_frame"] - u["first_frame"] for u in bad)
        verdict = (
            f"UNRELIABLE motion in {len(bad)} stretch(es), {frames} of {s['frames'] - 1} "
            "frame steps: lengths and positions there are not trustworthy (see report.json "
            "trajectory_quality)"
        )
    else:
        verdict = f"motion checked ({q.get('steps_checked', 0)} of {s['frames'] - 1} frame steps verified)"
    lines.append(
        f"wrote {out}: {s['frames_registered']}/{s['frames']} frames registered, inner diameter "
        f"{_diameter(s)}, {len(s['defects'])} defect(s), {_features(s)}"
        f"{s['timings_s']['total']:.1f} s; {verdict}"
    )
    return "\n".join(lines)


def _diameter(s: dict) -> str:
    """The headline diameter with its 1-sigma, and its range where the run measured a
    non-circular or changing section (report.json's min / max keys)."""
    from omnipipe.report import value_pm

    text = f"{value_pm(s['inner_diameter_mm'], s.get('inner_diameter_sigma_mm'), plain='+-')} mm"
    lo, hi = s.get("inner_diameter_min_mm"), s.get("inner_diameter_max_mm")
    return text if lo is None or hi is None else f"{text} (min {lo:.1f}, max {hi:.1f})"


def _features(s: dict) -> str:
    """The pipe's features by kind ("2 joint, 1 lateral; "), or nothing without any."""
    from collections import Counter

    kinds = Counter(f.get("kind", "?") for f in s.get("features") or [])
    if not kinds:
        return ""
    return "features " + ", ".join(f"{n} {k}" for k, n in sorted(kinds.items())) + "; "


def format_table_one(rows) -> str:
    """Table I as aligned text: measured +- 1 sigma, true, error and error / sigma.

    ``rows``: (name, measured, sigma, true, unit); sigma may be None.
    """
    from omnipipe.report import value_pm

    lines = [f"{'':28s} {'measured':>18s} {'true':>10s} {'error':>8s} {'err/sigma':>9s}"]
    for name, meas, sig, true, unit in rows:
        m = value_pm(meas, sig, plain="+-")
        t = "-" if true is None else f"{true:.2f}"
        e = "" if meas is None or true is None else f"{meas - true:+.2f}"
        z = "" if meas is None or true is None or not sig else f"{(meas - true) / sig:+.1f}"
        lines.append(f"{name:28s} {m:>18s} {t:>10s} {e:>8s} {z:>9s}  {unit}")
    return "\n".join(lines)


def _demo(args: argparse.Namespace) -> int:
    from omnipipe.dataset import open_dataset
    from omnipipe.evaluation import EvaluationConfig, EvaluationInputs
    from omnipipe.evaluation import run as evaluate
    from omnipipe.evaluation.cli import format_result
    from omnipipe.sim import make_scenario
    from omnipipe.sim import run as simulate

    start = time.perf_counter()
    out = Path(args.out)
    # The demo replaces its own earlier output (it carries a manifest), nothing else.
    prepare_output_dir(out, force=True)
    if args.quick:
        scenario = make_scenario("paper", frames=150, size=(800, 600), seed=args.seed)
    else:
        scenario = make_scenario("paper", seed=args.seed)
    print(
        f"simulating the paper's experiment: {scenario.frames} frames, "
        f"{scenario.rig.camera.width}x{scenario.rig.camera.height} -> {out / 'dataset'}"
    )
    # OUT is built whole in a temporary sibling and swapped in at the end: an
    # interrupted demo keeps the previous one.
    with atomic_output_dir(out, force=True) as tmp:
        dataset_dir, rec_dir = tmp / "dataset", tmp / "reconstruction"
        bar = HonestBar(
            total=scenario.frames, desc="render", unit="frame", disable=args.quiet,
            file=sys.stderr, smoothing=0,
        )
        simulate(scenario, dataset_dir, workers=2, progress=lambda d, t: bar.update(d - bar.n))
        bar.close()
        config = ReconstructConfig.default()
        dataset = open_dataset(dataset_dir)
        rec = run(config, dataset, _progress(args.quiet))
        write(rec, rec_dir)
        # The evaluation reads the written outputs (as `omnipipe evaluate` does); the
        # report is then rewritten with Table I in it.
        result = evaluate(EvaluationConfig(), EvaluationInputs(rec_dir, dataset_dir))
        ev = result.to_dict()
        write(rec, rec_dir, force=True, evaluation=ev)
    rec_dir = out / "reconstruction"
    print()
    print("Table I (paper Sec. VII) on the simulated pipe:")
    print(format_table_one(table_one(rec.summary, ev)))
    print()

    print(format_result(result))
    print(f"\nreport: {rec_dir / 'report.html'}  (total {time.perf_counter() - start:.0f} s)")
    return 0
