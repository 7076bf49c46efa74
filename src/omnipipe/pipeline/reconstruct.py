"""The reconstruction pipeline: dataset in, contract outputs out.

Stages, each a ``run(config, inputs)`` of its own subpackage: ``laser`` (light
section: metric ring points per frame), ``sfm`` (camera motion, metric by the laser),
``model`` (integration, mesh, texture, unrolled wall), ``analysis`` (inner diameter,
ovality, defects) and ``report``. Outputs are written to a temporary directory next
to OUT and moved into place at the end, so a failed or interrupted run never leaves
OUT looking complete.

Here: :func:`run` (every stage on a dataset) and its result :class:`Reconstruction`. In
modules of their own: the settings and the run's log (:mod:`.run_config`), each stage's
call (:mod:`.stage_calls`), the stage sequence with its checkpoints (:mod:`.run_state`),
report.json's content (:mod:`.summary`).
"""

from __future__ import annotations

import json
import time
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Any

from omnipipe.errors import ReconstructionError
from omnipipe.memory import release_freed_memory
from omnipipe.pipeline.run_config import RunLog, no_progress
from omnipipe.pipeline.run_state import stages
from omnipipe.pipeline.summary import report_summary, wall_points
from omnipipe.progress import ProgressFactory

if TYPE_CHECKING:  # imported inside the functions: `omnipipe --help` stays fast
    from concurrent.futures import Executor

    import numpy as np

    from omnipipe.analysis import AnalysisResult
    from omnipipe.contract import Defect, TrajectoryQuality
    from omnipipe.dataset import Dataset
    from omnipipe.model import ModelResult
    from omnipipe.pipeline.checkpoint import Checkpoints
    from omnipipe.pipeline.run_config import ReconstructConfig
    from omnipipe.report import ReportConfig, ReportInputs
    from omnipipe.report.views import DefectView
    from omnipipe.survey import Survey


@dataclass
class Reconstruction:
    """Everything a run produced, before it is written.

    Attributes:
        summary: the report.json content.
        timestamps: (N,) seconds of the registered frames.
        world_from_rig: (N, 4, 4) poses of the registered frames.
        model: the model stage result.
        analysis: the analysis stage result.
        report_config: how report.html is drawn (the ``report`` section of the config).
        frame_index: (N,) 0-based frame index of each registered pose.
        survey: the survey.yaml header, or None.
        defects: the reported defects (the summary's ``defects`` are their
            ``to_contract()``), largest first.
        trajectory_quality: what the camera motion check found (the summary's
            ``trajectory_quality``), or None.
        up_in_rig: (3,) unit up direction in the first registered frame's rig frame
            (imu.txt's accelerometer), or None: no gravity reference.
        up_sigma_rad: its 1-sigma angle (rad).
        defect_views: each defect's camera view (None where no frame sees it).
    """

    summary: dict[str, Any]
    timestamps: np.ndarray
    world_from_rig: np.ndarray
    model: ModelResult
    analysis: AnalysisResult
    report_config: ReportConfig | None = None
    frame_index: np.ndarray | None = None
    survey: Survey | None = None
    defects: list[Defect] = field(default_factory=list)
    trajectory_quality: TrajectoryQuality | None = None
    up_in_rig: np.ndarray | None = None
    up_sigma_rad: float = 0.0
    defect_views: list[DefectView | None] = field(default_factory=list)


def run(
    config: ReconstructConfig,
    dataset: Dataset,
    progress: ProgressFactory = no_progress,
    executor: Executor | None = None,
    checkpoints: Checkpoints | None = None,
) -> Reconstruction:
    """Run every stage on ``dataset``.

    ``executor`` does the frame-parallel work (default: one opened from
    ``config.workers`` / ``config.scheduler`` for this run, :mod:`omnipipe.executor`).
    ``checkpoints``: where each long stage's result is saved, and loaded from instead of
    computed when an earlier run with the same key saved it
    (:mod:`omnipipe.pipeline.checkpoint`); the result is the same either way.

    Raises:
        OmnipipeError: bad input (named file or field) or a stage that cannot proceed.
    """
    if executor is None:
        from omnipipe.executor import open_executor

        with open_executor(config.workers, config.scheduler, tasks=len(dataset)) as pool:
            return run(config, dataset, progress, pool, checkpoints)
    from omnipipe.spill import dropping_pages

    # Passes over the whole run map the scratch's pages of every keyframe and frame:
    # dropped as the run goes (omnipipe.spill).
    with dropping_pages():
        return _run(config, dataset, progress, executor, checkpoints)


