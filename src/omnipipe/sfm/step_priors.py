"""The wall's own shift as each keyframe step's length prior in the bundle adjustment.

The adjustment fits the feature tracks and the metric anchors (laser points found again,
Eq. 17, or wall-placed features). Where those run short together it shortens steps
unevenly: random-wide seed 32 (tiles, 640x480) had its adjusted steps 10-18 % below every
source on some steps and 4-6 % above on others, so that one run-wide factor
(:func:`omnipipe.sfm.run_length.run_length`) left 2.4 % of scale error and an ATE of
2.6 mm per 300 mm; seed 24 (joints), one keyframe step 0 -> 31, came out 12.2 mm for
13.04 true (the wall read 13.06 +- 0.34). The wall's dense axial shift
(:func:`omnipipe.sfm.wall_shift.step_wall_length`: both keyframes unrolled onto the
laser-measured wall cylinder and aligned by correlation) read every step of seed 32
within 1.6 %.

:func:`wall_priors` reads the wall on up to :data:`MAX_TRIGGER_STEPS` steps of the
adjusted run (evenly). Only when a reading leaves the adjusted step beyond
:data:`TRIGGER_SIGMAS` of its sigma (after the readings' run-wide median ratio is
removed: a uniform offset is the run's scale, which the run's length combines; with
fewer than :data:`MIN_RATIO_STEPS` readings the ratio itself counts, beyond
:data:`FEW_TRIGGER_SIGMAS` with :data:`RATIO_FLOOR` in its sigma) is every step read and each reading that agrees with
one of the step's sources within :data:`MAX_SOURCE_LOG` made a
:class:`~omnipipe.sfm.bundle.LengthPrior`; the run is then adjusted again with them. A
run the adjustment left consistent with the wall is not touched (a full-size run's
laser reads the scale better than the wall's 1 %: bend).

Conventions: lengths in mm along the travel, log ratios natural.
"""

from __future__ import annotations

import math
from concurrent.futures import Future
from dataclasses import dataclass, field

import numpy as np

from omnipipe.camera import CameraModel
from omnipipe.executor import shares_files
from omnipipe.sfm.bundle import LengthPrior
from omnipipe.sfm.image_store import ImageStore, StoredImage, load_image
from omnipipe.sfm.scale_check import StepCheck, WallCylinder, wall_cylinder
from omnipipe.sfm.types import Keyframes, SfmContext
from omnipipe.sfm.wall_shift import MIN_AXIAL_COS, candidate_window, wall_shift

# Steps read to decide whether the adjustment left the wall (evenly over the run).
MAX_TRIGGER_STEPS = 12
# A reading further than this many of its sigmas from its adjusted step (its run-wide
# median ratio removed) shows the adjustment moved that step. The readings' stated
# sigma runs 3-6x their error (random-wide seed 29, smooth: 1.8 % stated, every step
# within 0.3 %; its steps 0 and 3 adjusted +3.5 / -4.8 % off the readings' median ratio,
# 2.6 sigma: 3.0 left them, ATE 1.56 mm per 300 mm and 1.19 % of scale; 2.5 holds them:
# 1.02 and 0.33 %, scale34; the held steps confirmed by the wall,
# :func:`omnipipe.sfm.adjusted_steps.check_adjusted`).
TRIGGER_SIGMAS = 2.5
# Fewest readings for their median ratio to stand for the run's scale; with fewer the
# ratio itself is judged, RATIO_FLOOR (the wall's run-wide bias: shift_scale's floor)
# added to each reading's sigma.
MIN_RATIO_STEPS = 4
RATIO_FLOOR = 0.01
# ... and its ratio judged at this many sigmas: such a run's scale gets no say from the
# wall otherwise (shift_scale needs 4 readings). Random-wide seed 24, one step 0 -> 31:
# the wall 12.85 +- 0.34 mm (rim trimmed), the adjusted 12.21, 1.8 sigma with the floor;
# true 13.04. At 1 sigma seed 20 (tiles, 3 steps) was held to a reading 3.9 % long (the
# adjustment's own error there): 13 steps flagged, ATE 0.96 -> 1.38 mm per 300 mm.
FEW_TRIGGER_SIGMAS = 1.5
# A reading becomes a prior only within this |log| of the step's adjusted, decided or
# feature-depth length (a periodic wall's next course is further).
MAX_SOURCE_LOG = 0.25


