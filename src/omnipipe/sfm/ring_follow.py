"""Frames whose relative motion vision could not measure, turned by the gyro and placed
across the pipe by the laser ring's centre.

On a plain wall a keyframe step without relative motion is bridged: its length from the
odometry, its rotation zero and its direction along the robot's travel
(:func:`omnipipe.sfm.step_chain.bridge_lost_steps`). The robot turns there by a degree
or two and wanders sideways by millimetres (random-wide seed 34 with sensors, 180 mm:
5.6 mm over 41 mm of travel, 2.3 deg; ATE 2.0 mm, 14 mm per 300 mm). Both are measured
by what the robot still has:

* the gyro (``imu.txt``'s ``wx wy wz``, rad/s in the rig frame), integrated between the
  frames: rig_a_from_rig_b over a stretch of seconds to a tenth of a degree (its bias,
  not its noise);
* the laser ring: the laser plane cuts the pipe's wall in an ellipse whose centre lies
  on the pipe's axis whatever the rig's tilt, measured from hundreds of points (0.02 mm
  on a 180 mm pipe at 640x480; about 1 mm on a 960 mm one).

With the frames' rotations R_i and ring centres c_i (rig frame), a straight pipe's axis
(point a, direction u) holds every frame's centre: p_i + R_i c_i = a + s_i u, so

    p_i = p_f + R_f c_f - R_i c_i + s_i u,

f the stretch's first frame (its pose kept), s_i the frame's travel along the axis (the
bridged chain's, from the odometry). The axis direction u is the rig's mean axis over
the stretch (R_i's z); where the gyro shows the rig turning through a bend, the axis
turns with it (:func:`axis_directions`) and the centres follow it step by step. A tilt
of the robot in the pipe is not measured (the ring's ellipse shows its size but not its
sign), so it is stated: the stretch stays flagged, its reason saying what was measured
and what assumed. Frames after the stretch keep their poses relative to its last frame.

Conventions: world = rig frame of frame 0, poses world_from_rig (4, 4), mm, radians.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import replace

import numpy as np

from omnipipe.inputs.sensors import odometry_at
from omnipipe.sfm.ring_axis import robust_ellipse_centre
from omnipipe.sfm.robot_sensors import CREEP_MIN_MM
from omnipipe.sfm.rotation_check import gyro_rotations
from omnipipe.sfm.scale_check import TRACKED_MIN_MATCHES, StepCheck, UnreliableStretch
from omnipipe.sfm.step_chain import LOST_DIRECTION
from omnipipe.sfm.types import SfmInputs, SfmResult

# Fewest accepted ring points for a centre (a conic has five parameters; the robust
# passes drop defects and water).
MIN_RING_POINTS = 50
# The conic's outlier floor (mm): ring points beyond it and ring_axis.RING_OUTLIER_SIGMAS
# robust sigmas are dropped, in ring_axis.RING_PASSES passes.
RING_OUTLIER_FLOOR_MM = 0.3
# Fewest frames of a stretch with a ring centre of their own for the others' to be
# interpolated.
MIN_KNOWN_CENTRES = 3
# Smallest turn (deg) of the rig's z axes over an unmeasured stretch taken for the pipe
# bending (:func:`axis_directions`): the robot's tilt wobbles by about a degree in
# straight pipe (the simulator's 0.8 deg).
MIN_FOLLOWED_TURN_DEG = 3.0

# Said of a bridged stretch whose frames the gyro turned and the ring centres placed.
FOLLOWED = (
    " (its turn from the gyro and its sideways shift from the laser ring's centre; its "
    "direction along the rig's axes where the gyro shows a bend, else along their mean: "
    "the robot's tilt in the pipe is not measured)"
)


def ring_centre(points_in_rig: np.ndarray) -> np.ndarray | None:
    """(3,) the centre of one frame's laser ring in the rig frame (mm): where the pipe's
    axis pierces the laser plane.

    A tilted cylinder cuts the plane in an ellipse: a general conic
    ``a x^2 + b xy + c y^2 + d x + e y = 1`` is fitted in the plane's own 2-D basis (the
    points' principal directions), points beyond :data:`~omnipipe.sfm.ring_axis.RING_OUTLIER_SIGMAS`
    robust sigmas of it (defects, water, spurious peaks) dropped over
    :data:`~omnipipe.sfm.ring_axis.RING_PASSES` passes
    (:func:`~omnipipe.sfm.ring_axis.robust_ellipse_centre`). None with fewer than :data:`MIN_RING_POINTS` points or no ellipse.
    """
    fit = robust_ellipse_centre(points_in_rig, MIN_RING_POINTS, RING_OUTLIER_FLOOR_MM)
    return None if fit is None else fit[0]


def unmeasured(check: StepCheck) -> bool:
    """A keyframe step bridged without relative motion (its reason carries
    :data:`~omnipipe.sfm.step_chain.LOST_DIRECTION`), or bridged with a relative motion
    from fewer than :data:`~omnipipe.sfm.scale_check.TRACKED_MIN_MATCHES` matches (a
    plain wall's: random-wide seed 34 with sensors, its last step from 34 matches turned
    0.8 deg and slid 2.4 mm sideways)."""
    return bool(check.bridged_from) and (
        LOST_DIRECTION in check.reason or check.feature_matches < TRACKED_MIN_MATCHES
    )


def followed_reason(reason: str) -> str:
    """A placed step's reason: :data:`FOLLOWED` instead of (or after) what was assumed."""
    return (
        reason.replace(LOST_DIRECTION, FOLLOWED) if LOST_DIRECTION in reason else reason + FOLLOWED
    )