def _run(
    config: ReconstructConfig,
    dataset: Dataset,
    progress: ProgressFactory,
    executor: Executor,
    checkpoints: Checkpoints | None,
) -> Reconstruction:
    """:func:`run` with its executor open."""
    if dataset.rig.laser is None:  # a camera-only rig (rig.yaml without a laser section)
        raise ReconstructionError(
            "rig.yaml has no laser section: a camera-only rig cannot reconstruct "
            "(add laser.plane, e.g. from omnipipe calibrate laser)"
        )
    from omnipipe.dataset import validate_frames
    from omnipipe.inputs.lossy import assess_input
    from omnipipe.pipeline import frame_pass

    log = RunLog(t_start=time.perf_counter())
    validate_frames(dataset)
    log.warnings.extend(dataset.warnings)  # e.g. a truncated video
    input_quality = assess_input(dataset)  # lossy (JPEG/MPEG) input degrades everything
    if input_quality.warning:
        log.warnings.append(input_quality.warning)
    # The compiled kernels and per-rig tables of the decoding pass, made here once
    # rather than in every worker (the local pool's workers are forked from this process).
    frame_pass.warm_up(config.laser, config.sfm.stations, dataset.rig)
    log.timings["startup"] = time.perf_counter() - log.t_start
    from omnipipe.progress import reporting

    with reporting(progress):  # the stages' inner steps draw bars of their own
        motion, measured, mdl = stages(config, dataset, executor, progress, log, checkpoints)
    log.timings["total"] = time.perf_counter() - log.t_start
    summary, defects = report_summary(config, dataset, motion, measured, mdl, executor, log)
    summary["input_quality"] = input_quality.to_dict()
    reg = motion.registered_frames
    from omnipipe.report.clock import imu_up

    up = None if dataset.imu is None or not len(reg) else imu_up(dataset.imu, float(dataset.timestamps[reg[0]]))
    views = _defect_views(dataset, defects, measured.result, mdl, motion.result.world_from_rig[reg], reg)
    return Reconstruction(
        summary=summary,
        timestamps=dataset.timestamps[reg],
        world_from_rig=motion.result.world_from_rig[reg],
        model=mdl,
        analysis=measured.result,
        report_config=config.report,
        frame_index=reg,
        defects=defects,
        trajectory_quality=measured.quality,
        up_in_rig=None if up is None else up[0],
        up_sigma_rad=0.0 if up is None else up[1],
        defect_views=views,
    )


def _defect_views(
    dataset: Dataset,
    defects: list[Defect],
    res: AnalysisResult,
    mdl: ModelResult,
    world_from_rig: np.ndarray,
    frame_index: np.ndarray,
) -> list[DefectView | None]:
    """Each defect's camera view (:mod:`omnipipe.report.views`)."""
    from omnipipe.camera import camera_from_rig
    from omnipipe.report.views import defect_views

    if not defects:
        return []
    return defect_views(
        defects,
        wall_points(res),
        mdl.points_in_world,
        world_from_rig,
        frame_index,
        camera_from_rig(dataset.rig),
        dataset.read_frame,
    )


