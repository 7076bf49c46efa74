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
swapped in at the end with a manifest, so a kill, Ctrl-C or SIGTERM at any moment
leaves the earlier DIR (and the workers die with the batch, :mod:`omnipipe.executor`).
``--force`` replaces only an earlier omnipipe output, and a run's earlier folder only
with a successful new one: a run that fails keeps its earlier folder (status
``stale``, with its error); when no run succeeds, DIR is left as it was. On a cluster
the workers must read the datasets at the same paths (a shared file system); the
outputs are written here.
"""

from __future__ import annotations

import argparse
import html
import json
import os
import re
import shutil
import sys
import time
from collections.abc import Callable, Iterator, Sequence
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Any

from omnipipe.errors import OmnipipeError, one_line

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
        summary: the report.json content of the run's folder (None if it has none).
        kept_from: for a failed run whose earlier output (from the previous batch in
            DIR) is kept: when that output was written (UTC, ISO); None otherwise.
        written_utc: when the run's folder was written (UTC, ISO), None if it has none.
    """

    name: str
    dataset: str
    error: str | None = None
    summary: dict[str, Any] | None = None
    kept_from: str | None = None
    written_utc: str | None = None

    @property
    def ok(self) -> bool:
        return self.error is None

    @property
    def status(self) -> str:
        """``ok``; ``stale`` (failed now, its earlier output kept); or ``failed``."""
        if self.ok:
            return "ok"
        return "stale" if self.kept_from is not None else "failed"

    def to_dict(self) -> dict[str, Any]:
        """The run's row of index.json (mm; counts)."""
        s = self.summary or {}
        return {
            "name": self.name,
            "dataset": self.dataset,
            "status": self.status,
            "error": self.error,
            "written_utc": self.written_utc,
            "inner_diameter_mm": s.get("inner_diameter_mm"),
            "inner_diameter_sigma_mm": s.get("inner_diameter_sigma_mm"),
            "defects": None if self.summary is None else len(s.get("defects", [])),
            "warnings": None if self.summary is None else len(s.get("warnings", [])),
            "frames": s.get("frames"),
            "frames_registered": s.get("frames_registered"),
            "time_s": (s.get("timings_s") or {}).get("total"),
        }


@dataclass(frozen=True)
class PreviousRun:
    """A run's complete folder in the batch output that is about to be replaced.

    Attributes:
        root: the earlier batch output (DIR).
        name: the run's folder in it.
        files: the files of the folder, relative to ``root`` (from its manifest).
        summary: its report.json.
        written_utc: when it was written.
    """

    root: Path
    name: str
    files: tuple[str, ...]
    summary: dict[str, Any]
    written_utc: str


@dataclass
class BatchResult:
    """What ``run_batch`` did.

    Attributes:
        outcomes: one per dataset, in order.
        replaced: False when no run succeeded and DIR held an earlier output, which is
            then left exactly as it was (nothing written).
    """

    outcomes: list[RunOutcome]
    replaced: bool = True


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
        return TaskResult(error=one_line(str(exc)) or "failed")
    except Exception as exc:  # a bug: still one line, and the other runs go on
        return TaskResult(error=one_line(f"internal error ({type(exc).__name__}: {exc})"))


_SAFE_NAME = re.compile(r"[A-Za-z0-9_-][A-Za-z0-9._-]*")


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


def previous_runs(out: str | Path) -> dict[str, PreviousRun]:
    """The runs of an earlier batch output ``out`` whose folders are complete (listed
    ok or stale in its index.json, every file its manifest lists present), by name.

    Nothing is trusted that the manifest does not list; a damaged index gives {}.
    """
    from omnipipe.output import read_manifest

    root = Path(out)
    manifest = read_manifest(root)
    if manifest is None or "index.json" not in manifest.files:
        return {}
    try:
        rows = json.loads((root / "index.json").read_text(encoding="utf-8"))["runs"]
    except (OSError, ValueError, KeyError, TypeError):
        return {}
    found: dict[str, PreviousRun] = {}
    for row in rows if isinstance(rows, list) else []:
        name = row.get("name") if isinstance(row, dict) else None
        if not isinstance(name, str) or not _SAFE_NAME.fullmatch(name):
            continue
        if row.get("status") not in ("ok", "stale") or (root / name).is_symlink():
            continue
        files = tuple(sorted(f for f in manifest.files if f.startswith(f"{name}/")))
        if f"{name}/report.json" not in files:
            continue
        if not all(os.path.isfile(root / f) and not os.path.islink(root / f) for f in files):
            continue
        try:
            summary = json.loads((root / name / "report.json").read_text(encoding="utf-8"))
        except (OSError, ValueError):
            continue
        written = row.get("written_utc") or manifest.written_utc
        found[name] = PreviousRun(root, name, files, summary, str(written))
    return found


