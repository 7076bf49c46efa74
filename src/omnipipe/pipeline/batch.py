"""``omnipipe batch``: many inspection runs reconstructed over one executor.

Each run (a dataset directory, video or bag) is one task on the executor
(:mod:`omnipipe.executor`: local processes, or a Dask cluster with ``--scheduler``);
inside a task the run is reconstructed serially. The tasks return their
:class:`~omnipipe.pipeline.Reconstruction` to this process, which writes them in the
order given, one folder each, ``DIR/NAME/`` (the same files as ``omnipipe reconstruct``),
plus ``DIR/index.html`` and ``DIR/index.json`` listing every run with its inner
diameter +- 1 sigma, defect and warning counts and status. A run that fails (bad
dataset, a stage that cannot proceed) is listed with its one-line error and does not
stop the others; the exit code is 1 if any failed.

DIR is one omnipipe output (:mod:`omnipipe.output`): built in a temporary sibling,
swapped in at the end with a manifest; ``--force`` replaces only an earlier omnipipe
output. On a cluster the workers must read the datasets at the same paths (a shared
file system); the outputs are written here.
"""

from __future__ import annotations

import argparse
import html
import json
import re
import sys
from collections.abc import Callable, Sequence
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Any

from omnipipe.errors import OmnipipeError

HELP = "reconstruct many inspection runs over one executor, with an index.html"


@dataclass(frozen=True)
class BatchTask:
    """One run to reconstruct (picklable: sent to a worker).

    Attributes:
        dataset: the run's dataset directory, video or bag file.
        config: stage settings (its executor fields are ignored: a task runs serially).
    """

    dataset: str
    config: Any


@dataclass
class TaskResult:
    """What a worker sends back: the reconstruction, or the run's one-line error."""

    reconstruction: Any = None
    error: str | None = None


@dataclass
class RunOutcome:
    """One line of the batch index.

    Attributes:
        name: the run's output folder in DIR.
        dataset: the dataset as given on the command line.
        error: one-line reason of a failed run, None if it was reconstructed.
        summary: its report.json content (None if it failed).
    """

    name: str
    dataset: str
    error: str | None = None
    summary: dict[str, Any] | None = None

    @property
    def ok(self) -> bool:
        return self.error is None

    def to_dict(self) -> dict[str, Any]:
        """The run's row of index.json (mm; counts)."""
        s = self.summary or {}
        return {
            "name": self.name,
            "dataset": self.dataset,
            "status": "ok" if self.ok else "failed",
            "error": self.error,
            "inner_diameter_mm": s.get("inner_diameter_mm"),
            "inner_diameter_sigma_mm": s.get("inner_diameter_sigma_mm"),
            "defects": None if self.summary is None else len(s.get("defects", [])),
            "warnings": None if self.summary is None else len(s.get("warnings", [])),
            "frames": s.get("frames"),
            "frames_registered": s.get("frames_registered"),
            "time_s": (s.get("timings_s") or {}).get("total"),
        }


def reconstruct_task(task: BatchTask) -> TaskResult:
    """Reconstruct one run serially (runs in a worker). Never raises for a bad run:
    its error comes back as one line."""
    from omnipipe.dataset import open_dataset
    from omnipipe.executor import InlineExecutor
    from omnipipe.pipeline import run
    from omnipipe.survey import find_survey

    try:
        survey = find_survey(task.dataset)
        dataset = open_dataset(task.dataset)
        rec = run(task.config, dataset, executor=InlineExecutor())
        if survey is not None:
            rec.survey = survey
            rec.summary["survey"] = survey.to_dict()
        return TaskResult(reconstruction=rec)
    except OmnipipeError as exc:
        return TaskResult(error=_one_line(str(exc)))
    except Exception as exc:  # a bug: still one line, and the other runs go on
        return TaskResult(error=_one_line(f"internal error ({type(exc).__name__}: {exc})"))


def _one_line(text: str) -> str:
    return " ".join(text.split()) or "failed"


