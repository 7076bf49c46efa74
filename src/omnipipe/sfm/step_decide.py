"""Each keyframe step's length decided with the run's two scale sources (paper Sec. V-D).

The laser points found again by template matching along the epipolar curves (Eq. 17)
and the matched features' depths on the light-section wall
(:mod:`omnipipe.sfm.scale_check`) are related run-wide (:func:`run_scale`: a
consistent offset is a bias of one source, a large one makes the wall the anchor);
every step is then decided with that offset (:func:`decide_step`: trusted, resolved to
another consensus peak, or untrusted), and a step resolved to a chosen length later
(:func:`resolve_to`) has its laser re-matched around it (:func:`laser_around`).

Conventions: lengths in mm; log ratios natural.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, replace

import numpy as np

from omnipipe.sfm.flat_field import divided
from omnipipe.sfm.laser_scale import LaserMatches, match_laser_points
from omnipipe.sfm.scale_check import FEATURE_ONLY, ScaleCheckConfig, StepCheck, decide
from omnipipe.sfm.types import Keyframes, SfmContext, StepEvidence


@dataclass(frozen=True)
class RunScale:
    """The run-wide relation of the two scale sources.

    Attributes:
        offset_log: median log(laser / feature-depth length) over the steps (0: none
            measured or too large to be a bias).
        wall_anchored: True when the laser runs off the feature depths by more than
            ``scale_check.max_bias_log``: the features placed on the light-section wall
            anchor the scale instead of the laser's matches.
    """

    offset_log: float
    wall_anchored: bool


@dataclass(frozen=True)
class DecidedStep:
    """One keyframe step after the run-level decision.

    Attributes:
        b_from_a: (4, 4) rig_b_from_rig_a, unit (or zero) translation.
        scale_mm: the length to chain (mm; NaN: none trusted; 0 for a rotation).
        inliers: (M, 2) the inlier matches to keep (wrong-course ones dropped).
        laser: the laser matches to use as anchors (None: untrusted).
        check: the step's evidence and confidence.
    """

    b_from_a: np.ndarray
    scale_mm: float
    inliers: np.ndarray | None
    laser: LaserMatches | None
    check: StepCheck


def source_offset(evidence: list[StepEvidence], config: ScaleCheckConfig) -> float:
    """Median log(laser / feature depth) over the run's steps (0 with fewer than 3).

    A consistent offset is a bias of one source on this rig and pipe (e.g. the laser
    patches' coarse sampling in a large pipe), not an aliased step: the per-step
    check compares the sources after removing it, so it catches jumps (a wrong course)
    without flagging every step of a run whose sources disagree by a few per cent.
    """
    r = [
        math.log(ev.laser.scale / ev.feature_scale_mm)
        for ev in evidence
        if ev.laser is not None
        and math.isfinite(ev.laser.scale)
        and ev.laser.scale > 0
        and math.isfinite(ev.feature_scale_mm)
    ]
    offset = float(np.median(r)) if len(r) >= 3 else 0.0
    return offset if abs(offset) <= config.max_source_offset_log else 0.0


def run_scale(
    evidence: list[StepEvidence], config: ScaleCheckConfig, warnings: list[str]
) -> RunScale:
    """The two sources' run-wide offset, and whether the wall anchors the scale
    (both with a warning)."""
    offset = source_offset(evidence, config)
    if offset == 0.0 and len(evidence) >= 3:
        raw = source_offset(evidence, replace(config, max_source_offset_log=math.inf))
        if raw != 0.0:
            warnings.append(
                f"laser and feature-depth step lengths differ by {100 * (math.exp(raw) - 1):+.0f} % "
                "throughout the run: too much for a bias, every step is judged as measured"
            )
    systematic = abs(offset) > config.max_bias_log
    if systematic:
        warnings.append(
            f"laser template lengths (Eq. 17) run {100 * (math.exp(offset) - 1):+.0f} % off the "
            "feature depths on the light-section wall throughout the run: the scale is taken "
            "from the feature depths (steps still checked against the laser with that offset "
            "removed)"
        )
    return RunScale(offset, systematic)


def decide_step(ctx: SfmContext, kf: Keyframes, k: int, offset_log: float) -> DecidedStep:
    """Step ``k`` (keyframes k -> k + 1) decided with the run's source offset
    ``offset_log`` (:func:`source_offset`): its length, the matches to keep and the
    laser anchors to use; a resolved step (another consensus peak chosen) adds a
    warning."""
    ev = kf.evidence[k]
    if ev.status != "ok":
        return _unmeasured_step(ev)
    config = ctx.config
    lm = ev.laser
    gain = math.exp(offset_log)  # laser length = gain x feature depth length, run-wide
    check = decide(
        ev.a,
        ev.b,
        lm.scale,
        lm.peak_scales_mm,
        lm.peak_scores,
        ev.feature_scale_mm,
        ev.feature_matches,
        config.scale_check,
        gain,
    )
    scale = check.scale_mm
    if check.confidence == "resolved" or (
        check.confidence == "low" and not math.isfinite(lm.scale)
    ):
        # Re-match the laser around the chosen length: no point may pick another course.
        again = laser_around(ctx, kf, k, scale)
        if math.isfinite(again.scale):
            lm, scale = again, again.scale
        elif check.confidence == "resolved":
            lm = None
    elif check.confidence == "none" or check.reason.startswith(FEATURE_ONLY):
        lm = None  # its laser matches would pull the adjustment to a wrong length
    elif (
        check.confidence == "high"
        and math.isfinite(ev.feature_scale_mm)
        and abs(math.log(lm.scale / (gain * ev.feature_scale_mm)))
        > config.scale_check.anchor_agree_log
    ):
        # Agreeing within agree_log but not closely: part of the laser points took
        # another course (seen on tiles: laser +14.7 %, features +1.8 % of the true
        # step). The feature depths, whose median no single course dominates, give the
        # length; the laser's matches do not anchor the adjustment.
        scale, lm = gain * ev.feature_scale_mm, None
    inl = ev.inliers
    if math.isfinite(scale) and inl is not None:
        # Drop matches whose own depth ratio contradicts the length (a wrong course).
        expected = math.log(scale / gain)
        bad = np.isfinite(ev.log_scales) & (
            np.abs(ev.log_scales - expected) > config.scale_check.keep_match_log
        )
        inl = inl[~bad]
    if check.confidence == "resolved":  # the unreliable ones become stretches with a warning
        ctx.warnings.append(f"frames {ev.a}->{ev.b}: {check.reason}")
    return DecidedStep(ev.b_from_a.copy(), scale, inl, lm, check)


def _unmeasured_step(ev: StepEvidence) -> DecidedStep:
    """A rotation (trusted, no translation) or a lost step (no relative motion, or one
    not trusted: its ``lost_reason``)."""
    rotation = ev.status == "rotation"
    check = StepCheck(
        ev.a,
        ev.b,
        math.nan,
        0.0,
        math.nan,
        ev.feature_matches,
        0.0 if rotation else math.nan,
        "high" if rotation else "none",
        "" if rotation else ev.lost_reason or "relative motion not found",
    )
    return DecidedStep(ev.b_from_a.copy(), 0.0, ev.inliers, None, check)


def laser_around(ctx: SfmContext, kf: Keyframes, k: int, length_mm: float) -> LaserMatches:
    """Step k's laser points matched again (Eq. 17), searched only within
    ``scale_check.agree_log`` of ``length_mm``; both images divided by the step's flat
    field where the run has one (:mod:`omnipipe.sfm.flat_field`), as its evidence was."""
    ev, config = kf.evidence[k], ctx.config
    w = math.exp(config.scale_check.agree_log)
    field = kf.flats.get(k) if kf.flats is not None else None
    return match_laser_points(
        divided(kf.grays[k], field),
        divided(kf.grays[k + 1], field),
        ctx.camera,
        kf.ring_points[k],
        ev.b_from_a[:3, :3],
        ev.b_from_a[:3, 3],
        config.laser_scale,
        (length_mm / w, length_mm * w),
    )


def resolve_to(
    ctx: SfmContext,
    kf: Keyframes,
    decided: list[DecidedStep],
    lengths: np.ndarray,
    k: int,
    chosen: float,
    scale: RunScale,
    why: str,
    within: tuple[float, float] | None = None,
) -> None:
    """Step k resolved to ``chosen`` (mm, the chain's units) in place, ``why`` said in its
    reason and a warning: the laser re-matched around it (its length taken when found
    and, with ``within`` = (length, tolerance) in laser mm, within it; otherwise no laser
    anchors), the matches whose own depth ratio contradicts it dropped."""
    gain = math.exp(scale.offset_log)
    unit = gain if scale.wall_anchored else 1.0  # chain length = laser length / unit
    step, ev = decided[k], kf.evidence[k]
    c = step.check
    lm = laser_around(ctx, kf, k, chosen * unit)
    if within is not None and not abs(lm.scale - within[0]) <= within[1]:
        lm = replace(lm, scale=math.nan)
    if math.isfinite(lm.scale):
        chosen = lm.scale / unit
    inl = ev.inliers
    if inl is not None:
        expected = math.log(chosen * unit / gain)
        bad = np.isfinite(ev.log_scales) & (
            np.abs(ev.log_scales - expected) > ctx.config.scale_check.keep_match_log
        )
        inl = inl[~bad]
    reason = f"{c.reason}; resolved to {chosen:.1f} mm: {why}"
    ctx.warnings.append(f"frames {ev.a}->{ev.b}: {reason}")
    check = replace(c, scale_mm=chosen * unit, confidence="resolved", reason=reason)
    decided[k] = DecidedStep(
        step.b_from_a, chosen * unit, inl, lm if math.isfinite(lm.scale) else None, check
    )
    lengths[k] = chosen
