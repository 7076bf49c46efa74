"""The frame loop of camera motion (paper Sec. V, steps 1-3 and step 4's measurements).

Frames come in order (:func:`moving_frames`: stationary ones, whose robot stood still,
are left out, :mod:`omnipipe.sfm.stations`). :class:`KeyframeLoop` takes each moving
frame:

- the last keyframe's features are tracked into it by optical flow from the frame
  before (:class:`omnipipe.sfm.tracking.TrackChain`), or matched by SIFT descriptors
  (:mod:`omnipipe.sfm.features`) when too few were tracked or tracking is off; a new
  keyframe's correspondences are the best RANSAC-verified of its descriptor matches
  (global, or guided by the tracks) and the tracks themselves;
- the relative motion of the matched rays (eight-point algorithm with RANSAC,
  Eq. 10-16, :mod:`omnipipe.sfm.ransac`) tells how far the rays turned, rotation
  removed: under ``keyframe_min_parallax_deg`` the frame is *pending* (resected after
  the bundle adjustment), else it becomes the next keyframe; when its tracks are running
  out (``tracking.renew_ratio``), from half that angle on;
- each keyframe step's two scale measurements (laser template matches, Eq. 17; feature
  depths on the light-section wall) are submitted to the executor's workers, a bounded
  number at a time.
"""

from __future__ import annotations

import math
from collections import deque
from collections.abc import Callable, Iterator
from concurrent.futures import Executor, Future
from dataclasses import dataclass, replace
from typing import Any

import numpy as np
from scipy.spatial import cKDTree

from omnipipe.errors import ReconstructionError
from omnipipe.executor import default_workers, iter_frames, parallelism, shares_files
from omnipipe.image import gray_without_laser
from omnipipe.sfm.features import (
    FeatureExtractor,
    FrameFeatures,
    FrameViews,
    concat_features,
    guided_matches,
    match_features,
)
from omnipipe.sfm.flat_field import FlatWindow
from omnipipe.sfm.image_store import ImageStore, StoredImage
from omnipipe.sfm.planes import refine_matches
from omnipipe.sfm.ransac import RelativeMotion, estimate_relative_motion
from omnipipe.sfm.robot_sensors import odometry_moved
from omnipipe.sfm.scale_check import TRACKED_MIN_MATCHES
from omnipipe.sfm.stations import StationTracker
from omnipipe.sfm.tasks import (
    FeatureTask,
    handed_gray,
    handed_gray_file,
    matched_rays,
    step_evidence,
    track_back,
    verified_matches,
)
from omnipipe.sfm.tracking import (
    FlowImage,
    TrackChain,
    TrackConfig,
    Tracks,
    keyframe_detection,
    spread_order,
)
from omnipipe.sfm.types import (
    KeyframeRays,
    Keyframes,
    PendingFrame,
    SfmContext,
    SfmInputs,
    StepEvidence,
    StepScales,
)
from omnipipe.spill import Pack


@dataclass(frozen=True)
class MovingFrame:
    """A frame where the rig moved.

    Attributes:
        frame: its frame index.
        views: its perspective views (None: its features were detected in a worker).
        features: its SIFT features (None: not detected yet, ``views`` are set).
        gray: (H, W) its grey image without the laser (float32, or uint8/uint16 as
            :func:`omnipipe.sfm.tasks.compact_gray` sends it); None: the worker read the
            frame from the run's hand-off folder (``SfmInputs.handoff``), where the
            loop reads it should the frame become a keyframe
            (:func:`omnipipe.sfm.tasks.handed_gray`).
    """

    frame: int
    views: FrameViews | None
    features: FrameFeatures | None
    gray: np.ndarray | None


@dataclass(frozen=True)
class StepPair:
    """Two frames and their feature matches.

    Attributes:
        a, b: frame indices (a: the keyframe).
        features_a, features_b: their features.
        matches: (M, 2) (feature in a, feature in b) index pairs.
    """

    a: int
    b: int
    features_a: FrameFeatures
    features_b: FrameFeatures
    matches: np.ndarray


@dataclass(frozen=True)
class TrackedStep:
    """The last keyframe's features tracked into a frame.

    Attributes:
        tracks: the tracks (as the frame's features).
        inliers: (M, 2) RANSAC-verified (keyframe feature, frame feature) matches.
        parallax_rad: median angle the matched rays turned, rotation removed.
    """

    tracks: Tracks
    inliers: np.ndarray
    parallax_rad: float


@dataclass(frozen=True)
class _Keyframe:
    """The last keyframe: frame index, features, grey image (as it came) and views."""

    frame: int
    features: FrameFeatures
    gray: np.ndarray
    views: FrameViews | None