def unmeasured_stretches(checks: Sequence[StepCheck]) -> list[tuple[int, int]]:
    """(first frame, last frame) of each run of consecutive :func:`unmeasured` keyframe
    steps, in frame order."""
    out: list[tuple[int, int]] = []
    for c in sorted(checks, key=lambda c: c.first_frame):
        if not unmeasured(c):
            continue
        if out and out[-1][1] == c.first_frame:
            out[-1] = (out[-1][0], c.last_frame)
        else:
            out.append((c.first_frame, c.last_frame))
    return out


def follow_rings(
    world_from_rig: np.ndarray,
    stationary: np.ndarray,
    stretches: Sequence[tuple[int, int]],
    rotations: np.ndarray,
    centres: Sequence[np.ndarray | None],
    travel_mm: np.ndarray | None = None,
) -> tuple[np.ndarray, np.ndarray, list[tuple[int, int]]]:
    """Every frame's pose with the frames of ``stretches`` turned by ``rotations`` and
    placed across the axis by their ring ``centres`` (module docstring); the frames after
    a stretch moved with its last frame.

    Args:
        world_from_rig: (N, 4, 4) poses (the bridged chain's).
        stationary: (N,) frames that keep their predecessor's pose.
        stretches: (first, last) frames of the unmeasured stretches, in order.
        rotations: (N, 3, 3) rig_first_from_rig from the gyro.
        centres: per frame the ring centre (3,) in the rig frame, or None.
        travel_mm: (N,) the odometry's travel at each frame (mm), or None. With it a
            stretch's frames lie along its chained length in the odometry's proportions,
            and a stationary frame the odometry counted :data:`CREEP_MIN_MM` past its
            predecessor moves (a plain wall hides creeps from the stationary test:
            random-wide seed 10 with sensors, 0.4-0.5 mm frame steps taken for rest);
            without it, in the chain's.

    Returns:
        The new poses (N, 4, 4), the new stationary flags (N,) and the stretches that
        were placed (one whose frames lack a ring centre, or that does not travel, is
        left as it was).
    """
    old = np.asarray(world_from_rig, float)
    new = old.copy()
    still = np.asarray(stationary, bool).copy()
    fix = np.eye(4)  # new_from_old of the frames after the last placed stretch
    done: list[tuple[int, int]] = []
    start = 0
    for fa, fb in stretches:
        new[start:fa] = fix[None] @ old[start:fa]
        frames = np.arange(fa, fb + 1)
        anchor = fix @ old[fa]
        travel = old[fb, :3, 3] - old[fa, :3, 3]
        length = float(np.linalg.norm(travel))
        rot = anchor[:3, :3][None] @ (rotations[fa].T[None] @ rotations[frames])
        c = _filled(centres, frames, rot, travel_mm)
        if c is None or length < 1e-6:
            new[fa : fb + 1] = fix[None] @ old[fa : fb + 1]
            start = fb + 1
            continue
        s = (old[frames, :3, 3] - old[fa, :3, 3]) @ (travel / length)
        odo = None if travel_mm is None else travel_mm[frames] - travel_mm[fa]
        if odo is not None and np.isfinite(odo).all() and odo[-1] > 0:
            s = odo * (s[-1] / odo[-1])
            moving = np.abs(np.diff(odo)) * (s[-1] / odo[-1]) >= CREEP_MIN_MM
            still[frames[1:]] &= ~moving
        # The rings' axis points lie ahead of (or behind) their rigs along the pipe by
        # their centres' depth along the rig's z; where the pipe bends, the axis turns
        # there as it turns at the rig that far on.
        forward = 1.0 if rot[:, :, 2].mean(axis=0) @ (fix[:3, :3] @ travel) >= 0 else -1.0
        u = forward * axis_directions(rot[:, :, 2], s, s + forward * c[:, 2])
        on_axis = anchor[:3, 3] + anchor[:3, :3] @ c[0]
        pos = axis_points(on_axis, u, s) - np.einsum("nij,nj->ni", rot, c)
        for j, i in enumerate(frames):
            if j and still[i]:
                new[i] = new[i - 1]
                continue
            new[i, :3, :3], new[i, :3, 3] = rot[j], pos[j]
        fix = new[fb] @ np.linalg.inv(old[fb])
        done.append((fa, fb))
        start = fb + 1
    new[start:] = fix[None] @ old[start:]
    return new, still, done


