"""Whether a keyframe step's relative motion (its direction and turn) can be trusted.

One decision, made before the steps' lengths are decided and the same with or without
the robot's sensors: those may replace what vision cannot give, not change what it
gives. A step's relative motion (RANSAC on the rays, Eq. 10-16) rests on its inlier
matches; on a wall without texture (:func:`run_texture` below
:data:`~omnipipe.sfm.flow_contrast.TEXTURE_FLOOR`: the views' own local contrast, before
any stretch) a few dozen of them are tracks on the wall's shading and the sensor's
noise, whose own best motion is the wrong turn. Such a step with fewer than
:data:`MOTION_MIN_INLIERS` inliers is treated as one whose relative motion was not
found (:func:`untrusted_motions`): no direction, turn or length is taken from it; it is
bridged (the odometry's length, the gyro's turn and the laser ring's centre with the
robot's sensors; the gait without) and flagged, and a run left without a trusted step
is refused in one line (:func:`omnipipe.pipeline.quality.refuse_untrusted_motion`).

The bar and the floor, measured on the random-wide bench: benchmarks/RESULTS.md (feat26).
"""

from __future__ import annotations

import math
from dataclasses import replace

import numpy as np

from omnipipe.camera import camera_from_rig
from omnipipe.sfm.features import FeatureExtractor
from omnipipe.sfm.flow_contrast import TEXTURE_FLOOR, wall_texture
from omnipipe.sfm.scale_check import TRACKED_MIN_MATCHES
from omnipipe.sfm.step_records import Followed
from omnipipe.sfm.types import SfmConfig, SfmContext, SfmInputs, StepEvidence

# Fewest RANSAC inliers of a step whose relative motion is trusted on a wall below the
# texture floor: the bar a feature-depth length alone is trusted at, and the one below
# which a bridged step's direction is taken from the gyro and the ring
# (:func:`omnipipe.sfm.ring_follow.unmeasured`).
MOTION_MIN_INLIERS = TRACKED_MIN_MATCHES
# A trusted step on such a wall with fewer inliers than this has its direction stated
# to DIRECTION_SIGMA_DEG only (:func:`untrusted_motions`' warning; the directions
# measured against the inliers: benchmarks/RESULTS.md, mot32's entry).
DIRECTION_MIN_INLIERS = 300
DIRECTION_SIGMA_DEG = 2.0


def run_texture(config: SfmConfig, inputs: SfmInputs) -> float:
    """The run's wall texture: the median over its first, middle and last frames of
    :func:`~omnipipe.sfm.flow_contrast.wall_texture` (their perspective views before
    CLAHE, the laser's band masked); NaN when no frame has a view pixel."""
    extractor = FeatureExtractor(camera_from_rig(inputs.rig), replace(config.features, flow_plain=True))
    rings, n = inputs.rings.rings, inputs.n_frames
    spreads = []
    for i in sorted({0, n // 2, n - 1}):
        views = extractor.frame_views(inputs.read_frame(i), inputs.rig.laser.channel, rings[i].pixels)
        spreads.append(wall_texture(views.plain, views.masks))
    finite = [v for v in spreads if math.isfinite(v)]
    return float(np.median(finite)) if finite else math.nan


def untrusted_motions(ctx: SfmContext, inputs: SfmInputs, followed: Followed) -> None:
    """The steps whose relative motion rests on fewer than :data:`MOTION_MIN_INLIERS`
    inliers on a wall below the texture floor, made lost in place (their evidence
    :meth:`~omnipipe.sfm.types.StepEvidence.unmeasured` with the reason in ``lost_reason``,
    their later keyframe in ``followed.lost``), each with a warning; the steps kept with
    fewer than :data:`DIRECTION_MIN_INLIERS` there get a warning stating their direction
    to :data:`DIRECTION_SIGMA_DEG` (the rig's position across the pipe uncertain by that
    angle's share of the step's length). The frames are read (:func:`run_texture`) only
    when some step has so few inliers."""
    kf = followed.keyframes
    counts = {
        k: len(ev.inliers) for k, ev in enumerate(kf.evidence)
        if ev.status == "ok" and ev.inliers is not None and len(ev.inliers) < DIRECTION_MIN_INLIERS
    }
    if not counts:
        return
    texture = run_texture(ctx.config, inputs)
    if not texture < TEXTURE_FLOOR:
        return
    for k, n in counts.items():
        ev = kf.evidence[k]
        if n >= MOTION_MIN_INLIERS:
            ctx.warnings.append(
                f"frames {ev.a}->{ev.b}: the step's direction rests on {n} matches (fewer than "
                f"{DIRECTION_MIN_INLIERS}) on a wall of local contrast {texture:.2f} (below "
                f"{TEXTURE_FLOOR}): stated to +-{DIRECTION_SIGMA_DEG:g} deg only, the rig's "
                f"position across the pipe uncertain by up to "
                f"{100 * math.tan(math.radians(DIRECTION_SIGMA_DEG)):.1f} % of the step's length"
            )
            continue
        why = (
            f"relative motion not trusted: {n} matches (fewer than "
            f"{MOTION_MIN_INLIERS}) on a wall of local contrast {texture:.2f} (below "
            f"{TEXTURE_FLOOR}): its direction and turn are not measured"
        )
        ctx.warnings.append(f"frames {ev.a}->{ev.b}: {why}")
        kf.evidence[k] = replace(
            StepEvidence.unmeasured(ev.a, ev.b, np.eye(4), None, "lost"),
            feature_matches=ev.feature_matches,
            lost_reason=why,
        )
        followed.lost[ev.b] = True