def run_names(datasets: Sequence[str | Path]) -> list[str]:
    """A distinct, file-system-safe folder name per run (its folder or file stem)."""
    names: list[str] = []
    for d in datasets:
        p = Path(d)
        base = p.stem if p.suffix and not p.is_dir() else p.name
        if not base or base in (".", ".."):
            base = Path(p.resolve()).name
        base = re.sub(r"[^A-Za-z0-9._-]+", "_", base).lstrip(".") or "run"
        name, k = base, 2
        while name in names or name in ("index.html", "index.json"):
            name, k = f"{base}-{k}", k + 1
        names.append(name)
    return names


def run_batch(
    datasets: Sequence[str | Path],
    out: str | Path,
    config: Any,
    *,
    force: bool = False,
    protect: Sequence[str | Path] = (),
    progress: Callable[[str, int], Callable[[int], None]] | None = None,
    report: Callable[[RunOutcome], None] | None = None,
) -> list[RunOutcome]:
    """Reconstruct every dataset over the executor of ``config.workers`` /
    ``config.scheduler``; write ``out`` (one folder per run, index.html, index.json).

    Args:
        datasets: the runs, in the order of the index.
        out: the batch output folder.
        config: a :class:`~omnipipe.pipeline.ReconstructConfig` for every run.
        force: replace an earlier omnipipe output in ``out``.
        protect: further inputs (config file) ``out`` may not be or hold.
        progress: progress factory ``(stage, total) -> tick(done)`` (bar ``runs``).
        report: called with each run's outcome as soon as it is written.

    Returns:
        one :class:`RunOutcome` per dataset, in order.

    Raises:
        OutputError: ``out`` may not be written; ConfigError / SchedulerError: the
            executor cannot be opened. A failing run never raises.
    """
    from omnipipe.executor import open_executor, ordered_map
    from omnipipe.output import atomic_output_dir, prepare_output_dir
    from omnipipe.pipeline import write

    datasets = [str(d) for d in datasets]
    protect = [*datasets, *protect]
    out = Path(out)
    prepare_output_dir(out, force=force, protect=protect)  # refuse before the long work
    names = run_names(datasets)
    serial = replace(config, workers=1, scheduler=None)
    tasks = [BatchTask(d, serial) for d in datasets]
    tick = progress("runs", len(tasks)) if progress else None
    outcomes: list[RunOutcome] = []
    with (
        open_executor(config.workers, config.scheduler) as executor,
        atomic_output_dir(out, force=force, protect=protect) as tmp,
    ):
        results = ordered_map(executor, reconstruct_task, tasks)
        for name, dataset, result in zip(names, datasets, results, strict=True):
            outcome = RunOutcome(name, dataset, error=result.error)
            if result.reconstruction is not None:
                try:
                    write(result.reconstruction, tmp / name, protect=[dataset])
                    outcome.summary = result.reconstruction.summary
                except OmnipipeError as exc:
                    outcome.error = _one_line(str(exc))
            outcomes.append(outcome)
            if report:
                report(outcome)
            if tick:
                tick(len(outcomes))
        rows = [o.to_dict() for o in outcomes]
        (tmp / "index.json").write_text(json.dumps({"runs": rows}, indent=1), encoding="utf-8")
        (tmp / "index.html").write_text(index_html(outcomes), encoding="utf-8")
    return outcomes


def _fmt(value: Any, digits: int = 2) -> str:
    return "-" if value is None else f"{value:.{digits}f}"


