"""The stage sequence of a reconstruction run and its crash-safe hand-on.

:func:`stages` runs the frame pass, the camera motion, the analysis and the model in
order (the calls of :mod:`.stage_calls`). After each, its result is saved as a checkpoint
with the run's notes as they were then (:class:`_Saved`, :mod:`omnipipe.pipeline.checkpoint`);
a rerun loads the latest stage saved instead of computing it again, with those notes, and
does the frame pass only if a later stage still needs it. The moving frames, as decoded,
are handed from the decoding pass to the motion's and the model's workers through a
:class:`~omnipipe.handoff.FrameHandoff` when the executor is a local process pool.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import TYPE_CHECKING, Any

from omnipipe.memory import release_freed_memory, return_large_blocks
from omnipipe.pipeline.run_config import RunLog
from omnipipe.pipeline.stage_calls import (
    analyse,
    analysis_on_disk,
    build_model,
    camera_motion,
    decode,
    model_on_disk,
)
from omnipipe.progress import ProgressFactory

if TYPE_CHECKING:  # imported inside the functions: `omnipipe --help` stays fast
    from concurrent.futures import Executor

    from omnipipe.dataset import Dataset
    from omnipipe.handoff import FrameHandoff
    from omnipipe.model import ModelResult
    from omnipipe.pipeline.checkpoint import Checkpoints
    from omnipipe.pipeline.frame_pass import FramePassResult
    from omnipipe.pipeline.run_config import ReconstructConfig
    from omnipipe.pipeline.stage_calls import Measured, Motion


@dataclass(frozen=True)
class _Saved:
    """A stage's checkpoint: its result and the run's notes when it ended.

    Attributes:
        result: the stage's result.
        timings: the stage times (s) so far.
        warnings: the run's warnings so far.
    """

    result: Any
    timings: dict[str, float]
    warnings: list[str]


def _restore(checkpoints: Checkpoints | None, stage: str, log: RunLog) -> Any | None:
    """The result of ``stage`` loaded from ``checkpoints`` (the run's notes as they were
    when it was saved), or None."""
    saved = None if checkpoints is None else checkpoints.load(stage)
    if not isinstance(saved, _Saved):
        return None
    log.timings = dict(saved.timings)
    log.warnings = list(saved.warnings)
    return saved.result


def _keep(checkpoints: Checkpoints | None, stage: str, result: Any, log: RunLog) -> None:
    if checkpoints is not None:
        checkpoints.save(stage, _Saved(result, dict(log.timings), list(log.warnings)))


def stages(
    config: ReconstructConfig,
    dataset: Dataset,
    executor: Executor,
    progress: ProgressFactory,
    log: RunLog,
    checkpoints: Checkpoints | None,
) -> tuple[Motion, Measured, ModelResult]:
    """The frame pass, camera motion, analysis and model, each loaded from its
    checkpoint when there is one (then the frame pass is done only if a later stage
    still needs it), otherwise computed and saved."""
    from concurrent.futures import ProcessPoolExecutor

    from omnipipe.handoff import FrameHandoff

    # The moving frames as decoded, from the decoding pass to the motion's and the
    # model's workers (a local pool's workers share this file system).
    handoff = FrameHandoff(len(dataset)) if isinstance(executor, ProcessPoolExecutor) else None
    try:
        return _stages_handing_on(config, dataset, executor, progress, log, checkpoints, handoff)
    finally:
        if handoff is not None:
            handoff.close()


def _stages_handing_on(
    config: ReconstructConfig,
    dataset: Dataset,
    executor: Executor,
    progress: ProgressFactory,
    log: RunLog,
    checkpoints: Checkpoints | None,
    handoff: FrameHandoff | None,
) -> tuple[Motion, Measured, ModelResult]:
    """:func:`stages`, the decoding pass leaving the moving frames in ``handoff``."""
    cp = checkpoints
    frames_box: list[FramePassResult] = []
    folder = None if handoff is None else handoff.folder

    def frames() -> FramePassResult:
        # Needed after the camera motion was loaded: the pass's notes are in the loaded
        # ones already, so it notes into a log of its own.
        own = log if motion is None else RunLog(log.t_start)
        if not frames_box:
            got = _restore(cp, "frames", own)
            if got is None:
                got = decode(config, dataset, executor, progress, own, cp, handoff)
                _keep(cp, "frames", got, own)
            frames_box.append(got)
        return frames_box[0]

    motion: Motion | None = None
    motion = _restore(cp, "sfm", log)
    if motion is None:
        motion = camera_motion(config, dataset, frames(), executor, progress, log, folder)
        _keep(cp, "sfm", motion, log)
    # From here on this process's large freed arrays leave its memory at once (the
    # analysis', the model's and the writers' per-point and per-cell arrays); not during
    # the frame-by-frame stages, where mapping each image's arrays afresh cost 38 % more
    # CPU at 1600x1200 (benchmarks/RESULTS.md).
    return_large_blocks()
    found = _restore(cp, "analysis", log)
    if found is None:
        found = analyse(config, dataset, frames(), motion, executor, progress, log)
        _keep(cp, "analysis", found, log)
    # What grows with the run waits in its scratch (omnipipe.spill), also when loaded.
    measured, feed = analysis_on_disk(*found)
    del found
    frames_box.clear()
    release_freed_memory()
    mdl = _restore(cp, "model", log)
    if mdl is None:
        mdl = build_model(config, dataset, measured, feed, executor, progress, log, folder)
        _keep(cp, "model", mdl, log)
    mdl = model_on_disk(mdl)
    release_freed_memory()
    return motion, measured, mdl
