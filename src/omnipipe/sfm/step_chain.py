"""Keyframe steps made metric and chained, with their bundle adjustment anchors
(paper Sec. V-D).

:func:`chain_steps` decides every step (:mod:`omnipipe.sfm.step_decide`), lets the
other witnesses judge the flagged ones (:mod:`omnipipe.sfm.step_resolve`,
:mod:`omnipipe.sfm.wall_resolve`), bridges steps without a length from the odometry or
the gait (:func:`bridge_steps`, :func:`bridge_lost_steps`) and chains the poses; each
step's anchors are its laser matches or its features placed on the light-section wall
(:func:`wall_anchors`).

Conventions: poses world_from_kf (4, 4), mm, world = keyframe 0; lengths in the chain's
units (a wall-anchored chain: feature-depth units).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, replace

import numpy as np

from omnipipe.geometry import invert
from omnipipe.sfm.robot_sensors import (
    OdometrySteps,
    bridge_estimate,
    calibrate_odometry,
    odometry_disagreement,
)
from omnipipe.sfm.scale_check import (
    ScaleCheckConfig,
    StepCheck,
    bent_wall,
    wall_cylinder,
    wall_depth,
)
from omnipipe.sfm.step_decide import RunScale, decide_step
from omnipipe.sfm.step_resolve import confirm_by_gait, contradict_trusted, resolve_by_prior
from omnipipe.sfm.types import Anchor, Keyframes, PairMatches, SfmContext, StepEvidence
from omnipipe.sfm.wall_resolve import resolve_by_wall, wall_confirms_bridged
from omnipipe.spill import drop_pages

# Most wall-placed features per step used as anchors (evenly over the step's matches).
WALL_ANCHORS_PER_STEP = 120


@dataclass(frozen=True)
class ChainedSteps:
    """The keyframe steps made metric and chained (before the bundle adjustment).

    Attributes:
        world_from_kf: (K, 4, 4) chained keyframe poses, mm (world = keyframe 0).
        scales_mm: (K-1,) each step's chained length, mm.
        pair_matches: each step's inlier matches (the adjustment's tracks).
        anchors: each step's metric anchors (laser matches, or wall-placed features).
        checks: (K-1,) each step's decision.
    """

    world_from_kf: np.ndarray
    scales_mm: list[float]
    pair_matches: list[PairMatches]
    anchors: list[Anchor]
    checks: list[StepCheck]


def chain_steps(
    ctx: SfmContext,
    kf: Keyframes,
    scale: RunScale,
    odometry: OdometrySteps | None = None,
    counts: np.ndarray | None = None,
) -> ChainedSteps:
    """Every keyframe step decided (:func:`decide_step`) with the run's source offset,
    made metric and chained from keyframe 0; each step's inlier matches and metric
    anchors (its laser matches, or with ``scale.wall_anchored`` its features placed on
    the light-section wall) for the bundle adjustment.

    A step vision could not measure is bridged (:func:`bridge_steps`): its length comes
    from the odometry (calibrated against the trusted steps) or the gait, with a
    1-sigma, recorded in its check; it stays flagged. A step measured by its feature
    depths alone is trusted when its pace agrees with its neighbours'
    (:func:`confirm_by_gait`, ``counts``: (K-1,) moving frames per step,
    :func:`omnipipe.sfm.step_window.moving_counts`); a flagged step the wall's own shift
    decides is resolved (:func:`resolve_by_wall`; with odometry only where it agrees),
    and the frames inside it are placed by the wall too (:func:`omnipipe.sfm.creep.wall_resolved`)."""
    decided = [decide_step(ctx, kf, k, scale.offset_log) for k in range(len(kf.evidence))]
    gain = math.exp(scale.offset_log) if scale.wall_anchored else 1.0
    # Feature-depth units when the wall anchors (the laser's bias removed).
    lengths = np.array(
        [math.nan if ev.status == "lost" else d.scale_mm / gain for d, ev in zip(decided, kf.evidence, strict=True)],
        float,
    )
    if counts is not None:
        confirm_by_gait(ctx, decided, lengths, counts, kf.evidence)
    # With odometry, only where it agrees with the wall's reading (alone, the wall took
    # creeps of 1-2 mm for rest on a plain wall: seed 25s, 4 silent frame steps); the
    # frames inside a step it decides are placed by the wall too (sfm.creep.wall_resolved).
    agreed = resolve_by_wall(ctx, kf, decided, lengths, scale, counts, odometry)
    checks = [d.check for d in decided]
    if odometry is not None:
        trusted = np.array([c.reliable for c in checks], bool) & np.isfinite(lengths)
        odometry = calibrate_odometry(odometry, lengths, trusted)
    if odometry is not None:
        contradict_trusted(ctx, decided, lengths, odometry)
    resolve_by_prior(ctx, kf, decided, lengths, odometry, scale, counts)
    checks = [d.check for d in decided]
    lengths, checks, odometry = bridge_steps(lengths, checks, odometry, counts)
    wall_confirms_bridged(ctx, checks, lengths, agreed)
    scales: list[float] = []
    steps_b_from_a: list[np.ndarray] = []
    pair_matches: list[PairMatches] = []
    anchors: list[Anchor] = []
    for k, step in enumerate(decided):
        if k % DROP_EVERY_STEPS == DROP_EVERY_STEPS - 1:
            drop_pages()  # the steps' rings and features read so far (omnipipe.spill)
        length = float(lengths[k])
        scales.append(length)
        b_from_a = step.b_from_a.copy()
        b_from_a[:3, 3] *= length
        steps_b_from_a.append(b_from_a)
        if step.inliers is not None:
            pair_matches.append(PairMatches(k, k + 1, step.inliers))
        if scale.wall_anchored:
            # The laser's matches carry its bias: the wall itself anchors the scale.
            wall = wall_anchors(kf, k, length, ctx.config.scale_check)
            if wall is not None:
                anchors.append(wall)
        elif step.laser is not None and len(step.laser.index):
            lm, pts = step.laser, kf.ring_points[k][step.laser.index]
            anchors.append(Anchor(k, k + 1, pts, lm.pixels_b, np.log(lm.scale_mm), epipolar=True))
        elif step.check.reliable and length > 0:
            # Trusted on its feature depths alone (the laser's peaks ambiguous): its
            # wall-placed features anchor it, else the adjustment has no metric anchor
            # there (random-wide seed 3: skipped, no frame resected).
            wall = wall_anchors(kf, k, length, ctx.config.scale_check)
            if wall is not None:
                anchors.append(wall)
    bridge_lost_steps(steps_b_from_a, kf.evidence, checks, lengths)
    if odometry is not None:  # vision's trusted lengths (a bridged one is the odometry's)
        trusted = np.array([c.reliable and not c.bridged_from for c in checks], bool)
        ctx.warnings.extend(odometry_disagreement(odometry, lengths, trusted, kf.frames))
    world_from_kf = [np.eye(4)] if kf.frames else []
    for b_from_a in steps_b_from_a:
        world_from_kf.append(world_from_kf[-1] @ invert(b_from_a))
    return ChainedSteps(np.array(world_from_kf), scales, pair_matches, anchors, checks)


DROP_EVERY_STEPS = 32
"""Steps :func:`chain_steps` anchors between two :func:`omnipipe.spill.drop_pages`: the
pages of the keyframes' rings and features it reads are resident for that many steps,
not for the whole pass (which can take less than the dropping thread's interval)."""


def bridge_steps(
    lengths: np.ndarray,
    checks: list[StepCheck],
    odometry: OdometrySteps | None,
    counts: np.ndarray | None = None,
) -> tuple[np.ndarray, list[StepCheck], OdometrySteps | None]:
    """Lengths (K-1,) mm with every unmeasured one (NaN) bridged
    (:func:`omnipipe.sfm.robot_sensors.bridge_estimate`), the checks recording the
    bridge, and the odometry calibrated against the trusted steps."""
    lengths = np.array(lengths, float)
    trusted = np.array([c.reliable for c in checks], bool) & np.isfinite(lengths)
    if odometry is not None and not odometry.calibrated:
        odometry = calibrate_odometry(odometry, lengths, trusted)
    out = list(checks)
    for k in np.flatnonzero(~np.isfinite(lengths)):
        est, sigma, source = bridge_estimate(int(k), lengths, trusted, odometry, counts)
        if source:
            out[k] = replace(
                out[k],
                bridged_mm=est,
                bridged_sigma_mm=sigma,
                bridged_from=source,
                reason=f"{out[k].reason}; length bridged from the {source}: "
                f"{est:.1f} +- {sigma:.1f} mm".lstrip("; "),
            )
    for k in np.flatnonzero(~np.isfinite(lengths)):
        lengths[k] = out[k].bridged_mm if out[k].bridged_from else 0.0
    return lengths, out, odometry


def wall_anchors(kf: Keyframes, k: int, scale_mm: float, config: ScaleCheckConfig) -> Anchor | None:
    """Matched features of keyframe k placed on the light-section wall of its ring
    points: points in rig k, their pixels in keyframe k + 1 and each one's log length,
    as an anchor of step k; None if too few.

    Only matches whose own depth ratio agrees with the step's length ``scale_mm``
    (``keep_match_log``), at most :data:`WALL_ANCHORS_PER_STEP`.
    """
    ev, fa, fb = kf.evidence[k], kf.features[k], kf.features[k + 1]
    if (
        ev.inliers is None
        or not math.isfinite(scale_mm)
        or scale_mm <= 0
        or len(ev.log_scales) == 0
    ):
        return None
    # The wall bent by the step's axis turn per length (straight pipe: a cylinder).
    wall = bent_wall(
        wall_cylinder(kf.ring_points[k]), ev.b_from_a[:3, :3], ev.b_from_a[:3, 3], scale_mm
    )
    keep = np.isfinite(ev.log_scales) & (
        np.abs(ev.log_scales - math.log(scale_mm)) <= config.keep_match_log
    )
    idx = np.flatnonzero(keep)
    if wall is None or len(idx) < config.min_feature_matches:
        return None
    idx = idx[
        np.linspace(0, len(idx) - 1, min(WALL_ANCHORS_PER_STEP, len(idx))).round().astype(int)
    ]
    rays = fa.rays_in_rig[ev.inliers[idx, 0]]
    depth = wall_depth(rays, wall)
    ok = np.isfinite(depth)
    return Anchor(
        k,
        k + 1,
        rays[ok] * depth[ok, None],
        fb.pixels[ev.inliers[idx[ok], 1]],
        ev.log_scales[idx[ok]],
    )


def bridge_lost_steps(
    steps_b_from_a: list[np.ndarray],
    evidence: list[StepEvidence],
    checks: list[StepCheck],
    lengths: np.ndarray,
) -> None:
    """Give steps whose relative motion was not found their bridged length, in place.

    Such a step has no measurement at all (its check says so and the stretch is reported
    unreliable); chaining it as zero length would shorten everything after it. The robot
    moves along its own axis: no rotation, translation along the median direction of the
    trusted steps (rig -z, the way the world moves past a rig travelling along its +z,
    with fewer than 3), ``lengths[k]`` long (:func:`bridge_steps`: odometry or gait).

    Args:
        steps_b_from_a: (4, 4) rig_b_from_rig_a of every keyframe step, mm; lost ones are
            replaced.
        evidence, checks: the steps' evidence and decisions, same order.
        lengths: (K-1,) each step's length (mm), bridged ones included.
    """
    trusted = [
        t[:3, 3] / np.linalg.norm(t[:3, 3])
        for t, ev, c in zip(steps_b_from_a, evidence, checks, strict=True)
        if ev.status == "ok" and c.confidence == "high" and np.linalg.norm(t[:3, 3]) > 0
    ]
    direction = np.median(np.array(trusted), axis=0) if len(trusted) >= 3 else np.array([0, 0, -1.0])
    direction = direction / max(np.linalg.norm(direction), 1e-12)
    for k, ev in enumerate(evidence):
        if ev.status == "lost" and math.isfinite(lengths[k]):
            step = np.eye(4)
            step[:3, 3] = direction * lengths[k]
            steps_b_from_a[k] = step
            if checks[k].bridged_from:
                # Only the length is known (random-wide plain walls with odometry, e.g.
                # seed 34s: ATE 2.0 mm, 1.2 / 1.6 mm across the axis, 0.4 mm along it).
                checks[k] = replace(checks[k], reason=f"{checks[k].reason}{LOST_DIRECTION}")


# Said of a step without relative motion whose length was bridged: its direction and
# rotation are assumed, not measured.
LOST_DIRECTION = (
    " (its direction assumed along the robot's travel, its rotation zero: the rig's "
    "sideways shift and turn there are not measured)"
)
