"""The frame loop of camera motion (paper Sec. V, steps 1-3 and step 4's measurements).

Frames come in order (:func:`moving_frames`: stationary ones, whose robot stood still,
are left out, :mod:`omnipipe.sfm.stations`). :class:`KeyframeLoop` takes each moving
frame:

- the last keyframe's features are tracked into it by optical flow
  (:mod:`omnipipe.sfm.tracking`), or matched by SIFT descriptors
  (:mod:`omnipipe.sfm.features`) when too few were tracked or tracking is off;
- the relative motion of the matched rays (eight-point algorithm with RANSAC,
  Eq. 10-16, :mod:`omnipipe.sfm.ransac`) tells how far the rays turned, rotation
  removed: under ``keyframe_min_parallax_deg`` the frame is *pending* (resected after
  the bundle adjustment), else it becomes the next keyframe;
- each keyframe step's two scale measurements (laser template matches, Eq. 17; feature
  depths on the light-section wall) are submitted to the executor's workers, a bounded
  number at a time.
"""

from __future__ import annotations

import math
from collections import deque
from collections.abc import Callable, Iterator
from concurrent.futures import Future
from dataclasses import dataclass, replace

import numpy as np

from omnipipe.errors import ReconstructionError
from omnipipe.executor import iter_frames, parallelism
from omnipipe.image import gray_without_laser
from omnipipe.sfm.features import FeatureExtractor, FrameFeatures, FrameViews, match_features
from omnipipe.sfm.image_store import ImageStore
from omnipipe.sfm.planes import refine_matches
from omnipipe.sfm.ransac import RelativeMotion, estimate_relative_motion
from omnipipe.sfm.robot_sensors import odometry_moved
from omnipipe.sfm.stations import StationTracker
from omnipipe.sfm.tasks import FeatureTask, matched_rays, step_evidence, track_into
from omnipipe.sfm.tracking import Tracks, followed_count, track_features
from omnipipe.sfm.types import (
    KeyframeRays,
    Keyframes,
    PendingFrame,
    SfmContext,
    SfmInputs,
    StepEvidence,
    StepScales,
)


@dataclass(frozen=True)
class MovingFrame:
    """A frame where the rig moved.

    Attributes:
        frame: its frame index.
        views: its perspective views (None: its features were detected in a worker).
        features: its SIFT features (None: not detected yet, ``views`` are set).
        gray: (H, W) its grey image without the laser (float32, or uint8/uint16 as
            :func:`omnipipe.sfm.tasks.compact_gray` sends it).
    """

    frame: int
    views: FrameViews | None
    features: FrameFeatures | None
    gray: np.ndarray


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
    ctx: SfmContext, inputs: SfmInputs, grays: ImageStore, progress: Callable[[int], None] | None
) -> Followed:
    """Every moving frame through :class:`KeyframeLoop`; ``grays`` (empty) receives the
    keyframes' grey images; ``progress`` is told the frames done, over all N."""
    loop = KeyframeLoop(ctx, inputs, grays)
    for frame in moving_frames(ctx, inputs, loop.extractor, loop.moved, progress):
        loop.add(frame)
    return loop.result()


