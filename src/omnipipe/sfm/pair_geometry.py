"""The geometry of one step between two frames (:class:`~omnipipe.sfm.step_records.StepPair`).

Its relative motion on the matched rays (:func:`relative_motion`, RANSAC, Eq. 10-16),
the matches one motion explains (:func:`verified`), the rays' parallax with the rotation
removed (:func:`pair_parallax`, radians), the matches refined on projection planes
(:func:`refined_motion`, Sec. V-A) and the test of chained tracks against descriptor
matches on a periodic wall (:func:`skipped_period`). Rays are unit vectors in the rig
frame; matches (M, 2) (feature in a, feature in b) index pairs.
"""

from __future__ import annotations

import math

import numpy as np

from omnipipe.errors import ReconstructionError
from omnipipe.sfm.features import FrameFeatures
from omnipipe.sfm.planes import refine_matches
from omnipipe.sfm.ransac import RelativeMotion, estimate_relative_motion
from omnipipe.sfm.step_records import StepPair
from omnipipe.sfm.tasks import verified_matches
from omnipipe.sfm.tracking import TrackConfig
from omnipipe.sfm.types import SfmContext


def relative_motion(ctx: SfmContext, pair: StepPair) -> RelativeMotion | None:
    """Relative motion of frame b from keyframe a on the matched rays, or None (with a
    warning)."""
    m = pair.matches
    try:
        return estimate_relative_motion(
            pair.features_a.rays_in_rig[m[:, 0]], pair.features_b.rays_in_rig[m[:, 1]], ctx.ransac
        )
    except ReconstructionError as exc:
        ctx.warnings.append(f"frames {pair.a}->{pair.b}: {exc}; pose kept from frame {pair.a}")
        return None


def verified(ctx: SfmContext, fa: FrameFeatures, fb: FrameFeatures, m: np.ndarray) -> np.ndarray:
    """The matches ``m`` (M, 2) one relative motion explains (RANSAC inliers; none when
    no motion fits; :func:`omnipipe.sfm.tasks.verified_matches`)."""
    return verified_matches(fa, fb, m, ctx.ransac)


def skipped_period(
    feature: np.ndarray,
    track_rays: np.ndarray,
    matches: np.ndarray,
    features_b: FrameFeatures,
    tolerance_rad: float,
    config: TrackConfig,
) -> bool:
    """True when the tracks of keyframe features ``feature`` (P,), at ``track_rays``
    (P, 3) in frame b, and RANSAC-verified descriptor ``matches`` (M, 2) into
    ``features_b`` disagree: of at least ``config.min_tracks`` features both found, at
    most half are within ``tolerance_rad`` of each other (a track that jumped a period
    of a periodic wall lands a period from its descriptor match)."""
    pos = {int(f): i for i, f in enumerate(feature)}
    common = [(pos[int(a)], int(b)) for a, b in matches if int(a) in pos]
    if len(common) < config.min_tracks:
        return False
    t, b = np.array(common).T
    cos = np.sum(track_rays[t] * features_b.rays_in_rig[b], axis=1)
    return bool(np.mean(cos > math.cos(tolerance_rad)) <= 0.5)


def pair_parallax(pair: StepPair, motion: RelativeMotion) -> float:
    """Median angle (rad) between matched rays once the rotation is removed."""
    inl = pair.matches[motion.inliers]
    if len(inl) == 0:
        return 0.0
    R = motion.rig2_from_rig1[:3, :3]
    ra = pair.features_a.rays_in_rig[inl[:, 0]] @ R.T
    rb = pair.features_b.rays_in_rig[inl[:, 1]]
    return float(np.median(np.arccos(np.clip(np.sum(ra * rb, axis=1), -1.0, 1.0))))


def refined_motion(
    ctx: SfmContext, pair: StepPair, motion: RelativeMotion, gray_a: np.ndarray, gray_b: np.ndarray
) -> RelativeMotion:
    """Paper Sec. V-A: refine frame b's matched rays on projection planes (in place),
    re-estimate the motion (kept when that fails)."""
    inl = pair.matches[motion.inliers]
    fa, fb = pair.features_a, pair.features_b
    refined = refine_matches(
        np.asarray(gray_a, np.float32),
        np.asarray(gray_b, np.float32),
        ctx.camera,
        fa.rays_in_rig[inl[:, 0]],
        fb.rays_in_rig[inl[:, 1]],
        motion.rig2_from_rig1,
        ctx.config.planes,
    )
    fb.rays_in_rig[inl[:, 1]] = refined
    fb.pixels[inl[:, 1]] = ctx.camera.project(refined)[0]
    again = relative_motion(ctx, pair)
    return again if again is not None else motion