@dataclass(frozen=True)
class _BackJob:
    """A keyframe's features to follow back through the frames pending before it
    (:func:`omnipipe.sfm.tasks.track_back`), held until the step after it is matched.

    Attributes:
        k: the keyframe's index.
        views: its views; features: its features (no descriptors).
        followed: (F,) the features within the budget (indices into ``features``).
        pending_views: the pending frames' views, latest first; frames: their indices.
        key_images, pending_images: the flow images of ``views`` and of each pending
            frame's views as this process's chain made them (None where it did not).
    """

    k: int
    views: FrameViews
    features: FrameFeatures
    followed: np.ndarray
    pending_views: list[FrameViews]
    frames: list[int]
    key_images: list[FlowImage] | None = None
    pending_images: list[list[FlowImage] | None] | None = None


@dataclass(frozen=True)
class _EvidenceJob:
    """A step's evidence, completed by the worker's ``future`` when there is one."""

    evidence: StepEvidence
    future: Future[StepScales] | None = None

    def result(self) -> StepEvidence:
        """The complete evidence (waits for the worker)."""
        if self.future is None:
            return self.evidence
        got: StepScales = self.future.result()
        return replace(
            self.evidence,
            laser=got.laser,
            log_scales=got.log_scales,
            feature_scale_mm=got.feature_scale_mm,
            feature_matches=got.feature_matches,
        )


@dataclass(frozen=True)
class Followed:
    """What the frame loop found.

    Attributes:
        keyframes: the keyframes and their steps' evidence.
        pending: the moving frames that are not keyframes, in frame order.
        next_matches: pending frame -> its correspondences with the keyframe after it
            (being computed in a worker).
        moved: (N,) True for the frames where the rig moved (each starts a station).
        keyframe: (N,) True for the keyframes.
        lost: (N,) True for the frames whose relative motion was not found.
        tracked: (N,) True for the pending frames placed by optical-flow tracks.
    """

    keyframes: Keyframes
    pending: list[PendingFrame]
    next_matches: dict[int, Future[KeyframeRays]]
    moved: np.ndarray
    keyframe: np.ndarray
    lost: np.ndarray
    tracked: np.ndarray


def follow_keyframes(
    ctx: SfmContext,
    inputs: SfmInputs,
    grays: ImageStore,
    progress: Callable[[int], None] | None,
    ratio: np.ndarray | None = None,
) -> Followed:
    """Every moving frame through :class:`KeyframeLoop`; ``grays`` (empty) receives the
    keyframes' grey images; ``progress`` is told the frames done, over all N; ``ratio``
    (N,) receives the stationary test's ratios when it runs here (:func:`moving_frames`)."""
    loop = KeyframeLoop(ctx, inputs, grays)
    for frame in moving_frames(ctx, inputs, loop.extractor, loop.moved, progress, ratio):
        loop.add(frame)
    loop.finish()
    return loop.result()