class KeyframeLoop:
    """Takes the moving frames in order; keeps the keyframes (features, grey images in
    ``grays``), the pending frames between them and the steps' evidence jobs."""

    def __init__(self, ctx: SfmContext, inputs: SfmInputs, grays: ImageStore) -> None:
        n = inputs.n_frames
        self.ctx = ctx
        self.inputs = inputs
        self.extractor = FeatureExtractor(ctx.camera, ctx.config.features)
        self.grays = grays
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
        self._jobs: list[_EvidenceJob] = []
        self._in_flight: deque[Future] = deque()
        self._last: _Keyframe | None = None
        self._min_parallax = math.radians(ctx.config.keyframe_min_parallax_deg)

    def add(self, frame: MovingFrame) -> None:
        """One moving frame: pending (too little parallax) or the next keyframe."""
        last = self._last
        features = frame.features
        if last is None:
            self._add_keyframe(
                frame, self.extractor.detect(frame.views) if features is None else features
            )
            return
        closing = frame.frame == self.inputs.n_frames - 1  # the last frame is always a keyframe
        if features is None and not closing:
            step = _tracked_step(self.ctx, self.extractor, last, frame)
            if step is not None and step.parallax_rad < self._min_parallax:
                # Too little baseline, followed without SIFT: resected after the adjustment.
                self._defer(frame, step.tracks.features, step.inliers)
                self.tracked[frame.frame] = True
                return
        if features is None:
            features = self.extractor.detect(frame.views)
        m = match_features(last.features, features, self.ctx.config.features.ratio)
        pair = StepPair(last.frame, frame.frame, last.features, features, m)
        motion = _relative(self.ctx, pair)
        if motion is None:
            self.lost[frame.frame] = True  # its pose (and the chain after it) lacks this step
        if motion is not None and _parallax(pair, motion) < self._min_parallax and not closing:
            # Too little baseline for a reliable step: resected after the adjustment.
            self._defer(frame, features, m[motion.inliers])
            return
        if self.ctx.config.planes.enabled and motion is not None and motion.translation_reliable:
            motion = _refine(self.ctx, pair, motion, last.gray, frame.gray)
        self._measure(pair, motion, last.gray, frame.gray)
        self._add_keyframe(frame, features)

    def result(self) -> Followed:
        """The keyframes with their steps' complete evidence, and the pending frames."""
        rings = self.inputs.rings.rings
        keyframes = Keyframes(
            self.frames,
            self.features,
            self.grays,
            [rings[f].points_in_rig for f in self.frames],
            [job.result() for job in self._jobs],
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

    def _defer(self, frame: MovingFrame, features: FrameFeatures, inliers: np.ndarray) -> None:
        """``frame`` pending, with its ``inliers`` to the last keyframe."""
        self.pending.append(PendingFrame(frame.frame, len(self.features) - 1, features, inliers))
        if frame.views is not None:
            self._pending_views[frame.frame] = frame.views

    def _measure(
        self, pair: StepPair, motion: RelativeMotion | None, gray_a: np.ndarray, gray_b: np.ndarray
    ) -> None:
        """The step's evidence: its status, and for a translation both scale sources
        (laser Eq. 17 with its peaks, feature depths) measured in a worker; at most
        twice the executor's parallelism in flight (each holds two images)."""
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
        config = self.ctx.config
        future = self.ctx.executor.submit(
            step_evidence,
            gray_a,
            gray_b,
            self.ctx.camera,
            self.inputs.rings.rings[a].points_in_rig,
            b_from_a[:3, :3],
            b_from_a[:3, 3],
            pair.features_a.rays_in_rig[inl[:, 0]],
            pair.features_b.rays_in_rig[inl[:, 1]],
            config.laser_scale,
            config.scale_check,
        )
        evidence = StepEvidence.unmeasured(a, b, b_from_a, inl, "ok")
        self._jobs.append(_EvidenceJob(evidence, future))
        self._in_flight.append(future)
        while len(self._in_flight) > 2 * parallelism(self.ctx.executor):
            self._in_flight.popleft().result()

    def _add_keyframe(self, frame: MovingFrame, features: FrameFeatures) -> None:
        """``frame`` the next keyframe. The frames pending since the last one also see
        its tracks: their correspondences with it go to the workers (tracked into the
        views of a tracked frame, matched to the descriptors of the others); then
        nothing more is matched to them or to the last keyframe, whose descriptors go."""
        self.features.append(features)
        self.grays.append(np.clip(frame.gray, 0, 65535).astype(np.uint16))
        self.frames.append(frame.frame)
        self.keyframe[frame.frame] = True
        self._last = _Keyframe(frame.frame, features, frame.gray, frame.views)
        config, executor = self.ctx.config, self.ctx.executor
        k_new = len(self.features) - 1
        for j in range(len(self.pending) - 1, -1, -1):
            p = self.pending[j]
            if p.keyframe != k_new - 1:
                break
            if p.frame in self._pending_views:
                self.next_matches[p.frame] = executor.submit(
                    track_into,
                    self.inputs.rig,
                    config.features,
                    frame.views,
                    features,
                    self._pending_views.pop(p.frame),
                    config.tracking,
                )
            else:
                self.next_matches[p.frame] = executor.submit(
                    matched_rays, features, p.features, config.features.ratio
                )
            self.pending[j] = replace(p, features=_slim(p.features))
        self._pending_views.clear()
        if k_new >= 1:
            self.features[k_new - 1] = _slim(self.features[k_new - 1])


def _slim(features: FrameFeatures) -> FrameFeatures:
    """``features`` without their descriptors (once nothing more is matched to them:
    the rays and pixels are what the adjustment and resection read)."""
    return replace(features, descriptors=np.zeros((0, 128), np.float32))


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


def _tracked_step(
    ctx: SfmContext, extractor: FeatureExtractor, key: _Keyframe, frame: MovingFrame
) -> TrackedStep | None:
    """The keyframe's features tracked into ``frame``'s views, or None when too few were
    tracked or no relative motion fits them (the frame then gets SIFT)."""
    config = ctx.config.tracking
    tracks = track_features(extractor, key.views, key.features, frame.views, config)
    followed = followed_count(len(key.features.rays_in_rig), config)
    if len(tracks.feature) < config.min_tracked_fraction * followed:
        return None
    m = tracks.matches
    try:
        motion = estimate_relative_motion(
            key.features.rays_in_rig[m[:, 0]], tracks.features.rays_in_rig, ctx.ransac
        )
    except ReconstructionError:
        return None
    pair = StepPair(key.frame, frame.frame, key.features, tracks.features, m)
    return TrackedStep(tracks, m[motion.inliers], _parallax(pair, motion))


def moving_frames(
    ctx: SfmContext,
    inputs: SfmInputs,
    extractor: FeatureExtractor,
    moved: np.ndarray,
    progress: Callable[[int], None] | None,
) -> Iterator[MovingFrame]:
    """Every frame where the rig moved, in order; fills ``moved`` (N,) and reports
    progress over all N frames. With ``config.tracking`` their views (features None:
    detected on the keyframes), else their features (views None).

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
        stream = iter_frames(
            ctx.executor,
            FeatureTask(config.features, detect=not config.tracking.enabled),
            inputs.dataset,
            np.flatnonzero(moved),
            most=4,
            payload=lambda i: rings[i].pixels,
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
