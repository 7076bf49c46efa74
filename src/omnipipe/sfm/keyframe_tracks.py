"""The chaining of keyframe steps: the last keyframe's features followed frame to frame.

:class:`KeyframeTracks` holds the last keyframe's :class:`~omnipipe.sfm.tracking.TrackChain`
and follows it into each moving frame's views (a
:class:`~omnipipe.sfm.step_records.TrackedStep`: the tracks, their RANSAC-verified
matches, their parallax in radians with the rotation removed); tells the keyframe
decision's threshold (``keyframe_min_parallax_deg``, half that when the tracks run
out); and gives a new keyframe's features (tracks carried on first, then its SIFT
features and corners) and its matches to the last keyframe: descriptor matches over
the whole frame, guided by the tracks, or the tracks themselves, whichever verified
best; on a periodic wall whose tracks skipped a period, SIFT from then on.
"""

from __future__ import annotations

import math
from collections.abc import Callable

import numpy as np
from scipy.spatial import cKDTree

from omnipipe.errors import ReconstructionError
from omnipipe.sfm.features import (
    FeatureExtractor,
    FrameFeatures,
    concat_features,
    guided_matches,
    match_features,
)
from omnipipe.sfm.keyframe_jobs import budget, subset
from omnipipe.sfm.pair_geometry import pair_parallax, skipped_period, verified
from omnipipe.sfm.ransac import estimate_relative_motion
from omnipipe.sfm.step_records import LastKeyframe, MovingFrame, StepPair, TrackedStep
from omnipipe.sfm.tracking import TrackChain, keyframe_detection
from omnipipe.sfm.types import SfmContext


