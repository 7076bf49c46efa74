"""Frames taken for standing that the odometry counted creeping: placed by the wall's own
shift, else by the odometry.

With odometry the decoding pass's stationary test still decides which frames stand; a
frame whose image barely changed keeps its station's pose even where the odometry
counted it creeping past :data:`~omnipipe.sfm.robot_sensors.CREEP_MIN_MM` and its noise
(:func:`~omnipipe.sfm.robot_sensors.odometry_creeps`). Those stations were flagged and
left standing: random-wide seed 24 with sensors (joints, 644 mm, a robot creeping 0.2-0.9
mm a frame) had every frame step flagged, the creeps landing in the next moving frame's
step (ATE 6.5 mm per 300 mm; without odometry, where the wall's shift places the same
frames, 3.8). The flag was true (the frames did creep) but the odometry's count was
thrown away. Each such station is now:

1. measured by the wall's shift (:func:`omnipipe.sfm.creep.place_creeps`, the keyframe
   step around it as the ruler) as the run without odometry measures a stretch the
   stationary test cannot verify: placed, and no longer flagged, when every frame step
   is read and the gain test passes;
2. else placed by the odometry: each of its frames at its fraction of the odometry's
   travel between the station's first frame and the next moving frame (rotation
   slerped), flagged with a reason that says so.

Conventions: world = rig frame of frame 0, poses world_from_rig (4, 4), mm.
"""

from __future__ import annotations

import math
from collections.abc import Callable

import numpy as np

from omnipipe.camera import CameraModel
from omnipipe.geometry import interpolated_pose
from omnipipe.inputs.sensors import Odometry, odometry_at
from omnipipe.sfm.adjust import travel_fraction
from omnipipe.sfm.creep import place_creeps
from omnipipe.sfm.robot_sensors import odometry_creeps
from omnipipe.sfm.scale_check import UnreliableStretch, WallCylinder, merge_stretches
from omnipipe.sfm.types import SfmResult

# How a creeping station the wall's shift could not place within its bound was placed.
BY_ODOMETRY = "its frames placed by the odometry (the wall's own shift could not place them)"
BY_WALL_UNBOUND = (
    "its frames placed by the wall's own shift, whose frame steps are not bound within "
    "the stationary test's limit"
)
LEFT_STANDING = "it may have crept"


def creep_reason(travel_mm: float, how: str) -> str:
    """The flag of a creeping station (``how``: :data:`BY_ODOMETRY`,
    :data:`BY_WALL_UNBOUND` or :data:`LEFT_STANDING`)."""
    return f"the odometry counted {travel_mm:.1f} mm at a frame taken for standing: {how}"


def widened(
    spans: list[tuple[int, int, float]], keyframes: np.ndarray, n: int
) -> list[tuple[int, int, float]]:
    """Each (first, last, mm) station widened to the keyframes around it (``keyframes``
    (N,) bool; the run's last frame after the last keyframe), with an unbounded hidden
    step (the wall's window spans the keyframe step)."""
    kfs = np.flatnonzero(keyframes)
    out = []
    for f, end, _ in spans:
        before, after = kfs[kfs <= f], kfs[kfs >= end]
        a = int(before[-1]) if len(before) else int(f)
        b = int(after[0]) if len(after) else n - 1
        if (a, b, math.inf) not in out:
            out.append((a, b, math.inf))
    return out


def odometry_placed(
    world_from_rig: np.ndarray,
    stationary: np.ndarray,
    travel_mm: np.ndarray,
    first: int,
    end: int,
) -> np.ndarray | None:
    """(N, 4, 4) the poses with station ``first``'s frames first+1 .. end-1 placed at
    their fraction of ``travel_mm`` (N,) between frame ``first`` and frame ``end`` (the
    next moving frame), or None when the odometry does not increase there or ``end`` is
    not a moving frame (the run's last station: no pose after it to place towards)."""
    if stationary[end] or end <= first + 1:
        return None
    pose = np.array(world_from_rig, float, copy=True)
    for i in range(first + 1, end):
        f = travel_fraction(travel_mm, first, end, i)
        if f is None:
            return None
        pose[i] = interpolated_pose(world_from_rig[first], world_from_rig[end], f)
    return pose


def place_odometry_creeps(
    result: SfmResult,
    odometry: Odometry,
    timestamps: np.ndarray,
    camera: CameraModel,
    read_gray: Callable[[int], np.ndarray],
    read_wall: Callable[[int], WallCylinder | None],
    warnings: list[str],
) -> None:
    """The stations the ``odometry`` counted creeping (``timestamps`` (N,) s: the
    frames'), placed by the wall's shift or by the odometry (module docstring), in
    ``result``; those the wall could not place flagged, and a warning for those it did.

    Args:
        read_gray: frame index -> its (H, W) grey image without the laser.
        read_wall: frame index -> its wall cylinder (rig frame), None without one.
    """
    t = np.asarray(timestamps, float)
    creeps = odometry_creeps(odometry, t, ~result.stationary)
    if not creeps:
        return
    n = len(result.stationary)
    crept = place_creeps(
        widened(creeps, result.keyframe, n), ~result.stationary, result.world_from_rig,
        result.registered, read_gray, read_wall, camera, result.scale_sigma_rel,
    )
    pose, moved = crept.world_from_rig, crept.moved
    by_wall = [(a, b) for a, b in crept.placed if not any(u[:2] == (a, b) for u in crept.unverified)]
    warnings.extend(
        f"frames {a}->{b}: the frames the odometry counted creeping placed by the wall's own shift"
        for a, b in by_wall
    )
    travel = odometry_at(odometry, t)[0]
    stretches = []
    flagged = [(c.first_frame, c.last_frame) for c in result.step_checks if not c.reliable]
    for f, end, mm in creeps:
        if any(a <= f and end <= b for a, b in by_wall):
            continue
        how = BY_WALL_UNBOUND if any(a <= f and end <= b for a, b in crept.placed) else LEFT_STANDING
        if how == LEFT_STANDING and result.registered[f : end + 1].all():
            placed = odometry_placed(pose, ~moved, travel, f, end)
            if placed is not None:
                pose, how = placed, BY_ODOMETRY
                moved[f + 1 : end] = np.abs(np.diff(travel[f:end])) > 0
        if any(a <= f and end <= b for a, b in flagged):
            # Inside a keyframe step flagged for its own reason (random-wide seed 34s,
            # a plain wall: every step bridged from the odometry, whose creep flags came
            # first in the merged stretches' reasons): said, not flagged twice.
            warnings.append(f"frames {f}->{end}: {creep_reason(mm, how)}")
        else:
            stretches.append(UnreliableStretch(f, end, creep_reason(mm, how)))
    result.world_from_rig = pose
    result.stationary = ~moved
    result.station = np.cumsum(moved) - 1
    if stretches:
        result.unreliable = merge_stretches(list(result.unreliable) + stretches)
