"""The run's metric scale read off the wall's own shift, after the bundle adjustment.

The laser (Eq. 17) and the features placed on the light-section wall
(:func:`omnipipe.sfm.scale_check.wall_scale_correction`) both measure a step from sparse
points matched between two keyframes; on some walls both run short together (tiles at
640x480, random-wide seeds 32 and 35: the laser's and the feature depths' step lengths
a median 5-6 % and 2-5 % below the truth, the adjusted run 7 % and 1.4 %), so no sigma
from them covers the truth. The wall's dense axial shift
(:func:`omnipipe.sfm.step_priors.trimmed_wall_length`: both keyframes unrolled onto the
laser-measured wall cylinder and aligned by correlation, the view's rim rows left out) needs neither: on those runs
it read every step within 1.7 % (median +0.7 % and -0.2 %).

:func:`shift_scale` reads it on up to :data:`MAX_SHIFT_STEPS` reliable adjusted steps
(evenly over the run) and returns the log ratio of the wall's total length to the
adjusted one over them with its 1-sigma: the readings' own sigmas in quadrature (each
carries the sectors' scatter and a relative floor) and :data:`SHIFT_SCALE_FLOOR` (a
bias of the wall's cylinder shared by every step).
:func:`omnipipe.sfm.run_length.run_length` combines it with the other two.

Conventions: lengths in mm along the travel; log ratios natural; sigmas relative.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from omnipipe.sfm.scale_check import StepCheck, wall_cylinder
from omnipipe.sfm.step_priors import submit_wall_length
from omnipipe.sfm.types import Keyframes, SfmContext
from omnipipe.sfm.wall_shift import candidate_window

# Most steps read (evenly over the run's reliable ones): each reading unrolls two
# keyframes, so a long run's cost stays bounded; a dozen readings put the median's
# statistical part below the floor.
MAX_SHIFT_STEPS = 12
# Fewest readings for a run-wide value.
MIN_SHIFT_STEPS = 4
# Relative 1-sigma every reading shares (the wall cylinder's radius, the unrolling's
# mapping): the steps' median ran within 0.7 % of the truth on six random-wide seeds at
# 640x480 (tiles, mosaic, brick, corrugated), but a smooth wall's run (seed 29) came out
# 2.2 % off, beyond 2 sigma at 0.5 % (benchmarks/RESULTS.md, scale32).
SHIFT_SCALE_FLOOR = 0.01
# Readings whose own ratio to the adjusted length lies further than this many robust
# sigmas (or their own) from the median ratio are left out (a misread shift).
OUTLIER_SIGMAS = 3.0
# A reading is used only when its candidate window holds the adjusted length and the
# decided one within this factor of each other (a step the adjustment moved far is no
# reference for the ratio).
MAX_SOURCE_RATIO = 1.5


@dataclass(frozen=True)
class ShiftScale:
    """The wall's shift against the adjusted run.

    Attributes:
        log: median log(wall length / adjusted length) over the read steps.
        sigma: its relative 1-sigma.
        steps: how many steps were read.
    """

    log: float
    sigma: float
    steps: int


def shift_scale(
    ctx: SfmContext,
    kf: Keyframes,
    world_from_kf: np.ndarray,
    checks: list[StepCheck],
    known: dict[int, tuple[float, float]] | None = None,
) -> ShiftScale | None:
    """The run's scale as the wall's own shift reads it (see the module docstring);
    None with fewer than :data:`MIN_SHIFT_STEPS` readings.

    Args:
        ctx: the run's context (camera).
        kf: the keyframes (grey images, ring points, evidence).
        world_from_kf: (K, 4, 4) adjusted keyframe poses, mm.
        checks: (K-1,) each step's check (reliable steps only are read).
        known: step -> (length, 1-sigma) mm already read on these poses
            (:class:`omnipipe.sfm.step_priors.WallPriors`), not read again.
    """
    steps = _candidate_steps(world_from_kf, checks, kf)
    if len(steps) > MAX_SHIFT_STEPS:
        steps = [steps[i] for i in np.linspace(0, len(steps) - 1, MAX_SHIFT_STEPS).round().astype(int)]
    walls, sigmas, adjusted = [], [], []
    jobs = {}  # the steps not read yet, on the executor's workers
    for k, b_from_a, length in steps:
        c = checks[k]
        cands = [length] + [v for v in (c.scale_mm, c.feature_scale_mm) if _near(v, length)]
        pair_walls = (wall_cylinder(kf.ring_points[k]), wall_cylinder(kf.ring_points[k + 1]))
        if not (known or {}).get(k):
            jobs[k] = submit_wall_length(ctx, kf, k, pair_walls, b_from_a, candidate_window(cands))
    for k, _, length in steps:
        wall, sigma = (known or {}).get(k) or jobs[k].result()
        if math.isfinite(wall):
            walls.append(wall)
            sigmas.append(sigma)
            adjusted.append(length)
    return _total_ratio(np.array(walls), np.array(sigmas), np.array(adjusted))


def _total_ratio(walls: np.ndarray, sigmas: np.ndarray, adjusted: np.ndarray) -> ShiftScale | None:
    """log(sum of the wall's lengths / sum of the adjusted ones) over the read steps
    ((N,) mm each; ``sigmas`` the readings' 1-sigma, mm) whose own ratio lies within
    :data:`OUTLIER_SIGMAS` robust sigmas of the median ratio, with its 1-sigma: the
    readings' sigmas in quadrature over the total, and :data:`SHIFT_SCALE_FLOOR`. The
    run's scale is its total over its total, not a per-step ratio (the adjusted steps
    scatter by several % around their sum: random-wide seed 32)."""
    if len(walls) < MIN_SHIFT_STEPS:
        return None
    r = np.log(walls / adjusted)
    med = float(np.median(r))
    spread = 1.4826 * float(np.median(np.abs(r - med)))
    keep = np.abs(r - med) <= OUTLIER_SIGMAS * np.maximum(spread, sigmas / walls)
    if keep.sum() < MIN_SHIFT_STEPS:
        return None
    total = float(walls[keep].sum())
    log = math.log(total / float(adjusted[keep].sum()))
    own = float(np.sqrt(np.sum(sigmas[keep] ** 2))) / total
    return ShiftScale(log, math.hypot(own, SHIFT_SCALE_FLOOR), int(keep.sum()))


def _near(value: float, length: float) -> bool:
    """Whether a source's length (mm) lies within :data:`MAX_SOURCE_RATIO` of ``length``."""
    return math.isfinite(value) and value > 0 and abs(math.log(value / length)) <= math.log(MAX_SOURCE_RATIO)


def _candidate_steps(
    world_from_kf: np.ndarray, checks: list[StepCheck], kf: Keyframes
) -> list[tuple[int, np.ndarray, float]]:
    """(k, rig_b_from_rig_a with unit translation, adjusted length mm) of every reliable,
    measured, translating step whose decided length agrees with its adjusted one."""
    out = []
    n = min(len(checks), len(world_from_kf) - 1, len(kf.evidence))
    for k in range(n):
        c = checks[k]
        if not c.measures_scale or kf.evidence[k].status != "ok":
            continue
        b_from_a = np.linalg.inv(world_from_kf[k + 1]) @ world_from_kf[k]
        length = float(np.linalg.norm(b_from_a[:3, 3]))
        if length <= 1e-6 or not _near(c.scale_mm, length):
            continue
        b_from_a = b_from_a.copy()
        b_from_a[:3, 3] /= length
        out.append((k, b_from_a, length))
    return out