@dataclass(frozen=True)
class WallPriors:
    """What :func:`wall_priors` read.

    Attributes:
        priors: the steps' lengths to hold the adjustment to (empty: leave it).
        readings: step -> (length, 1-sigma) mm of every step read on the adjusted poses
            given (NaN: not measured); :func:`omnipipe.sfm.shift_scale.shift_scale` reuses
            them when the run is not adjusted again.
    """

    priors: tuple[LengthPrior, ...] = ()
    readings: dict[int, tuple[float, float]] = field(default_factory=dict)


def wall_priors(
    ctx: SfmContext, kf: Keyframes, world_from_kf: np.ndarray, checks: list[StepCheck]
) -> WallPriors:
    """Each keyframe step's length read off the wall, as priors for adjusting the run
    again; no priors when the adjusted run ``world_from_kf`` ((K, 4, 4) mm) agrees with
    the wall (see the module docstring). ``checks``: (K-1,) the steps' decisions (their
    sources' lengths)."""
    steps = _readable_steps(world_from_kf, kf)
    if not steps:
        return WallPriors()
    first = steps
    if len(steps) > MAX_TRIGGER_STEPS:
        first = [steps[i] for i in np.linspace(0, len(steps) - 1, MAX_TRIGGER_STEPS).round().astype(int)]
    readings = _read_all(ctx, kf, [(k, b_from_a, length, checks[k]) for k, b_from_a, length in first])
    if not _moved(readings, {k: length for k, _, length in steps}):
        return WallPriors((), readings)
    readings |= _read_all(
        ctx, kf, [(k, b_from_a, length, checks[k]) for k, b_from_a, length in steps if k not in readings]
    )
    priors = []
    for k, _, length in steps:
        wall, sigma = readings[k]
        if math.isfinite(wall) and _agrees(wall, length, checks[k]):
            priors.append(LengthPrior(k, k + 1, wall, sigma))
    return WallPriors(tuple(priors), readings)


def bridged_priors(checks: list[StepCheck], skip: set[int] = frozenset()) -> tuple[LengthPrior, ...]:
    """Each bridged keyframe step's length (odometry, gait: :attr:`StepCheck.bridged_mm`
    with its 1-sigma) as a prior of the adjustment, but the steps in ``skip`` (read off
    the wall). A bridged step has no metric anchor of its own (no laser match, no
    wall-placed feature) and few feature tracks, so without it the adjustment left its
    length to chance: random-features seed 26's first two steps, bridged 10.5 / 10.2 +-
    0.8 mm (true 11.9 / 11.7), came out 15.3 / 4.0 mm with the laser anchors measured
    along their curves and 20.4 / 6.7 mm with both components (benchmarks/RESULTS.md)."""
    return tuple(
        LengthPrior(k, k + 1, c.bridged_mm, c.bridged_sigma_mm)
        for k, c in enumerate(checks)
        if c.bridged_from
        and k not in skip
        and math.isfinite(c.bridged_mm)
        and c.bridged_mm > 0
        and math.isfinite(c.bridged_sigma_mm)
        and c.bridged_sigma_mm > 0
    )


def _read_all(
    ctx: SfmContext, kf: Keyframes, steps: list[tuple[int, np.ndarray, float, StepCheck]]
) -> dict[int, tuple[float, float]]:
    """Step k -> (length, 1-sigma) mm read off the wall (NaN: not measured), searched
    around its adjusted length and its sources', for each (k, b_from_a, length, check)
    of ``steps``; the readings run on the executor's workers (:func:`read_wall_length`)."""
    jobs = {}
    for k, b_from_a, length, check in steps:
        cands = [length] + [
            v for v in (check.scale_mm, check.feature_scale_mm) if _near(v, length, math.log(1.5))
        ]
        walls = (wall_cylinder(kf.ring_points[k]), wall_cylinder(kf.ring_points[k + 1]))
        jobs[k] = submit_wall_length(ctx, kf, k, walls, b_from_a, candidate_window(cands))
    return {k: job.result() for k, job in jobs.items()}


def submit_wall_length(
    ctx: SfmContext,
    kf: Keyframes,
    k: int,
    walls: tuple[WallCylinder | None, WallCylinder | None],
    b_from_a: np.ndarray,
    window_mm: tuple[float, float],
) -> Future[tuple[float, float]]:
    """:func:`trimmed_wall_length` of keyframe step k -> k + 1 submitted to the run's
    executor (a local pool's worker reads the two grey images from their files)."""
    pair = tuple(
        kf.grays.ref(j) if shares_files(ctx.executor) and isinstance(kf.grays, ImageStore) else kf.grays[j]
        for j in (k, k + 1)
    )
    return ctx.executor.submit(read_wall_length, ctx.camera, pair, walls, b_from_a, window_mm)