def index_html(outcomes: Sequence[RunOutcome]) -> str:
    """A self-contained HTML page listing every run (links to each report.html)."""
    failed = sum(not o.ok for o in outcomes)
    rows = []
    for o in outcomes:
        r = o.to_dict()
        name = html.escape(o.name)
        link = f'<a href="{name}/report.html">{name}</a>' if o.ok else name
        diameter = "-"
        if r["inner_diameter_mm"] is not None:
            diameter = _fmt(r["inner_diameter_mm"])
            if r["inner_diameter_sigma_mm"] is not None:
                diameter += f" &plusmn; {_fmt(r['inner_diameter_sigma_mm'])}"
        status = "ok" if o.ok else f"FAILED: {html.escape(o.error or '')}"
        cells = [
            link,
            html.escape(o.dataset),
            diameter,
            "-" if r["defects"] is None else str(r["defects"]),
            "-" if r["warnings"] is None else str(r["warnings"]),
            "-" if r["frames"] is None else f"{r['frames_registered']}/{r['frames']}",
            _fmt(r["time_s"], 1),
            status,
        ]
        cls = "ok" if o.ok else "failed"
        rows.append(f'<tr class="{cls}">' + "".join(f"<td>{c}</td>" for c in cells) + "</tr>")
    head = "".join(
        f"<th>{h}</th>"
        for h in (
            "run",
            "dataset",
            "inner diameter (mm, &plusmn; 1 sigma)",
            "defects",
            "warnings",
            "frames registered",
            "time (s)",
            "status",
        )
    )
    return (
        "<!DOCTYPE html>\n<html><head><meta charset='utf-8'><title>omnipipe batch</title>"
        "<style>body{font-family:sans-serif;margin:2em}table{border-collapse:collapse}"
        "td,th{border:1px solid #bbb;padding:4px 8px;text-align:left}"
        "tr.failed td{background:#fdd}</style></head><body>"
        f"<h1>omnipipe batch: {len(outcomes)} runs, {failed} failed</h1>"
        f"<table><thead><tr>{head}</tr></thead><tbody>{''.join(rows)}</tbody></table>"
        "</body></html>\n"
    )


def register(sub: argparse._SubParsersAction) -> None:
    """Add the ``batch`` sub-command."""
    from omnipipe.pipeline.cli import _add_knobs, add_execution_options

    p = sub.add_parser(
        "batch",
        help=HELP,
        description="Reconstructs every RUN (dataset directory, video or bag; rig.yaml beside "
        "it) as one task of the executor, writes DIR/NAME/ per run (the outputs of omnipipe "
        "reconstruct) and DIR/index.html + index.json listing them. A failed run is listed "
        "with its error and does not stop the others; exit code 1 if any failed.",
    )
    p.add_argument("runs", nargs="+", metavar="RUN", help="dataset directories, videos or bags")
    p.add_argument(
        "--out", required=True, help="batch output folder (refused if it exists, unless --force)"
    )
    p.add_argument(
        "--force",
        action="store_true",
        help="replace an earlier omnipipe output in OUT (never a folder holding other files)",
    )
    _add_knobs(p)
    add_execution_options(p)
    p.set_defaults(func=_batch)


def _batch(args: argparse.Namespace) -> int:
    from omnipipe.pipeline import ReconstructConfig
    from omnipipe.pipeline.cli import _overrides, with_execution

    config = with_execution(ReconstructConfig.from_yaml(args.config, _overrides(args)), args)
    protect = [args.config] if args.config else []

    def say(o: RunOutcome) -> None:
        if args.quiet:
            return
        r = o.to_dict()
        if o.ok:
            line = (
                f"ok      {o.name}: inner diameter {_fmt(r['inner_diameter_mm'])} +- "
                f"{_fmt(r['inner_diameter_sigma_mm'])} mm, {r['defects']} defect(s), "
                f"{r['warnings']} warning(s)"
            )
        else:
            line = f"FAILED  {o.name}: {o.error}"
        print(line, flush=True)

    outcomes = run_batch(
        args.runs,
        args.out,
        config,
        force=args.force,
        protect=protect,
        report=say,  # one line per run as it is written: the batch's progress
    )
    failed = [o.name for o in outcomes if not o.ok]
    print(
        f"wrote {args.out}: {len(outcomes) - len(failed)} of {len(outcomes)} runs reconstructed "
        f"(index: {Path(args.out) / 'index.html'})"
    )
    if failed:
        print(
            f"omnipipe batch: error: {len(failed)} of {len(outcomes)} runs failed: "
            f"{', '.join(failed)}",
            file=sys.stderr,
        )
        return 1
    return 0
