"""Flagged keyframe steps resolved by the wall's own shift (paper Sec. V-D).

:func:`resolve_by_wall`: the unrolled walls of a step's two keyframes aligned densely
(:func:`omnipipe.sfm.wall_shift.step_wall_length`), a length independent of the laser
(Eq. 17) and of the feature depths, confirms one of the step's candidates, withdraws a
laser peak both sources chose on a wrong course, or (one clear peak over a wide window)
gives the step's length alone.

Conventions: lengths in mm; each source compared in its own mm.
"""

from __future__ import annotations

import math
from dataclasses import replace

import numpy as np

from omnipipe.sfm.robot_sensors import OdometrySteps
from omnipipe.sfm.scale_check import (
    FEATURE_DEPTH_SIGMA_FLOOR,
    PEAK_CHOSEN,
    ScaleCheckConfig,
    StepCheck,
    wall_cylinder,
)
from omnipipe.sfm.step_decide import DecidedStep, RunScale, resolve_to
from omnipipe.sfm.step_resolve import ACCEPT_SIGMAS, confirmed_candidates
from omnipipe.sfm.types import Keyframes, SfmContext
from omnipipe.sfm.wall_shift import (
    SECTORS,
    StepImages,
    WallLength,
    candidate_window,
    step_wall_length,
)


def resolve_by_wall(
    ctx: SfmContext,
    kf: Keyframes,
    decided: list[DecidedStep],
    lengths: np.ndarray,
    scale: RunScale,
    counts: np.ndarray | None = None,
    odometry: OdometrySteps | None = None,
) -> dict[int, tuple[float, float, float]]:
    """Flagged steps whose vision candidates (every laser consensus peak, the feature
    depth length) include exactly one the wall's own shift confirms
    (:func:`omnipipe.sfm.wall_shift.step_wall_length`: the unrolled walls of the two
    keyframes aligned densely, a third source independent of both) and exclude the
    others, resolved to it in place with a warning (as :func:`resolve_by_prior`). The
    comparison is in each source's own mm; the wall reading's 1-sigma is widened by the
    candidate's (:data:`~omnipipe.sfm.scale_check.FEATURE_DEPTH_SIGMA_FLOOR`), and two
    of it over the step's ``counts[k]`` moving frames must stay within
    ``adjusted_agree_mm`` a frame (a frame step off by more is wrong). With the robot's
    ``odometry``, a reading it does not confirm (:func:`_odometry_confirms`) decides
    nothing, nor does the wall alone (no candidate confirmed): such a reading the
    odometry confirms is returned, step k -> (length, 1-sigma in the chain's mm, the
    shift's correlation), for :func:`wall_confirms_bridged`.

    A trusted step whose laser and feature depths differ by more than
    ``anchor_agree_log`` (:func:`omnipipe.sfm.step_decide.decide_step` took the feature
    length without anchors: :func:`_laser_set_aside`) is judged by the wall likewise."""
    agreed: dict[int, tuple[float, float, float]] = {}
    gain = math.exp(scale.offset_log)
    unit = gain if scale.wall_anchored else 1.0  # chain length = laser length / unit
    config = ctx.config.scale_check
    for k, (step, ev) in enumerate(zip(decided, kf.evidence, strict=True)):
        c = step.check
        peak_chosen = c.confidence == "resolved" and c.reason.startswith(PEAK_CHOSEN)
        set_aside = c.reliable and not peak_chosen and _laser_set_aside(step, gain, config)
        if (c.reliable and not peak_chosen and not set_aside) or ev.status != "ok":
            continue
        cand = _candidates(c, set_aside, gain, unit)
        if not cand:
            continue
        pair, reading = _wall_reading(ctx, kf, k, [v for v, _, _ in cand], peak_chosen)
        if not reading.measured:
            continue
        wall_mm = reading.length_mm
        sigma = math.hypot(reading.sigma_mm, FEATURE_DEPTH_SIGMA_FLOOR * wall_mm)
        if odometry is not None and not _odometry_confirms(odometry, k, wall_mm / unit, sigma / unit):
            continue
        if peak_chosen:
            if not _wall_vetoes(ctx, decided, lengths, k, reading, sigma, gain):
                continue
            c = decided[k].check
        moving = int(counts[k]) if counts is not None and k < len(counts) else 1
        if 2.0 * sigma > config.adjusted_agree_mm * max(moving, 1):
            continue
        near = confirmed_candidates(np.array([v for v, _, _ in cand]), wall_mm, sigma, config.agree_log)
        if near is not None:
            names = " and ".join(sorted({cand[i][2] for i in near}))
            if set_aside:
                decided[k] = replace(step, check=replace(c, reason=_set_aside_reason(c, gain)))
            resolve_to(
                ctx, kf, decided, lengths, k, float(np.median([cand[i][1] for i in near])), scale,
                f"the {names} length agrees with the wall's own shift {wall_mm:.1f} +- "
                f"{sigma:.1f} mm (unrolled wall, correlation {reading.shift.ncc:.2f}), the other "
                "candidates do not",
                (wall_mm, ACCEPT_SIGMAS * sigma),
            )
        elif set_aside:
            continue  # trusted on its feature depths, as decided
        elif odometry is None:
            _wall_alone(ctx, decided, lengths, k, pair, reading, unit)
        else:
            # With odometry the step is bridged from it instead: the frames inside then
            # follow its travel, not a resection on a wall whose features could not
            # measure the step (random-wide seed 24s, joints: 5 frame steps 0.25-0.5 mm
            # off, unflagged, inside a step the wall alone resolved). The two agreeing
            # measure its length (:func:`wall_confirms_bridged`).
            agreed[k] = (wall_mm / unit, sigma / unit, reading.shift.ncc)
    return agreed