def write(
    rec: Reconstruction,
    out: str | Path,
    *,
    force: bool = False,
    evaluation: dict[str, Any] | None = None,
    protect: Sequence[str | Path] = (),
    progress: ProgressFactory = no_progress,
) -> Path:
    """Write the contract outputs of ``rec`` to ``out`` atomically, with a manifest.

    ``force`` replaces only an earlier omnipipe output (see :mod:`omnipipe.output`);
    ``protect`` lists inputs (dataset, config file) that ``out`` may not be or hold.
    ``progress`` draws a bar ``output`` over the files written. Besides the contract's
    files: defects.csv and defects/*.png (:mod:`omnipipe.report.deliverable`).

    Raises:
        OutputError: ``out`` exists (without ``force``), is not omnipipe's, or cannot be
            written.
    """
    import gc

    from omnipipe import model as model_stage
    from omnipipe import report
    from omnipipe.dataset import atomic_output_dir, write_tum
    from omnipipe.report.clock import clock_reference
    from omnipipe.report.deliverable import write_deliverable
    from omnipipe.report.features_csv import write_features

    # The run's cyclic garbage (freed only when the collector next runs) and the pages
    # it held, not under the writers.
    gc.collect()
    release_freed_memory()
    out = Path(out)
    travel = float(rec.world_from_rig[-1][2, 3] - rec.world_from_rig[0][2, 3]) if len(rec.world_from_rig) else 1.0
    rec.summary["clock_reference"] = clock_reference(
        rec.survey, rec.up_in_rig, travel, rec.up_sigma_rad
    ).to_dict()
    from omnipipe.spill import dropping_pages

    with dropping_pages(), atomic_output_dir(out, force=force, protect=protect) as tmp:
        tick = progress("output", 3)
        write_tum(tmp / "trajectory.txt", rec.timestamps, rec.world_from_rig)
        model_stage.write_outputs(rec.model, tmp)
        tick(1)
        (tmp / "report.json").write_text(json.dumps(rec.summary, indent=1), encoding="utf-8")
        report.run(
            rec.report_config or report.ReportConfig(),
            report_inputs(rec, evaluation),
            tmp / "report.html",
        )
        tick(2)
        write_deliverable(
            tmp,
            rec.summary,
            rec.defects,
            rec.model.unrolled,
            rec.survey,
            travel_along_rig_z=travel,
            views=rec.defect_views,
        )
        write_features(
            tmp, rec.summary, rec.survey,
            travel_along_rig_z=float(rec.world_from_rig[-1][2, 3] - rec.world_from_rig[0][2, 3]),
        )
        tick(3)
    return out


def report_inputs(rec: Reconstruction, evaluation: dict[str, Any] | None = None) -> ReportInputs:
    """What report.html shows, from a reconstruction (and optional evaluation)."""
    from omnipipe.report import ReportInputs

    mdl, res = rec.model, rec.analysis
    truth = None
    if evaluation:
        truth = table_one(rec.summary, evaluation)
    return ReportInputs(
        summary=rec.summary,
        world_from_rig=rec.world_from_rig,
        mesh_vertices=mdl.mesh_vertices if mdl.textured_vertices is None else mdl.textured_vertices,
        mesh_faces=mdl.mesh_faces if mdl.textured_faces is None else mdl.textured_faces,
        mesh_uvs=mdl.textured_uvs,
        texture=mdl.texture,
        unrolled=None if mdl.unrolled is None else mdl.unrolled.image,
        unrolled_extent=None if mdl.unrolled is None else mdl.unrolled.extent,
        unrolled_alpha=None if mdl.unrolled is None else mdl.unrolled.alpha,
        stations_axial_mm=res.stations_axial_mm,
        stations_diameter_mm=res.stations_diameter_mm,
        stations_ovality=res.stations_ovality,
        radius_mm=None if res.inner_diameter_mm is None else res.inner_diameter_mm / 2,
        truth=truth,
        evaluation=evaluation,
        frame_index=rec.frame_index,
        defects=rec.defects,
        trajectory_quality=rec.trajectory_quality,
        wall=wall_points(res),
        defect_views=rec.defect_views,
        wall_points_in_world=mdl.points_in_world,
    )


def table_one(
    summary: dict[str, Any], evaluation: dict[str, Any]
) -> list[tuple[str, float | None, float | None, float | None, str]]:
    """The paper's Table I rows (name, measured, its 1-sigma, true, unit) from an evaluation."""
    rows: list[tuple[str, float | None, float | None, float | None, str]] = []
    d = evaluation.get("diameter", {})
    rows.append(
        (
            "inside diameter",
            d.get("measured_mm"),
            summary.get("inner_diameter_sigma_mm"),
            d.get("true_mm"),
            "mm",
        )
    )
    for k, row in enumerate(evaluation.get("defects", [])):
        t = row.get("true")
        if t is None:
            continue
        m = row.get("measured") or {}
        name = f"{t['kind']} {k + 1}"
        for what in ("height", "width", "length"):
            rows.append(
                (
                    f"{what} of {name}",
                    m.get(f"{what}_mm"),
                    m.get(f"{what}_sigma_mm"),
                    t[f"{what}_mm"],
                    "mm",
                )
            )
    return rows