class KeyframeTracks:
    """The last keyframe's features followed frame to frame (:attr:`chain`; None:
    tracking off), the keyframe decision's parallax threshold (rad) and a new
    keyframe's features and matches to the last one. ``ctx.config.tracking`` and
    ``keyframe_min_parallax_deg`` set them; ``extractor`` detects the features."""

    def __init__(self, ctx: SfmContext, extractor: FeatureExtractor) -> None:
        self.ctx = ctx
        self.extractor = extractor
        self._min_parallax = math.radians(ctx.config.keyframe_min_parallax_deg)
        self.step_inliers = 0  # verified matches of the last keyframe step
        # The last keyframe's tracks, followed frame to frame (None: tracking off).
        self.chain: TrackChain | None = None
        # SIFT on every moving frame (once the chained tracks were found to skip a
        # period of the wall).
        self.direct = False
        # A new feature this close (rad) to a track carried on is that track.
        self._near = 2.0 * ctx.camera.angular_resolution()

    def start(self, frame: MovingFrame, features: FrameFeatures, n_continued: int) -> None:
        """The new keyframe's features followed on from it (with views and tracking on;
        else no chain): the tracks carried on first (its first ``n_continued``), then the
        new features evenly, up to the budget."""
        config = self.ctx.config
        prior, self.chain = self.chain, None
        if frame.views is not None and config.tracking.enabled:
            # The tracks carried on first, then the new features evenly, up to the budget.
            followed = budget(n_continued, features, config.tracking)
            self.chain = TrackChain(
                self.extractor, frame.views, features, config.tracking, followed, prior=prior,
                key_images=frame.views.flow,
            )

    def step(self, key: LastKeyframe, frame: MovingFrame) -> TrackedStep | None:
        """The last keyframe's tracks followed on into ``frame``'s views, or None when
        there is no chain (tracking off), too few were tracked or no relative motion fits
        them (the frame then gets SIFT)."""
        if self.chain is None or frame.views is None:
            return None
        config = self.ctx.config.tracking
        if self.direct:
            return None  # the chain skipped a period once: descriptors from here on
        least = max(config.min_tracks, self.ctx.ransac.min_inliers)
        tracks = self.chain.advance(frame.views, frame.views.flow)
        if len(tracks.feature) < least:
            return None
        m = tracks.matches
        try:
            motion = estimate_relative_motion(
                key.features.rays_in_rig[m[:, 0]], tracks.features.rays_in_rig, self.ctx.ransac
            )
        except ReconstructionError:
            return None
        pair = StepPair(key.frame, frame.frame, key.features, tracks.features, m)
        return TrackedStep(tracks, m[motion.inliers], pair_parallax(pair, motion))

    def least_parallax(self, step: TrackedStep | None) -> float:
        """The parallax (rad) from which the frame of ``step`` (its tracks; None: none)
        becomes a keyframe: ``keyframe_min_parallax_deg``, half that when its tracks
        are running out (:meth:`running_out`)."""
        if step is not None and self.running_out(step):
            return self._min_parallax / 2
        return self._min_parallax

    def running_out(self, step: TrackedStep) -> bool:
        """True when ``step``'s verified tracks fell below ``tracking.renew_ratio`` of
        the last keyframe step's inliers (none yet: False)."""
        ratio = self.ctx.config.tracking.renew_ratio
        return ratio > 0 and len(step.inliers) < ratio * self.step_inliers

    def matches(
        self,
        last: LastKeyframe,
        frame: MovingFrame,
        step: TrackedStep,
        redo: Callable[[LastKeyframe], None],
    ) -> tuple[FrameFeatures, np.ndarray, int]:
        """The next keyframe's features, its (last keyframe feature, feature) matches
        and how many of its features are tracks carried on.

        Three candidates, verified by RANSAC: its SIFT features matched to the last
        keyframe's by descriptor over the whole frame (Lowe's ratio test), or guided by
        the chained tracks (:func:`omnipipe.sfm.features.guided_matches`: only within
        ``tracking.guided_radius_px`` of where each track went, so no period of a
        periodic wall is skipped); or the chained tracks themselves (the keyframe then
        carries them on as its first features). Descriptor matches are the more precise
        where the wall's descriptors tell its points apart: the one with more inliers is
        taken, unless the chained tracks have ``tracking.chain_over_descriptors`` times
        as many (periodic walls, brick faces, plain walls). The guided matches are
        verified only when they could be taken (more than the global ones' inliers, and
        enough against the tracks'): RANSAC keeps a subset of them. When the tracks
        skipped a period, SIFT from here on, and ``redo(last)`` matches the frames
        pending since ``last`` again."""
        config = self.ctx.config.tracking
        ratio = self.ctx.config.features.ratio
        inl = step.inliers
        detected = self.keyframe_features(frame, None)
        radius = config.guided_radius_px * self.ctx.camera.angular_resolution()
        track_rays = step.tracks.features.rays_in_rig[inl[:, 1]]
        everywhere = verified(self.ctx, last.features, detected, match_features(last.features, detected, ratio))
        guided = guided_matches(last.features, detected, inl[:, 0], track_rays, radius, ratio)
        if len(guided) > len(everywhere) and config.chain_over_descriptors * len(guided) >= len(inl):
            guided = verified(self.ctx, last.features, detected, guided)
        else:  # RANSAC keeps a subset: these could be taken neither way
            guided = guided[:0]
        best = everywhere if len(everywhere) >= len(guided) else guided
        if not self.direct and skipped_period(inl[:, 0], track_rays, everywhere, detected, 2 * radius, config):
            # The wall moved more than half its period between two frames somewhere: SIFT
            # on every moving frame from here on, and this step's frames are redone.
            self.ctx.warnings.append(
                f"frames {last.frame}->{frame.frame}: the tracks followed frame to frame disagree with "
                "the descriptor matches (a periodic wall moved more than half its period between "
                "two frames): matched by SIFT descriptors from here on"
            )
            self.direct = True
            redo(last)
            return detected, everywhere, 0
        if len(best) and config.chain_over_descriptors * len(best) >= len(inl):
            return detected, best, 0
        continued = subset(step.tracks.features, inl[:, 1])
        features = self.keyframe_features(frame, detected, continued)
        return features, np.stack([inl[:, 0], np.arange(len(inl))], axis=1), len(inl)

    def keyframe_features(
        self,
        frame: MovingFrame,
        features: FrameFeatures | None,
        continued: FrameFeatures | None = None,
    ) -> FrameFeatures:
        """A keyframe's features: ``continued`` (tracks carried on from the last
        keyframe) first, then its SIFT features (``features``, or detected on its views)
        that are not where a continued track is, then Shi-Tomasi corners where SIFT
        found few (:func:`omnipipe.sfm.tracking.corner_features`; with views only)."""
        if features is None:
            features = keyframe_detection(self.extractor, frame.views, self.ctx.config.tracking)
        if continued is not None and len(continued.view):
            near = cKDTree(continued.rays_in_rig).query(features.rays_in_rig, distance_upper_bound=self._near)[0]
            features = concat_features([continued, subset(features, np.flatnonzero(~np.isfinite(near)))])
        return features