def _wall_reading(
    ctx: SfmContext, kf: Keyframes, k: int, candidates_mm: list[float], peak_chosen: bool
) -> tuple[StepImages, WallLength]:
    """Step k's two keyframes (camera, grey images, walls, relative pose) and the wall's
    shift read over the window its candidates span (down to :data:`VETO_REACH_DOWN` of
    it for a ``peak_chosen`` step: the wall may find the step far below every one)."""
    c = kf.evidence[k]
    pair: StepImages = (
        ctx.camera,
        (kf.grays[k], kf.grays[k + 1]),
        (wall_cylinder(kf.ring_points[k]), wall_cylinder(kf.ring_points[k + 1])),
        c.b_from_a,
    )
    window = candidate_window(_plausible(candidates_mm, c.feature_scale_mm))
    if peak_chosen:
        window = (VETO_REACH_DOWN * window[0], window[1])
    return pair, step_wall_length(*pair, window)


def _candidates(c: StepCheck, set_aside: bool, gain: float, unit: float) -> list[tuple[float, float, str]]:
    """(own mm, chain's mm, name) of every vision candidate of a step: its laser
    consensus peaks (and, ``set_aside``, its laser length), its feature depth length."""
    cand = [(p, p / unit, "laser peak") for p in c.laser_peaks_mm if p > 0]
    if set_aside:
        cand.append((c.laser_scale_mm, c.laser_scale_mm / unit, "laser"))
    if math.isfinite(c.feature_scale_mm) and c.feature_scale_mm > 0:
        cand.append((c.feature_scale_mm, c.feature_scale_mm * gain / unit, "feature depth"))
    return cand


def _laser_set_aside(step: DecidedStep, gain: float, config: ScaleCheckConfig) -> bool:
    """A trusted step whose laser length (``gain``: the run's laser / feature-depth
    offset) differs from its feature depths by more than ``anchor_agree_log`` (within
    ``agree_log``): :func:`~omnipipe.sfm.step_decide.decide_step` took the feature length
    and dropped the laser's anchors, so nothing measured it twice. The wall's shift may
    (its cases: benchmarks/RESULTS.md, feat27)."""
    c = step.check
    return (
        c.confidence == "high"
        and step.laser is None
        and math.isfinite(c.laser_scale_mm)
        and c.laser_scale_mm > 0
        and math.isfinite(c.feature_scale_mm)
        and c.feature_scale_mm > 0
        and abs(math.log(c.laser_scale_mm / (gain * c.feature_scale_mm))) > config.anchor_agree_log
    )


