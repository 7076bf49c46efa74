"""Metric length of every keyframe step and of the whole run (paper Sec. V-D, step 4).

Each step has two length measurements (:class:`~omnipipe.sfm.types.StepEvidence`):
the laser points found again by template matching along the epipolar curves (Eq. 17)
and the matched features' depths on the light-section wall
(:mod:`omnipipe.sfm.scale_check`). Here

- the run-wide offset of the two sources is measured (:func:`run_scale`): a
  consistent offset is a bias of one source, a large one makes the wall the anchor;
- every step is decided with it (:func:`decide_step`: trusted, resolved to another
  consensus peak, or untrusted) and chained into metric steps with their bundle
  adjustment tracks and anchors (:func:`chain_steps`); steps measured by their
  feature depths alone are confirmed by the window of steps around them
  (:func:`confirm_by_gait`), trusted steps the odometry contradicts are not trusted
  (:func:`contradict_trusted`), and steps without a length are bridged from the
  odometry or the gait (:func:`bridge_steps`, :func:`bridge_lost_steps`);
- after the adjustment, steps that left their sources are flagged
  (:func:`check_adjusted`) and the run's overall scale is combined with the
  wall-placed features' (:func:`run_length`, :func:`combine_scales`), with its
  relative 1-sigma.

The steps live in named modules: :mod:`~omnipipe.sfm.step_decide` (the run-wide offset,
each step's decision), :mod:`~omnipipe.sfm.step_resolve` and
:mod:`~omnipipe.sfm.wall_resolve` (flagged steps judged by the gait, the odometry, the
wall's own shift), :mod:`~omnipipe.sfm.step_chain` (bridging, chaining, anchors),
:mod:`~omnipipe.sfm.adjusted_steps` (the check of adjusted steps) and
:mod:`~omnipipe.sfm.run_length` (the run's scale and sigma); this module names them
together.
"""

from omnipipe.sfm.adjusted_steps import ADJUSTED_OFFSET_MIN_STEPS, check_adjusted
from omnipipe.sfm.run_length import (
    DECIDED_SIGMAS,
    SHARED_SCALE_SIGMA,
    RunLength,
    combine_scales,
    decided_log,
    run_length,
    scale_sigma,
)
from omnipipe.sfm.step_chain import (
    WALL_ANCHORS_PER_STEP,
    ChainedSteps,
    bridge_lost_steps,
    bridge_steps,
    chain_steps,
    wall_anchors,
)
from omnipipe.sfm.step_decide import DecidedStep, RunScale, decide_step, run_scale, source_offset
from omnipipe.sfm.step_resolve import (
    ACCEPT_SIGMAS,
    REJECT_SIGMAS,
    confirm_by_gait,
    confirmed_candidates,
    contradict_trusted,
    resolve_by_prior,
    tracked_depths_confirm,
)
from omnipipe.sfm.wall_resolve import (
    PLAUSIBLE_FACTOR,
    VETO_REACH_DOWN,
    VETO_SIGMAS,
    WALL_ALONE_BACK_MM,
    WALL_ALONE_MAX_AMBIGUITY,
    WALL_ALONE_MIN_MM,
    WALL_ALONE_MIN_NCC,
    WALL_ALONE_REACH,
    resolve_by_wall,
)

__all__ = [
    "ACCEPT_SIGMAS",
    "ADJUSTED_OFFSET_MIN_STEPS",
    "DECIDED_SIGMAS",
    "PLAUSIBLE_FACTOR",
    "REJECT_SIGMAS",
    "SHARED_SCALE_SIGMA",
    "VETO_REACH_DOWN",
    "VETO_SIGMAS",
    "WALL_ALONE_BACK_MM",
    "WALL_ALONE_MAX_AMBIGUITY",
    "WALL_ALONE_MIN_MM",
    "WALL_ALONE_MIN_NCC",
    "WALL_ALONE_REACH",
    "WALL_ANCHORS_PER_STEP",
    "ChainedSteps",
    "DecidedStep",
    "RunLength",
    "RunScale",
    "bridge_lost_steps",
    "bridge_steps",
    "chain_steps",
    "check_adjusted",
    "combine_scales",
    "confirm_by_gait",
    "confirmed_candidates",
    "contradict_trusted",
    "decide_step",
    "decided_log",
    "resolve_by_prior",
    "resolve_by_wall",
    "run_length",
    "run_scale",
    "scale_sigma",
    "source_offset",
    "tracked_depths_confirm",
    "wall_anchors",
]