def axis_directions(rig_z: np.ndarray, s: np.ndarray, at: np.ndarray | None = None) -> np.ndarray:
    """(n, 3) the pipe axis' unit direction (world frame) at travel ``at`` (n,) mm (None:
    ``s``) from a stretch's rig z axes ``rig_z`` (n, 3) (world_from_rig's third column,
    the gyro's turn) at their travel ``s`` (n,) mm.

    The robot rides along the pipe, so where the pipe bends its rig turns with it: the
    z axes' straight-line fit in the travel (normalised) follows an elbow's turn, the
    rig's tilt in the pipe staying as it was (not measured: the same assumption as in
    straight pipe); evaluated at ``at``, where the laser ring cuts the axis (the rig
    turns there that much further on). Only a turn that stands out of the rig's wobble
    is followed: the fit's turn over the stretch at least :data:`MIN_FOLLOWED_TURN_DEG`
    and 3 x the z axes' rms scatter about the fit (rad); otherwise the axis is straight
    along the z axes' mean (a degree of wobble taken for a bend would swing a 50 mm
    stretch's positions by tenths of a mm)."""
    z = np.asarray(rig_z, float)
    s = np.asarray(s, float)
    mean = z.mean(axis=0) / np.linalg.norm(z.mean(axis=0))
    straight = np.tile(mean, (len(z), 1))
    x = s - float(np.mean(s))
    if len(z) < 3 or float(x @ x) <= 0:
        return straight
    slope = (x @ (z - z.mean(axis=0))) / float(x @ x)
    fit = z.mean(axis=0)[None] + x[:, None] * slope[None]
    scatter = float(np.sqrt(np.mean(np.sum((z - fit) ** 2, axis=1))))
    ends = fit[[int(np.argmin(s)), int(np.argmax(s))]]
    ends /= np.linalg.norm(ends, axis=1, keepdims=True)
    turn = math.acos(float(np.clip(ends[0] @ ends[1], -1.0, 1.0)))
    if turn < max(math.radians(MIN_FOLLOWED_TURN_DEG), 3.0 * scatter):
        return straight
    xa = (s if at is None else np.asarray(at, float)) - float(np.mean(s))
    out = z.mean(axis=0)[None] + xa[:, None] * slope[None]
    return out / np.linalg.norm(out, axis=1, keepdims=True)


def axis_points(start: np.ndarray, u: np.ndarray, s: np.ndarray) -> np.ndarray:
    """(n, 3) points along an axis from ``start`` (3,), the first frame's, with unit
    directions ``u`` (n, 3) at travel ``s`` (n,) mm: each step along its ends' mean
    direction (a bend's chord)."""
    start = np.asarray(start, float)
    if len(s) < 2:
        return np.tile(start, (len(s), 1))
    mid = 0.5 * (u[1:] + u[:-1])
    mid /= np.maximum(np.linalg.norm(mid, axis=1, keepdims=True), 1e-12)
    steps = np.diff(np.asarray(s, float))[:, None] * mid
    return start[None] + np.vstack([np.zeros(3), np.cumsum(steps, axis=0)])