def _set_aside_reason(c: StepCheck, gain: float) -> str:
    """What a step :func:`_laser_set_aside` says before the wall resolves it."""
    gap = 100 * (c.laser_scale_mm / (gain * c.feature_scale_mm) - 1)
    return (
        f"laser {c.laser_scale_mm:.1f} mm and feature depth {c.feature_scale_mm:.1f} mm "
        f"lengths differ by {gap:+.0f} %"
    )


def _odometry_confirms(odometry: OdometrySteps, k: int, length: float, sigma: float) -> bool:
    """Whether the odometry's step k (uncalibrated: its stated sigma) lies within
    :data:`ACCEPT_SIGMAS` of the wall's ``length`` +- ``sigma`` (the chain's mm), both
    sigmas combined; no odometry length for the step: False. Random-wide seeds 24s,
    33s, 8s: the wall's 13.1 +- 0.4, 21.2 +- 0.5, 1.1 +- 0.1 mm, the odometry's 13.0 +-
    0.5, 21.5 +- 1.3, 1.2 +- 0.2 (true 13.0, 21.3, 1.1)."""
    est, sig = odometry.estimate(k)
    if not (math.isfinite(est) and math.isfinite(sig)):
        return False
    return abs(length - est) <= ACCEPT_SIGMAS * math.hypot(sig, sigma)


# The wall's window spans the laser peaks within this factor of the feature-depth length
# (all of them without one): a wild peak (random-wide seed 29: 62.5 mm for a 19 mm step)
# would widen it so far that the template left is too short to read (no peak inside).
PLAUSIBLE_FACTOR = 2.0


def _plausible(candidates_mm: list[float], feature_mm: float) -> list[float]:
    """The candidate lengths (mm) the wall's window spans: with a feature-depth length
    ``feature_mm``, those within :data:`PLAUSIBLE_FACTOR` of it; else all."""
    if not (math.isfinite(feature_mm) and feature_mm > 0):
        return candidates_mm
    f = PLAUSIBLE_FACTOR
    return [v for v in candidates_mm if feature_mm / f <= v <= feature_mm * f]


# A laser peak chosen over the best because the feature depths agree with it
# (scale_check.decide) is withdrawn when the wall's own shift lies further than this
# many of its sigmas from it (a reading: no second peak above
# wall_shift.MAX_AMBIGUITY; withdrawing only flags the step): both sources then sit on
# one wrong course (random-wide seed 19, smooth: laser peak 10.9 and feature depths
# 11.9 mm for 8.95 true).
VETO_SIGMAS = 4.0
# ... searched down to this fraction of the candidates' window (the right course may be
# a period below all of them).
VETO_REACH_DOWN = 0.4


def _wall_vetoes(
    ctx: SfmContext,
    decided: list[DecidedStep],
    lengths: np.ndarray,
    k: int,
    reading: WallLength,
    sigma: float,
    gain: float,
) -> bool:
    """Whether step k's chosen laser peak is withdrawn by the wall (see
    :data:`VETO_SIGMAS`); if so, in place: untrusted, no length, no laser anchors."""
    step = decided[k]
    c = step.check
    # The chosen peak in laser mm, and in feature-depth mm (the run's laser / feature
    # gain removed): withdrawn only when neither agrees (random-wide seed 11: the laser
    # runs 10 % short throughout, its right peaks 10 % below the wall).
    if min(abs(v - reading.length_mm) for v in (c.scale_mm, c.scale_mm / gain)) <= VETO_SIGMAS * sigma:
        return False
    reason = (
        f"{c.reason}; but the wall's own shift {reading.length_mm:.1f} +- {sigma:.1f} mm "
        "(unrolled wall) disagrees"
    )
    ctx.warnings.append(f"frames {c.first_frame}->{c.last_frame}: {reason}")
    decided[k] = replace(
        step, scale_mm=math.nan, laser=None,
        check=replace(c, scale_mm=math.nan, confidence="none", reason=reason),
    )
    lengths[k] = math.nan
    return True