def keep_previous(run: PreviousRun, dest_root: Path) -> None:
    """Put the earlier folder of ``run`` into the new output ``dest_root`` unchanged:
    hard links (no copy, no change to the earlier output), copies where the file system
    has none."""
    for rel in run.files:
        dst = dest_root / rel
        dst.parent.mkdir(parents=True, exist_ok=True)
        try:
            os.link(run.root / rel, dst, follow_symlinks=False)
        except OSError:
            shutil.copy2(run.root / rel, dst, follow_symlinks=False)


class _NothingReplaced(Exception):
    """No run succeeded: the batch output is left as it was (the temporary one removed)."""


def run_batch(
    datasets: Sequence[str | Path],
    out: str | Path,
    config: Any,
    *,
    force: bool = False,
    protect: Sequence[str | Path] = (),
    progress: Callable[[str, int], Callable[[int], None]] | None = None,
    report: Callable[[RunOutcome], None] | None = None,
) -> BatchResult:
    """Reconstruct every dataset over the executor of ``config.workers`` /
    ``config.scheduler``; write ``out`` (one folder per run, index.html, index.json).

    ``out`` is replaced as one omnipipe output (:mod:`omnipipe.output`: built aside,
    swapped in whole; a kill or Ctrl-C at any moment keeps the earlier one). With
    ``force`` and an earlier batch in ``out``: a run that fails keeps its earlier folder
    (status ``stale`` in the index, with this time's error); when no run succeeds,
    ``out`` is left exactly as it was.

    Args:
        datasets: the runs, in the order of the index.
        out: the batch output folder.
        config: a :class:`~omnipipe.pipeline.ReconstructConfig` for every run.
        force: replace an earlier omnipipe output in ``out``.
        protect: further inputs (config file) ``out`` may not be or hold.
        progress: progress factory ``(stage, total) -> tick(done)`` (bar ``runs``).
        report: called with each run's outcome as soon as it is written.

    Returns:
        the outcome of every dataset, in order, and whether ``out`` was replaced.

    Raises:
        OutputError: ``out`` may not be written; ConfigError / SchedulerError: the
            executor cannot be opened. A failing run never raises.
    """
    from omnipipe.executor import open_executor
    from omnipipe.output import atomic_output_dir, prepare_output_dir, read_manifest

    datasets = [str(d) for d in datasets]
    protect = [*datasets, *protect]
    out = Path(out)
    prepare_output_dir(out, force=force, protect=protect)  # refuse before the long work
    had_output = read_manifest(out) is not None
    previous = previous_runs(out) if force else {}
    names = run_names(datasets)
    serial = replace(config, workers=1, scheduler=None)
    tasks = [BatchTask(d, serial) for d in datasets]
    tick = progress("runs", len(tasks)) if progress else None
    outcomes: list[RunOutcome] = []
    try:
        with (
            open_executor(config.workers, config.scheduler, tasks=len(tasks)) as executor,
            atomic_output_dir(out, force=force, protect=protect) as tmp,
        ):
            for outcome in _write_runs(executor, tasks, names, previous, tmp):
                outcomes.append(outcome)
                if report:
                    report(outcome)
                if tick:
                    tick(len(outcomes))
            if had_output and not any(o.ok for o in outcomes):
                raise _NothingReplaced()
            rows = [o.to_dict() for o in outcomes]
            index = json.dumps({"runs": rows}, indent=1)
            (tmp / "index.json").write_text(index, encoding="utf-8")
            (tmp / "index.html").write_text(index_html(outcomes), encoding="utf-8")
    except _NothingReplaced:
        return BatchResult(outcomes, replaced=False)
    return BatchResult(outcomes)