def _filled(
    centres: Sequence[np.ndarray | None],
    frames: np.ndarray,
    rot: np.ndarray,
    travel_mm: np.ndarray | None = None,
) -> np.ndarray | None:
    """(len(frames), 3) the frames' ring centres in their rig frames; a missing one (a
    frame whose ring the decoding pass did not extract: one it took for standing, though
    the odometry moved it) interpolated between its neighbours' (before the first and
    after the last one: theirs) as a world-frame vector (``rot`` (len(frames), 3, 3):
    the frames' world_from_rig rotations; the rig's wobble turns its rig-frame centre,
    the camera's offset from the axis varies smoothly), in the odometry's travel
    (``travel_mm`` (N,)) when it increases over the stretch, else in frame order. None
    when fewer than :data:`MIN_KNOWN_CENTRES` of its frames have one. On a plain wall
    the decoding pass takes most frames for standing (random-wide seed 34 with sensors:
    7 rings in 32 frames; at "half its frames" the stretch was left unplaced: ATE 13.4
    mm per 300 mm on the user's path, 3.85 with every ring)."""
    have = np.array([centres[i] is not None for i in frames])
    if have.sum() < min(MIN_KNOWN_CENTRES, len(frames)):
        return None
    known = np.einsum("nij,nj->ni", rot[have], np.array([centres[i] for i in frames[have]]))
    x = np.arange(len(frames), dtype=float)
    if travel_mm is not None:
        d = np.asarray(travel_mm, float)[frames]
        if np.isfinite(d).all() and (np.diff(d) >= 0).all() and d[-1] > d[0]:
            x = d
    world = np.column_stack([np.interp(x, x[have], known[:, k]) for k in range(3)])
    out = np.einsum("nji,nj->ni", rot, world)  # back to each rig frame
    out[have] = np.array([centres[i] for i in frames[have]])
    return out


def followed_reasons(
    unreliable: Sequence[UnreliableStretch],
    stretches: Sequence[tuple[int, int]],
    done: Sequence[tuple[int, int]],
) -> list[UnreliableStretch]:
    """The unreliable stretches, with the bridged steps' reason saying what the gyro and
    the ring measured (:data:`FOLLOWED`) where every unmeasured stretch inside is placed."""
    out = []
    for u in unreliable:
        inside = [s for s in stretches if u.first_frame <= s[0] and s[1] <= u.last_frame]
        if inside and all(s in done for s in inside):
            u = replace(u, reason=followed_reason(u.reason))
        out.append(u)
    return out


def add_ring_follow(result: SfmResult, inputs: SfmInputs) -> None:
    """With a gyro: the frames of the keyframe steps bridged without relative motion
    turned by it and placed across the axis by their ring centres
    (:func:`follow_rings`), in place; those stretches stay flagged, their reasons (and
    their steps' checks) saying what was measured."""
    if inputs.imu is None or inputs.timestamps is None:
        return
    stretches = unmeasured_stretches(result.step_checks)
    if not stretches:
        return
    rotations = gyro_rotations(inputs.imu, inputs.timestamps)
    if rotations is None:
        return
    wanted = {i for fa, fb in stretches for i in range(fa, fb + 1)}
    centres = [
        ring_centre(inputs.rings.rings[i].points_in_rig)
        if i in wanted and result.registered[i]
        else None
        for i in range(inputs.n_frames)
    ]
    travel = None
    if inputs.odometry is not None:
        travel = odometry_at(inputs.odometry, inputs.timestamps)[0]
    poses, still, done = follow_rings(
        result.world_from_rig, result.stationary, stretches, rotations, centres, travel
    )
    if not done:
        return
    result.world_from_rig = poses
    result.stationary = still
    result.station = np.cumsum(~still) - 1
    result.unreliable = followed_reasons(result.unreliable, stretches, done)
    result.step_checks = [
        replace(c, reason=followed_reason(c.reason))
        if unmeasured(c) and any(fa <= c.first_frame and c.last_frame <= fb for fa, fb in done)
        else c
        for c in result.step_checks
    ]