# A step no candidate of which the wall confirms takes the wall's own length only when
# its shift is the one clear peak over a wide window: every length from WALL_ALONE_BACK_MM
# back to WALL_ALONE_REACH times its own (at least WALL_ALONE_MIN_MM), so a brick, tile or
# corrugation period within it shows as a second peak (an alias beyond it would need a
# true step longer than a period: no frame-to-frame method survives that); that peak at most
# WALL_ALONE_MAX_AMBIGUITY of the best, the correlation at least WALL_ALONE_MIN_NCC and
# every sector agreeing.
WALL_ALONE_BACK_MM = 2.0
WALL_ALONE_REACH = 2.5
WALL_ALONE_MIN_MM = 20.0
WALL_ALONE_MAX_AMBIGUITY = 0.5
WALL_ALONE_MIN_NCC = 0.2


def _wall_alone(
    ctx: SfmContext,
    decided: list[DecidedStep],
    lengths: np.ndarray,
    k: int,
    pair: StepImages,
    reading: WallLength,
    unit: float,
) -> None:
    """Step k resolved to the wall's own length in place when its shift is unambiguous
    over a wide window (the constants above), with a warning; its laser matches do not
    anchor it (none of their lengths is right) and its matches stay (the adjustment's
    tracks: a step it then moves is flagged by :func:`check_adjusted`)."""
    reach = max(WALL_ALONE_REACH * reading.length_mm, WALL_ALONE_MIN_MM)
    wide = step_wall_length(*pair, (-WALL_ALONE_BACK_MM, reach))
    if (
        not wide.measured
        or wide.shift.ambiguity > WALL_ALONE_MAX_AMBIGUITY
        or wide.shift.ncc < WALL_ALONE_MIN_NCC
        or wide.shift.sectors < SECTORS
        or abs(wide.length_mm - reading.length_mm) > reading.sigma_mm
    ):
        return
    step = decided[k]
    c = step.check
    chosen = reading.length_mm / unit
    reason = (
        f"{c.reason}; resolved to {chosen:.1f} mm: the wall's own shift "
        f"{reading.length_mm:.1f} +- {reading.sigma_mm:.1f} mm (unrolled wall, correlation "
        f"{wide.shift.ncc:.2f}, no other shift within {reach:.0f} mm above "
        f"{wide.shift.ambiguity:.2f} of it); none of the other candidates agrees"
    )
    ctx.warnings.append(f"frames {c.first_frame}->{c.last_frame}: {reason}")
    decided[k] = replace(
        step,
        scale_mm=chosen * unit,
        laser=None,
        check=replace(c, scale_mm=chosen * unit, confidence="resolved", reason=reason),
    )
    lengths[k] = chosen


def wall_confirms_bridged(
    ctx: SfmContext,
    checks: list[StepCheck],
    lengths: np.ndarray,
    agreed: dict[int, tuple[float, float, float]],
) -> None:
    """Steps bridged from the odometry whose wall reading it confirmed
    (:func:`resolve_by_wall`'s ``agreed``: step k -> (length, 1-sigma mm, correlation))
    made ``resolved`` in place: two independent measurements agree (the wall's own
    shift, the robot's travel), so the length is their inverse-variance mean with its
    1-sigma, not an estimate. The step stays bridged (its frames follow the odometry's
    travel, the adjustment holds it to that length with that sigma, and it does not
    speak for the run's scale: :attr:`~omnipipe.sfm.scale_check.StepCheck.measures_scale`)."""
    for k, (wall_mm, wall_sigma, ncc) in agreed.items():
        c = checks[k]
        if c.bridged_from != "odometry" or not (math.isfinite(c.bridged_mm) and c.bridged_sigma_mm > 0):
            continue
        w_wall, w_odo = wall_sigma**-2, c.bridged_sigma_mm**-2
        length = (w_wall * wall_mm + w_odo * c.bridged_mm) / (w_wall + w_odo)
        sigma = (w_wall + w_odo) ** -0.5
        reason = (
            f"{c.reason}; measured: the wall's shift {wall_mm:.1f} +- {wall_sigma:.1f} mm "
            f"(unrolled wall, correlation {ncc:.2f}) agrees with it: {length:.1f} +- {sigma:.1f} mm"
        )
        ctx.warnings.append(f"frames {c.first_frame}->{c.last_frame}: {reason}")
        checks[k] = replace(
            c, confidence="resolved", reason=reason, bridged_mm=length, bridged_sigma_mm=sigma
        )
        lengths[k] = length
