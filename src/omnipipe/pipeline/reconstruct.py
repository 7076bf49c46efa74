"""The reconstruction pipeline's run: dataset in, a :class:`Reconstruction` out.

Stages, each a ``run(config, inputs)`` of its own subpackage: ``laser`` (light
section: metric ring points per frame), ``sfm`` (camera motion, metric by the laser),
``model`` (integration, mesh, texture, unrolled wall), ``analysis`` (inner diameter,
ovality, defects) and ``report``. Here: :func:`run` (every stage on a dataset) and its
result :class:`Reconstruction`. In modules of their own: the settings and the run's log
(:mod:`.run_config`), each stage's call (:mod:`.stage_calls`), the stage sequence with
its checkpoints (:mod:`.run_state`), report.json's content (:mod:`.summary`) and the
writing of the outputs (:mod:`.outputs`: to a temporary directory next to OUT moved into
place at the end, so a failed or interrupted run never leaves OUT looking complete).
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Any

from omnipipe.errors import ReconstructionError
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
    from omnipipe.report import ReportConfig
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