def _write_runs(
    executor: Any,
    tasks: Sequence[BatchTask],
    names: Sequence[str],
    previous: dict[str, PreviousRun],
    tmp: Path,
) -> Iterator[RunOutcome]:
    """Each run's outcome as its folder is written into ``tmp``: the new reconstruction,
    or for a failed run its earlier folder (``previous``), kept."""
    from omnipipe.executor import describe, ordered_map
    from omnipipe.pipeline import write

    # Each run is one task of the batch's executor and runs serially inside its worker:
    # report.json says so (not the worker's own inline executor).
    batch_executor = describe(executor) | {"per_run": "one task of the batch, serial in its worker"}
    results = ordered_map(executor, reconstruct_task, tasks)
    for name, task, result in zip(names, tasks, results, strict=True):
        outcome = RunOutcome(name, task.dataset, error=result.error)
        if result.reconstruction is not None:
            result.reconstruction.summary["executor"] = batch_executor
            try:
                write(result.reconstruction, tmp / name, protect=[task.dataset])
                outcome.summary = result.reconstruction.summary
                outcome.written_utc = _utc_now()
            except OmnipipeError as exc:
                outcome.error = one_line(str(exc))
        result.reconstruction = None  # not kept once written: bounded memory
        if outcome.error is not None and name in previous:
            earlier = previous[name]
            if os.path.lexists(tmp / name):  # a write that failed half-way
                shutil.rmtree(tmp / name)
            keep_previous(earlier, tmp)
            outcome.summary = earlier.summary
            outcome.kept_from = outcome.written_utc = earlier.written_utc
        yield outcome


def _utc_now() -> str:
    return time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime())


def _fmt(value: Any, digits: int = 2) -> str:
    return "-" if value is None else f"{value:.{digits}f}"


_INDEX_STYLE = (
    "<style>body{font-family:system-ui,sans-serif;margin:2em}table{border-collapse:collapse}"
    "td,th{border:1px solid #bbb;padding:4px 8px;text-align:left;vertical-align:top}"
    "th{background:#eee}tr.failed td{background:#fdd}tr.stale td{background:#ffd}"
    ".warn{color:#a40}.small{font-size:.85em;color:#444}ul{margin:0;padding-left:1.1em}</style>"
)
_INDEX_COLUMNS = (
    "run",
    "site / asset",
    "dataset",
    "inner diameter (mm, &plusmn; 1 sigma)",
    "defects",
    "warnings",
    "frames registered",
    "time (s)",
    "executor",
    "status",
)


def _survey_cell(s: dict[str, Any]) -> str:
    """Site, asset, nodes and date of a run's survey header, or '-'."""
    sv = s.get("survey") or {}
    parts = [
        f"{label}{html.escape(str(sv[key]))}"
        for key, label in (
            ("site", ""), ("asset_id", "asset "), ("start_node", "from "), ("end_node", "to "),
            ("direction", ""), ("date", ""),
        )
        if sv.get(key) is not None
    ]
    return "<br>".join(parts) if parts else "-"


def _defects_cell(s: dict[str, Any]) -> str:
    """The run's defects, one line each: kind, height, clock position and flags."""
    from omnipipe.contract import Defect
    from omnipipe.report.deliverable import defect_rows
    from omnipipe.survey import FIELDS, Survey

    entries = s.get("defects") or []
    if not entries:
        return "none"
    sv = s.get("survey")
    try:
        survey = Survey(**{k: v for k, v in sv.items() if k in FIELDS}) if isinstance(sv, dict) else None
        rows = defect_rows([Defect.from_contract(e) for e in entries], s, survey)
    except (KeyError, TypeError, ValueError):
        return str(len(entries))
    items = []
    for row in rows:
        v, d = row.values, row.defect
        flags = f" <span class='warn'>{html.escape(v['flags'])}</span>" if v["flags"] else ""
        items.append(
            f"<li>{html.escape(d.kind)} {'&ge; ' if d.truncated else ''}{d.height_mm:.1f} mm at "
            f"{v['clock']}, {v['distance_start_m']} m{flags}</li>"
        )
    return f"{len(entries)}<ul class='small'>{''.join(items)}</ul>"


def _warnings_cell(s: dict[str, Any] | None) -> str:
    if s is None:
        return "-"
    warnings = s.get("warnings") or []
    if not warnings:
        return "0"
    items = "".join(f"<li>{html.escape(str(w))}</li>" for w in warnings[:8])
    more = f"<li>... {len(warnings) - 8} more in the run's report</li>" if len(warnings) > 8 else ""
    return f"{len(warnings)}<ul class='small warn'>{items}{more}</ul>"