class KeyframeLoop:
    """Takes the moving frames in order; keeps the keyframes (features, grey images in
    ``grays``), the pending frames between them and the steps' evidence jobs."""

    def __init__(self, ctx: SfmContext, inputs: SfmInputs, grays: ImageStore) -> None:
        n = inputs.n_frames
        self.ctx = ctx
        self.inputs = inputs
        self.extractor = FeatureExtractor(ctx.camera, ctx.config.features)
        # With workers, this process's SIFT and flow run the views on every core (the
        # chain waits for them; the workers are often idle then).
        self.extractor.threads = default_workers() if ctx.parallel else 1
        self.grays = grays
        self._flat = FlatWindow(
            ctx.camera, ctx.config.laser_scale.flat_field_keyframes, shares_files(ctx.executor)
        )
        self.moved = np.zeros(n, bool)  # filled by moving_frames
        self.keyframe = np.zeros(n, bool)
        self.lost = np.zeros(n, bool)
        self.tracked = np.zeros(n, bool)
        self.frames: list[int] = []
        self.features: list[FrameFeatures] = []
        self.pending: list[PendingFrame] = []
        self.next_matches: dict[int, Future[KeyframeRays]] = {}
        # The tracked pending frames' views, until the next keyframe.
        self._pending_views: dict[int, FrameViews] = {}
        # Their flow images as the chain made them (sent with the views to be followed back).
        self._pending_images: dict[int, list[FlowImage]] = {}
        # The pending frames' parallax (rad) from their keyframe, until the next keyframe.
        self._pending_parallax: dict[int, float] = {}
        self._jobs: list[_EvidenceJob] = []
        # The steps' evidence jobs and the pending frames' correspondences whose arrays
        # are not in the scratch yet (indices into _jobs, frames of next_matches):
        # moved there once the worker has finished (:meth:`_settle`).
        self._open_jobs: list[int] = []
        self._jobs_seen = 0
        self._open_matches: list[int] = []
        # What waits for the adjustment and the resection (features of the keyframes and
        # pending frames once nothing more is matched to them): in the run's scratch.
        self._pack = Pack()
        self._in_flight: deque[Future] = deque()
        self._back: _BackJob | None = None  # the last keyframe's, until its next step
        self._last: _Keyframe | None = None
        self._min_parallax = math.radians(ctx.config.keyframe_min_parallax_deg)
        self._step_inliers = 0  # verified matches of the last keyframe step
        # The last keyframe's tracks, followed frame to frame (None: tracking off).
        self._chain: TrackChain | None = None
        self._latest: MovingFrame | None = None  # the last moving frame added
        # SIFT on every moving frame (once the chained tracks were found to skip a
        # period of the wall).
        self._direct = False
        # A new feature this close (rad) to a track carried on is that track.
        self._near = 2.0 * ctx.camera.angular_resolution()

    def add(self, frame: MovingFrame, closing: bool = False) -> None:
        """One moving frame: pending (too little parallax) or the next keyframe (always
        with ``closing``)."""
        self._latest = frame
        last = self._last
        features = frame.features
        if last is None:
            gray = self._gray_of(frame)
            self._keep_gray(gray, frame)
            self._add_keyframe(frame, self._keyframe_features(frame, features), 0, gray)
            return
        closing = closing or frame.frame == self.inputs.n_frames - 1  # always a keyframe
        step = self._chained_step(last, frame)
        least = self._least_parallax(step)
        if step is not None and step.parallax_rad < least and not closing:
            # Too little baseline, followed without SIFT: resected after the adjustment.
            self._defer(frame, step.tracks.features, step.inliers, step.parallax_rad)
            self.tracked[frame.frame] = True
            return
        if step is not None:
            features, m, n_continued = self._chained_matches(last, frame, step)
            tracked = not self._direct  # chained tracks, or descriptors they verified
        else:
            tracked = False
            if features is None:
                features = self._keyframe_features(frame, None)
            n_continued = 0
            m = match_features(last.features, features, self.ctx.config.features.ratio)
        pair = StepPair(last.frame, frame.frame, last.features, features, m)
        motion = _relative(self.ctx, pair)
        if motion is None:
            self.lost[frame.frame] = True  # its pose (and the chain after it) lacks this step
        parallax = _parallax(pair, motion) if motion is not None else math.nan
        if motion is not None and parallax < least and not closing:
            # Too little baseline for a reliable step: resected after the adjustment.
            self._defer(frame, features, m[motion.inliers], parallax)
            return
        gray = self._gray_of(frame)  # a keyframe: its grey image is needed now
        if self.ctx.config.planes.enabled and motion is not None and motion.translation_reliable:
            motion = _refine(self.ctx, pair, motion, last.gray, gray)
        self._keep_gray(gray, frame)  # before the step's evidence, which may read it from there
        self._measure(pair, motion, last.gray, gray, tracked)
        self._step_inliers = int(np.count_nonzero(motion.inliers)) if motion is not None else 0
        self._add_keyframe(frame, features, n_continued, gray, parallax)

    def _least_parallax(self, step: TrackedStep | None) -> float:
        """The parallax (rad) from which the frame of ``step`` (its tracks; None: none)
        becomes a keyframe: ``keyframe_min_parallax_deg``, half that when its tracks
        are running out (:meth:`_running_out`)."""
        if step is not None and self._running_out(step):
            return self._min_parallax / 2
        return self._min_parallax

    def _running_out(self, step: TrackedStep) -> bool:
        """True when ``step``'s verified tracks fell below ``tracking.renew_ratio`` of
        the last keyframe step's inliers (none yet: False)."""
        ratio = self.ctx.config.tracking.renew_ratio
        return ratio > 0 and len(step.inliers) < ratio * self._step_inliers

    def _chained_matches(
        self, last: _Keyframe, frame: MovingFrame, step: TrackedStep
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
        enough against the tracks'): RANSAC keeps a subset of them."""
        config = self.ctx.config.tracking
        ratio = self.ctx.config.features.ratio
        inl = step.inliers
        detected = self._keyframe_features(frame, None)
        radius = config.guided_radius_px * self.ctx.camera.angular_resolution()
        track_rays = step.tracks.features.rays_in_rig[inl[:, 1]]
        everywhere = _verified(self.ctx, last.features, detected, match_features(last.features, detected, ratio))
        guided = guided_matches(last.features, detected, inl[:, 0], track_rays, radius, ratio)
        if len(guided) > len(everywhere) and config.chain_over_descriptors * len(guided) >= len(inl):
            guided = _verified(self.ctx, last.features, detected, guided)
        else:  # RANSAC keeps a subset: these could be taken neither way
            guided = guided[:0]
        best = everywhere if len(everywhere) >= len(guided) else guided
        if not self._direct and _skipped_period(inl[:, 0], track_rays, everywhere, detected, 2 * radius, config):
            # The wall moved more than half its period between two frames somewhere: SIFT
            # on every moving frame from here on, and this step's frames are redone.
            self.ctx.warnings.append(
                f"frames {last.frame}->{frame.frame}: the tracks followed frame to frame disagree with "
                "the descriptor matches (a periodic wall moved more than half its period between "
                "two frames): matched by SIFT descriptors from here on"
            )
            self._direct = True
            self._redo_pending(last)
            return detected, everywhere, 0
        if len(best) and config.chain_over_descriptors * len(best) >= len(inl):
            return detected, best, 0
        continued = _subset(step.tracks.features, inl[:, 1])
        features = self._keyframe_features(frame, detected, continued)
        return features, np.stack([inl[:, 0], np.arange(len(inl))], axis=1), len(inl)

    def _keyframe_features(
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
            features = concat_features([continued, _subset(features, np.flatnonzero(~np.isfinite(near)))])
        return features

    def _redo_pending(self, last: _Keyframe) -> None:
        """The frames pending since ``last`` (with views) matched to it again by SIFT
        descriptors, their chained tracks dropped (no matches when none are verified:
        they are then resected from the next keyframe's side, or flagged)."""
        k = len(self.features) - 1
        ratio = self.ctx.config.features.ratio
        for j, p in enumerate(self.pending):
            views = self._pending_views.pop(p.frame, None)
            self._pending_images.pop(p.frame, None)
            if p.keyframe != k or views is None:
                continue
            features = self.extractor.detect(views)
            inliers = _verified(self.ctx, last.features, features, match_features(last.features, features, ratio))
            self.pending[j] = replace(p, features=features, inliers=inliers)
            self.tracked[p.frame] = False

    def _chained_step(self, key: _Keyframe, frame: MovingFrame) -> TrackedStep | None:
        """The last keyframe's tracks followed on into ``frame``'s views, or None when
        there is no chain (tracking off), too few were tracked or no relative motion fits
        them (the frame then gets SIFT)."""
        if self._chain is None or frame.views is None:
            return None
        config = self.ctx.config.tracking
        if self._direct:
            return None  # the chain skipped a period once: descriptors from here on
        least = max(config.min_tracks, self.ctx.ransac.min_inliers)
        tracks = self._chain.advance(frame.views, frame.views.flow)
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
        return TrackedStep(tracks, m[motion.inliers], _parallax(pair, motion))

    def finish(self) -> None:
        """After the last moving frame: when it was left pending (the robot stood still
        from there on), it becomes a keyframe, so that no frame waits for a step that
        never comes (without it, a plain wall's few tracked frames left no step at all:
        nothing measured, nothing refused).

        With the robot's odometry, only when the wall is measurable there (the frame's
        verified matches to the last keyframe, at least
        :data:`~omnipipe.sfm.scale_check.TRACKED_MIN_MATCHES`): else its frames are
        placed by the travel (:func:`omnipipe.sfm.adjust.resect_pending`; a closing step
        promoted on a plain wall took a wrong laser length). Not closing a textured
        wall's only step left every frame to the odometry (random-wide seed 1,
        corrugated 963 mm, 28 mm of travel under the keyframe parallax: 31 of 31 steps
        "frame could not be resected", ATE 5.5 mm per 300 mm; closed, 0 and 1.2)."""
        frame = self._latest
        if frame is None or not self.pending or self.pending[-1].frame != frame.frame:
            return
        if self.inputs.odometry is not None and len(self.pending[-1].inliers) < TRACKED_MIN_MATCHES:
            return
        self.pending.pop()
        self._pending_views.pop(frame.frame, None)
        self._pending_images.pop(frame.frame, None)
        self.tracked[frame.frame] = False
        self.add(frame, closing=True)

    def result(self) -> Followed:
        """The keyframes with their steps' complete evidence, and the pending frames."""
        self._follow_back()
        self._throttle(self._flat.finish())
        rings = self.inputs.rings.rings
        keyframes = Keyframes(
            self.frames,
            self.features,
            self.grays,
            [self._pack.put(rings[f].points_in_rig) for f in self.frames],
            [_evidence_held(self._pack, job.result()) for job in self._jobs],
            self._flat.fields,
        )
        return Followed(
            keyframes,
            self.pending,
            self.next_matches,
            self.moved,
            self.keyframe,
            self.lost,
            self.tracked,
        )

    def _follow_back(self) -> None:
        """The held :class:`_BackJob` submitted to the workers, its features narrowed to
        those a keyframe step matched (its inliers to the keyframes before and after it):
        the resection reads a frame's rays only of features in the adjustment's tracks,
        which are made of these matches, so the poses are those of following them all
        (each track's flow is its own), for a part of the work (where the chained tracks
        carry the steps, few of the new features are matched on)."""
        job, self._back = self._back, None
        if job is None:
            return
        steps = [(self._step(job.k - 1), 1), (self._step(job.k), 0)]
        matched = [e.inliers[:, side] for e, side in steps if e is not None and e.inliers is not None]
        followed = matched_only(job.followed, matched)
        if len(followed) == 0:
            for f in job.frames:
                self.next_matches[f] = _done(KeyframeRays(np.zeros(0, int), np.zeros((0, 3))))
            return
        whole = self.ctx.executor.submit(
            track_back,
            self.inputs.rig,
            self.ctx.config.features,
            job.views,
            job.features,
            followed,
            job.pending_views,
            self.ctx.config.tracking,
            job.key_images,
            job.pending_images,
        )
        for f, part in zip(job.frames, _split(whole, len(job.frames)), strict=True):
            self.next_matches[f] = part
            self._open_matches.append(f)

    def _step(self, k: int) -> StepEvidence | None:
        """Keyframe step k -> k + 1's evidence as measured so far (None: not yet)."""
        return self._jobs[k].evidence if 0 <= k < len(self._jobs) else None

    def _defer(self, frame: MovingFrame, features: FrameFeatures, inliers: np.ndarray, parallax: float) -> None:
        """``frame`` pending, with its ``inliers`` to the last keyframe and the
        ``parallax`` (rad) of its rays from it."""
        self.pending.append(PendingFrame(frame.frame, len(self.features) - 1, features, inliers))
        self._pending_parallax[frame.frame] = parallax
        if frame.views is not None:
            self._pending_views[frame.frame] = frame.views
            if self._chain is not None and self._chain.views is frame.views:
                self._pending_images[frame.frame] = self._chain.images

    def _measure(
        self,
        pair: StepPair,
        motion: RelativeMotion | None,
        gray_a: np.ndarray,
        gray_b: np.ndarray,
        tracked: bool = False,
    ) -> None:
        """The step's evidence: its status, and for a translation both scale sources
        (laser Eq. 17 with its peaks, feature depths) measured in a worker; at most
        twice the executor's parallelism in flight (each holds two images). ``tracked``:
        the matches were verified frame to frame (:attr:`StepEvidence.tracked`)."""
        a, b = pair.a, pair.b
        if motion is None:
            self._jobs.append(_EvidenceJob(StepEvidence.unmeasured(a, b, np.eye(4), None, "lost")))
            return
        inl = pair.matches[motion.inliers]
        b_from_a = motion.rig2_from_rig1.copy()
        if not motion.translation_reliable:
            self.ctx.warnings.append(f"frames {a}->{b}: rotation only (no measurable translation)")
            self._jobs.append(
                _EvidenceJob(StepEvidence.unmeasured(a, b, b_from_a, inl, "rotation"))
            )
            return
        config, ex, k = self.ctx.config, self.ctx.executor, len(self.grays) - 2
        held_a, held_b = gray_for_worker(self.grays, k, gray_a, ex), gray_for_worker(self.grays, k + 1, gray_b, ex)
        args = (
            self.ctx.camera,
            self.inputs.rings.rings[a].points_in_rig,
            b_from_a[:3, :3],
            b_from_a[:3, 3],
            pair.features_a.rays_in_rig[inl[:, 0]],
            pair.features_b.rays_in_rig[inl[:, 1]],
            config.laser_scale,
            config.scale_check,
        )
        # Submitted once the keyframes around it give its flat field (sfm.flat_field).
        future, sent = self._flat.submit(k, lambda flat: ex.submit(step_evidence, held_a, held_b, *args, flat))
        evidence = replace(StepEvidence.unmeasured(a, b, b_from_a, inl, "ok"), tracked=tracked)
        self._jobs.append(_EvidenceJob(evidence, future))
        self._throttle(sent)

    def _throttle(self, sent: list[Future]) -> None:
        """At most twice the executor's parallelism of evidence jobs in flight."""
        self._in_flight.extend(sent)
        while len(self._in_flight) > 2 * parallelism(self.ctx.executor):
            self._in_flight.popleft().result()

    def _gray_of(self, frame: MovingFrame) -> np.ndarray:
        """``frame``'s grey image: as it came, or read from the run's hand-off folder
        where the worker left the frame (:class:`omnipipe.sfm.tasks.FeatureTask`)."""
        if frame.gray is not None:
            return frame.gray
        if self.inputs.handoff is None:
            raise ReconstructionError(f"frame {frame.frame}: no grey image and no hand-off folder")
        return handed_gray(self.inputs.handoff, frame.frame, self.inputs.rig.laser.channel)

    def _keep_gray(self, gray: np.ndarray, frame: MovingFrame) -> None:
        """The next keyframe's grey image (``frame``'s, ``gray``) into ``grays``: its file in
        the run's hand-off folder where that holds it as it is (no copy written:
        :func:`omnipipe.sfm.tasks.handed_gray_file`; the folder outlives the camera
        motion), else an 8-bit one as it is (its readers take it as float32: the same
        values in half the bytes of uint16), any other as uint16; and to the flat
        field's window (:mod:`omnipipe.sfm.flat_field`) with its ring's pixels."""
        handed = self.inputs.handoff
        path = None if frame.gray is not None or handed is None else handed_gray_file(handed, frame.frame)
        if path is not None:
            self.grays.append_file(path)
        else:
            self.grays.append(gray if gray.dtype == np.uint8 else np.clip(gray, 0, 65535).astype(np.uint16))
        self._throttle(self._flat.add_keyframe(gray, self.inputs.rings.rings[frame.frame].pixels))

    def _add_keyframe(
        self,
        frame: MovingFrame,
        features: FrameFeatures,
        n_continued: int,
        gray: np.ndarray,
        parallax: float = math.nan,
    ) -> None:
        """``frame`` the next keyframe (its first ``n_continued`` features carried on from
        the last one); its features are followed on from it. The frames pending since
        the last one also see its tracks: their correspondences with it go to the
        workers (its other features followed back frame by frame through the pending
        frames' views, or matched to the descriptors of frames without views); then
        nothing more is matched to them or to the last keyframe, whose descriptors go.
        ``parallax``: the step's (rad; :func:`followed_back`)."""
        self.features.append(features)
        self.frames.append(frame.frame)
        self.keyframe[frame.frame] = True
        self._last = _Keyframe(frame.frame, features, gray, frame.views)
        config = self.ctx.config
        fresh = np.arange(n_continued, len(features.view))
        prior, self._chain = self._chain, None
        if frame.views is not None and config.tracking.enabled:
            # The tracks carried on first, then the new features evenly, up to the budget.
            followed = _budget(n_continued, features, config.tracking)
            self._chain = TrackChain(
                self.extractor, frame.views, features, config.tracking, followed, prior=prior,
                key_images=frame.views.flow,
            )
        k_new = len(self.features) - 1
        since = [j for j, p in enumerate(self.pending) if p.keyframe == k_new - 1]
        viewed = [j for j in since if self.pending[j].frame in self._pending_views]
        back = [
            viewed[i]
            for i in followed_back(
                [len(self.pending[j].inliers) for j in viewed],
                [_share(self._pending_parallax.get(self.pending[j].frame, math.nan), parallax) for j in viewed],
                config.tracking,
            )
        ]
        self._follow_back()  # the keyframe before: its steps to either side are matched now
        if back and frame.views is not None:
            self._back = _BackJob(
                k_new,
                frame.views,
                _slim(features),
                fresh[_budget(0, _subset(features, fresh), config.tracking)],
                [self._pending_views[self.pending[j].frame] for j in back],
                [self.pending[j].frame for j in back],
                self._chain.images if self._chain is not None and self._chain.views is frame.views else None,
                [self._pending_images.get(self.pending[j].frame) for j in back],
            )
        waiting = set(self._back.frames) if self._back is not None else set()
        for j in since:
            p = self.pending[j]
            if p.frame not in self.next_matches and p.frame not in waiting and len(p.features.descriptors):
                self.next_matches[p.frame] = self.ctx.executor.submit(
                    matched_rays, features, p.features, config.features.ratio
                )
                self._open_matches.append(p.frame)
            self.pending[j] = replace(
                p, features=_held(self._pack, p.features), inliers=self._pack.put(p.inliers)
            )
        self._pending_views.clear()
        self._pending_images.clear()
        self._pending_parallax.clear()
        if k_new >= 1:
            self.features[k_new - 1] = _held(self._pack, self.features[k_new - 1])
        self._settle()

    def _settle(self) -> None:
        """The steps' evidence and the pending frames' correspondences whose workers have
        finished (or that had none): their arrays into the run's scratch
        (:func:`_evidence_held`, :func:`_rays_held`; the same values), so that what the
        loop holds in memory does not grow with the keyframes. A worker's exception is
        left in its future, raised where the result is asked for."""
        self._open_jobs += range(self._jobs_seen, len(self._jobs))
        self._jobs_seen = len(self._jobs)
        open_jobs = []
        for k in self._open_jobs:
            job = self._jobs[k]
            if job.future is None or _finished(job.future):
                self._jobs[k] = _EvidenceJob(_evidence_held(self._pack, job.result()))
            else:
                open_jobs.append(k)
        self._open_jobs = open_jobs
        open_matches = []
        for f in self._open_matches:
            future = self.next_matches[f]
            if _finished(future):
                self.next_matches[f] = _done(_rays_held(self._pack, future.result()))
            else:
                open_matches.append(f)
        self._open_matches = open_matches


def gray_for_worker(
    grays: ImageStore, k: int, gray: np.ndarray, executor: Executor
) -> np.ndarray | StoredImage:
    """Keyframe ``k``'s grey image ``gray`` (H, W) as sent to ``executor``'s worker: a
    reference to its file in ``grays`` (the keyframe store, ``k`` an index into it) for
    a local pool's worker when the stored copy holds the same values (an 8- or
    16-bit grey image), else the array itself (inline, a Dask cluster, a float image)."""
    exact = gray.dtype in (np.uint8, np.uint16)
    return grays.ref(k) if exact and shares_files(executor) else gray


def followed_back(counts: list[int], shares: list[float], config: TrackConfig) -> list[int]:
    """Which pending frames (``counts``: each one's verified tracks of its keyframe, in
    frame order; ``shares``: its parallax as a share of the new keyframe's, NaN where
    not known) the new keyframe's features are followed back into, as positions in
    ``counts``, latest first: from the latest down to the earliest with fewer than
    ``config.back_below`` tracks, or a share of at least ``config.back_beyond`` (or not
    known), whichever is earlier (the chain goes frame by frame, so the later ones on
    the way are followed too); none when no frame needs it."""
    needs = [
        i
        for i, (n, share) in enumerate(zip(counts, shares, strict=True))
        if n < config.back_below or not share < config.back_beyond
    ]
    return list(range(len(counts) - 1, needs[0] - 1, -1)) if needs else []


def _share(part: float, whole: float) -> float:
    """``part / whole``; NaN when ``whole`` is not positive or either is NaN."""
    return part / whole if whole > 0 else math.nan


def _budget(n_first: int, features: FrameFeatures, config: TrackConfig) -> np.ndarray:
    """Indices of ``features`` to follow, at most ``config.max_points``: the first
    ``n_first``, then the rest; of a part too large for what is left, evenly over the
    list, or with ``config.spread_px`` spread over the views
    (:func:`~omnipipe.sfm.tracking.spread_order`)."""
    n, most = len(features.view), config.max_points

    def part(lo: int, hi: int, k: int) -> np.ndarray:
        if k <= 0 or hi <= lo:
            return np.zeros(0, int)
        if k >= hi - lo:
            return np.arange(lo, hi)
        if config.spread_px > 0 and features.view_pixels is not None:
            order = spread_order(features.view[lo:hi], features.view_pixels[lo:hi], config.spread_px)
            return lo + np.sort(order[:k])
        return np.unique(np.linspace(lo, hi - 1, k).round().astype(int))

    head = part(0, n_first, most)
    return np.concatenate([head, part(n_first, n, most - len(head))])


def _split(whole: Future[list[KeyframeRays]], n: int) -> list[Future[KeyframeRays]]:
    """One future per item of the list ``whole`` will hold (``n`` items)."""
    parts: list[Future[KeyframeRays]] = [Future() for _ in range(n)]

    def done(f: Future[list[KeyframeRays]]) -> None:
        exc = f.exception()
        for i, part in enumerate(parts):
            if exc is not None:
                part.set_exception(exc)
            else:
                part.set_result(f.result()[i])

    whole.add_done_callback(done)
    return parts


def matched_only(followed: np.ndarray, matched: list[np.ndarray]) -> np.ndarray:
    """The features of ``followed`` (F,) that appear in any of ``matched`` (arrays of
    feature indices), in ``followed``'s order."""
    return followed[np.isin(followed, np.concatenate(matched))] if matched else followed[:0]


def _done(value: KeyframeRays) -> Future[KeyframeRays]:
    """A future already holding ``value``."""
    future: Future[KeyframeRays] = Future()
    future.set_result(value)
    return future


def _subset(features: FrameFeatures, idx: np.ndarray) -> FrameFeatures:
    """The features ``idx`` of ``features`` (descriptors too when it has them)."""
    desc = features.descriptors[idx] if len(features.descriptors) else np.zeros((len(idx), 128), np.float32)
    vpx = None if features.view_pixels is None else features.view_pixels[idx]
    return FrameFeatures(features.rays_in_rig[idx], features.pixels[idx], desc, features.view[idx], vpx)


def _slim(features: FrameFeatures) -> FrameFeatures:
    """``features`` without their descriptors (once nothing more is matched to them:
    the rays and pixels are what the adjustment and resection read)."""
    return replace(features, descriptors=np.zeros((0, 128), np.float32))


def _held(pack: Pack, features: FrameFeatures) -> FrameFeatures:
    """``features`` slimmed (:func:`_slim`), their arrays in ``pack`` (the run's scratch,
    :class:`omnipipe.spill.Pack`: the same values, resident only while read)."""
    vpx = None if features.view_pixels is None else pack.put(features.view_pixels)
    return FrameFeatures(
        pack.put(features.rays_in_rig), pack.put(features.pixels), np.zeros((0, 128), np.float32),
        pack.put(features.view), vpx,
    )


def _finished(future: Future | Any) -> bool:
    """True when ``future`` (a :class:`~concurrent.futures.Future`, or a flat-fielded
    step's handle holding one once released: :mod:`omnipipe.sfm.flat_field`) holds its
    result: done, neither cancelled nor failed."""
    future = getattr(future, "future", future)
    return (
        isinstance(future, Future) and future.done() and not future.cancelled() and future.exception() is None
    )


def _rays_held(pack: Pack, rays: KeyframeRays) -> KeyframeRays:
    """``rays`` with its arrays in ``pack`` (as :func:`_held`)."""
    return KeyframeRays(pack.put(rays.feature), pack.put(rays.rays_in_rig))


def _evidence_held(pack: Pack, evidence: StepEvidence) -> StepEvidence:
    """``evidence`` with its per-match arrays in ``pack`` (as :func:`_held`)."""
    laser = evidence.laser
    if laser is not None:
        laser = replace(
            laser, index=pack.put(laser.index), scale_mm=pack.put(laser.scale_mm),
            pixels_b=pack.put(laser.pixels_b), ncc=pack.put(laser.ncc),
        )
    inliers = None if evidence.inliers is None else pack.put(evidence.inliers)
    return replace(evidence, inliers=inliers, log_scales=pack.put(evidence.log_scales), laser=laser)


def _relative(ctx: SfmContext, pair: StepPair) -> RelativeMotion | None:
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


def _verified(ctx: SfmContext, fa: FrameFeatures, fb: FrameFeatures, m: np.ndarray) -> np.ndarray:
    """The matches ``m`` (M, 2) one relative motion explains (RANSAC inliers; none when
    no motion fits; :func:`omnipipe.sfm.tasks.verified_matches`)."""
    return verified_matches(fa, fb, m, ctx.ransac)


def _skipped_period(
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


def _parallax(pair: StepPair, motion: RelativeMotion) -> float:
    """Median angle (rad) between matched rays once the rotation is removed."""
    inl = pair.matches[motion.inliers]
    if len(inl) == 0:
        return 0.0
    R = motion.rig2_from_rig1[:3, :3]
    ra = pair.features_a.rays_in_rig[inl[:, 0]] @ R.T
    rb = pair.features_b.rays_in_rig[inl[:, 1]]
    return float(np.median(np.arccos(np.clip(np.sum(ra * rb, axis=1), -1.0, 1.0))))


def _refine(
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
    again = _relative(ctx, pair)
    return again if again is not None else motion


def moving_frames(
    ctx: SfmContext,
    inputs: SfmInputs,
    extractor: FeatureExtractor,
    moved: np.ndarray,
    progress: Callable[[int], None] | None,
    ratios: np.ndarray | None = None,
) -> Iterator[MovingFrame]:
    """Every frame where the rig moved, in order; fills ``moved`` (N,) (and ``ratios``
    (N,), the stationary test's, when it runs here) and reports progress over all N
    frames. With ``config.tracking`` their views (features None: detected on the
    keyframes; from a local pool's workers with their flow images), else their features.

    With ``inputs.moved``, ``inputs.dataset`` and a parallel executor, they come from
    workers that decode the frames themselves (:class:`omnipipe.sfm.tasks.FeatureTask`;
    the grey image as :func:`omnipipe.sfm.tasks.compact_gray` returns it); otherwise
    every frame is read here and the stationary test runs frame by frame (paper
    Sec. V, step 1). Frames the robot's odometry counted moving
    (:func:`omnipipe.sfm.robot_sensors.odometry_moved`) are moving frames too.
    """
    config = ctx.config
    n = inputs.n_frames
    rings = inputs.rings.rings
    # Where the images cannot tell (a plain wall), the odometry's count moves the rig too.
    by_odometry = (
        odometry_moved(inputs.odometry, inputs.timestamps)
        if inputs.odometry is not None and inputs.timestamps is not None
        else np.zeros(n, bool)
    )
    if inputs.moved is not None and inputs.dataset is not None and ctx.parallel:
        moved[:] = inputs.moved | by_odometry
        flow = config.tracking if config.tracking.enabled and shares_files(ctx.executor) else None
        stream = iter_frames(
            ctx.executor,
            FeatureTask(config.features, not config.tracking.enabled, flow),
            inputs.dataset,
            np.flatnonzero(moved),
            most=4,
            payload=lambda i: rings[i].pixels,
            handoff=inputs.handoff,
        )
        for i, (views, feats, gray) in stream:
            yield MovingFrame(i, views, feats, gray)
            if progress:
                progress(i + 1)
        if progress:
            progress(n)
        return
    channel = inputs.rig.laser.channel
    tracker = None
    if inputs.moved is None:
        tracker = StationTracker(extractor.camera.valid_mask(), config.stations)
    else:
        moved[:] = inputs.moved | by_odometry

    def moving(i: int, img: np.ndarray, gray: np.ndarray) -> MovingFrame:
        views = extractor.frame_views(img, channel, rings[i].pixels)
        if config.tracking.enabled:
            return MovingFrame(i, views, None, gray)
        return MovingFrame(i, None, extractor.detect(views), gray)

    held: tuple[int, np.ndarray, np.ndarray] | None = None  # a creeping stationary frame
    for i in range(n):
        if tracker is not None or moved[i]:
            img = inputs.read_frame(i)
            gray = gray_without_laser(img, channel)
            if tracker is not None:
                moved[i], ratio = tracker.update(gray)
                if ratios is not None:
                    ratios[i] = ratio
                moved[i] |= by_odometry[i]
                if moved[i] and held is not None:  # stations.promote_creep, one frame late
                    moved[held[0]] = True
                    yield moving(*held)
                creeping = not moved[i] and ratio > config.stations.creep_factor
                held = (i, img, gray) if creeping else None
            if moved[i]:
                yield moving(i, img, gray)
        if progress:
            progress(i + 1)