def read_wall_length(
    camera: CameraModel,
    grays: tuple[np.ndarray | StoredImage, ...],
    walls: tuple[WallCylinder | None, WallCylinder | None],
    b_from_a: np.ndarray,
    window_mm: tuple[float, float],
) -> tuple[float, float]:
    """:func:`trimmed_wall_length` of two grey images given or stored (a worker's task)."""
    return trimmed_wall_length(camera, (load_image(grays[0]), load_image(grays[1])), walls, b_from_a, window_mm)


def trimmed_wall_length(
    camera: CameraModel,
    grays: tuple[np.ndarray, np.ndarray],
    walls: tuple[WallCylinder | None, WallCylinder | None],
    b_from_a: np.ndarray,
    window_mm: tuple[float, float],
) -> tuple[float, float]:
    """(length, 1-sigma) mm of a keyframe step read off the wall (NaN: not measured), as
    :func:`omnipipe.sfm.wall_shift.step_wall_length` reads it but with the template off
    the view's rim rows (``wall_shift(trim_rim=True)``, creep32's: a rig-fixed ramp there
    matches itself at zero shift and pulls a reading short). Random-wide seeds 0, 8, 18,
    35 (28 keyframe steps at 640x480): mean error -0.6 -> -0.3 %, seed 8 -1.5 -> +0.2 %.

    Args:
        camera: the rig's camera model.
        grays: (H, W) grey images without the laser of keyframes a and b.
        walls: their wall cylinders (rig frames).
        b_from_a: (4, 4) rig_b_from_rig_a with unit translation.
        window_mm: (lo, hi) lengths searched, mm along the travel.
    """
    R, t = np.asarray(b_from_a, float)[:3, :3], np.asarray(b_from_a, float)[:3, 3]
    norm = float(np.linalg.norm(t))
    if norm <= 0 or not all(math.isfinite(w) for w in window_mm):
        return math.nan, math.nan
    cos_z = float((-R.T @ t)[2] / norm)  # the rig's travel along rig a's z, per length
    if abs(cos_z) < MIN_AXIAL_COS:
        return math.nan, math.nan
    shift = wall_shift(
        camera, grays[0], grays[1], walls[0], walls[1], (window_mm[0] * cos_z, window_mm[1] * cos_z),
        trim_rim=True,
    )
    if not (shift.measured and shift.shift_mm / cos_z > 0 and shift.sigma_mm > 0):
        return math.nan, math.nan
    return shift.shift_mm / cos_z, shift.sigma_mm / abs(cos_z)


def _moved(readings: dict[int, tuple[float, float]], adjusted: dict[int, float]) -> bool:
    """Whether a reading leaves its adjusted step beyond :data:`TRIGGER_SIGMAS`."""
    ks = [k for k, (w, _) in readings.items() if math.isfinite(w)]
    if not ks:
        return False
    r = np.array([math.log(readings[k][0] / adjusted[k]) for k in ks])
    rel = np.array([readings[k][1] / readings[k][0] for k in ks])
    if len(ks) >= MIN_RATIO_STEPS:
        return bool(np.any(np.abs(r - np.median(r)) > TRIGGER_SIGMAS * rel))
    return bool(np.any(np.abs(r) > FEW_TRIGGER_SIGMAS * np.hypot(rel, RATIO_FLOOR)))


def _agrees(wall: float, adjusted: float, check: StepCheck) -> bool:
    """Whether the wall's length lies within :data:`MAX_SOURCE_LOG` of a source's."""
    return any(_near(v, wall, MAX_SOURCE_LOG) for v in (adjusted, check.scale_mm, check.feature_scale_mm))


def _near(value: float, length: float, max_log: float) -> bool:
    return math.isfinite(value) and value > 0 and abs(math.log(value / length)) <= max_log


def _readable_steps(world_from_kf: np.ndarray, kf: Keyframes) -> list[tuple[int, np.ndarray, float]]:
    """(k, rig_b_from_rig_a with unit translation, adjusted length mm) of every step
    with a relative motion that translates."""
    out = []
    for k in range(min(len(world_from_kf) - 1, len(kf.evidence))):
        if kf.evidence[k].status != "ok":
            continue
        b_from_a = np.linalg.inv(world_from_kf[k + 1]) @ world_from_kf[k]
        length = float(np.linalg.norm(b_from_a[:3, 3]))
        if length <= 1e-6:
            continue
        b_from_a = b_from_a.copy()
        b_from_a[:3, 3] /= length
        out.append((k, b_from_a, length))
    return out