def _executor_cell(s: dict[str, Any]) -> str:
    ex = s.get("executor") or {}
    if not isinstance(ex, dict) or not ex:
        return "-"
    return html.escape(f"{ex.get('kind')} x {ex.get('workers')}")


def index_html(outcomes: Sequence[RunOutcome]) -> str:
    """A self-contained HTML page listing every run (links to each report.html; a stale
    run's row says that its output is the earlier one, and why the new run failed): its
    survey header, inner diameter, defects (kind, height, clock, distance, flags), warnings
    and the executor it ran on."""
    failed = sum(not o.ok for o in outcomes)
    stale = sum(o.status == "stale" for o in outcomes)
    rows = []
    for o in outcomes:
        r = o.to_dict()
        s = o.summary or {}
        name = html.escape(o.name)
        link = f'<a href="{name}/report.html">{name}</a>' if o.summary is not None else name
        diameter = "-"
        if r["inner_diameter_mm"] is not None:
            diameter = _fmt(r["inner_diameter_mm"])
            if r["inner_diameter_sigma_mm"] is not None:
                diameter += f" &plusmn; {_fmt(r['inner_diameter_sigma_mm'])}"
        status = {
            "ok": "ok",
            "stale": f"STALE: the output of {html.escape(o.kept_from or '')}, kept because "
            f"this run FAILED: {html.escape(o.error or '')}",
            "failed": f"FAILED: {html.escape(o.error or '')}",
        }[o.status]
        cells = [
            link,
            _survey_cell(s),
            html.escape(o.dataset),
            diameter,
            "-" if o.summary is None else _defects_cell(s),
            _warnings_cell(o.summary),
            "-" if r["frames"] is None else f"{r['frames_registered']}/{r['frames']}",
            _fmt(r["time_s"], 1),
            _executor_cell(s),
            status,
        ]
        rows.append(f'<tr class="{o.status}">' + "".join(f"<td>{c}</td>" for c in cells) + "</tr>")
    head = "".join(f"<th>{h}</th>" for h in _INDEX_COLUMNS)
    n_defects = sum(len((o.summary or {}).get("defects") or []) for o in outcomes)
    return (
        "<!DOCTYPE html>\n<html><head><meta charset='utf-8'><title>omnipipe batch</title>"
        f"{_INDEX_STYLE}</head><body>"
        f"<h1>omnipipe batch: {len(outcomes)} runs, {failed} failed"
        f"{f' ({stale} showing an earlier, stale output)' if stale else ''}</h1>"
        f"<p>{n_defects} defect(s) in all; clock positions as each run's report states "
        "(12:00 = image up where a run has no gravity reference); distances in m from each "
        "run's start node, or its first measured ring without survey.yaml.</p>"
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
        if not args.quiet:
            print(_outcome_line(o), flush=True)

    result = run_batch(
        args.runs,
        args.out,
        config,
        force=args.force,
        protect=protect,
        report=say,  # one line per run as it is written: the batch's progress
    )
    outcomes = result.outcomes
    failed = [o.name for o in outcomes if not o.ok]
    if not result.replaced:
        print(
            f"omnipipe batch: error: {len(failed)} of {len(outcomes)} runs failed; nothing "
            f"replaced: {args.out} keeps its earlier output",
            file=sys.stderr,
        )
        return 1
    stale = [o.name for o in outcomes if o.status == "stale"]
    print(
        f"wrote {args.out}: {len(outcomes) - len(failed)} of {len(outcomes)} runs reconstructed"
        + (f", {len(stale)} failed run(s) keep their earlier output (stale)" if stale else "")
        + f" (index: {Path(args.out) / 'index.html'})"
    )
    if failed:
        print(
            f"omnipipe batch: error: {len(failed)} of {len(outcomes)} runs failed: "
            f"{', '.join(failed)}",
            file=sys.stderr,
        )
        return 1
    return 0


def _outcome_line(o: RunOutcome) -> str:
    """The run's line on stdout as it is written."""
    r = o.to_dict()
    if o.ok:
        return (
            f"ok      {o.name}: inner diameter {_fmt(r['inner_diameter_mm'])} +- "
            f"{_fmt(r['inner_diameter_sigma_mm'])} mm, {r['defects']} defect(s), "
            f"{r['warnings']} warning(s)"
        )
    if o.status == "stale":
        return f"STALE   {o.name}: failed ({o.error}); kept its earlier output of {o.kept_from}"
    return f"FAILED  {o.name}: {o.error}"
