"""Camera motion of a whole sequence (paper Sec. V): every frame's metric pose.

1. Stations: frames taken while the earthworm robot stood still are found from the
   images (:mod:`omnipipe.sfm.stations`); each stop is one station, its frames share
   one pose and are flagged ``stationary``.
2. Keyframes: the last keyframe's SIFT features (perspective views,
   :mod:`omnipipe.sfm.features`) are tracked by optical flow into each station's first
   frame (:mod:`omnipipe.sfm.tracking`); the station becomes a keyframe once the rays
   turned ``keyframe_min_parallax_deg`` (rotation removed), and only then is SIFT run
   on it and matched with the last keyframe (also when too few features were tracked).
3. Relative motion: eight-point algorithm on ray vectors with RANSAC (Eq. 10-16);
   near-pure rotations are recognised and keep a zero translation.
4. Scale: the laser points of the earlier keyframe are found again in the later one
   by template matching along the epipolar curve (Sec. V-D, Eq. 17), which makes
   each step metric.
5. Bundle adjustment over all keyframes (:mod:`omnipipe.sfm.bundle`): reprojection
   errors of the feature tracks in pixels through the hyperboloid model, plus the
   laser points' matches as metric anchors, which keep the scale from drifting.
6. The stations that are not keyframes are resected against the adjusted tracks.
"""

from __future__ import annotations

import math
from collections import deque
from collections.abc import Callable, Iterator
from concurrent.futures import Executor, Future
from dataclasses import replace
from typing import TYPE_CHECKING

import numpy as np

from omnipipe.camera import camera_from_rig
from omnipipe.errors import ReconstructionError
from omnipipe.image import gray_without_laser
from omnipipe.sfm.adjust import adjust_keyframes, resect_pending
from omnipipe.sfm.features import (
    FeatureExtractor,
    FrameFeatures,
    FrameViews,
    match_features,
)
from omnipipe.sfm.image_store import ImageStore
from omnipipe.sfm.planes import refine_matches
from omnipipe.sfm.ransac import RansacConfig, estimate_relative_motion
from omnipipe.sfm.scale_check import (
    UnreliableStretch,
    merge_stretches,
)
from omnipipe.sfm.stations import StationTracker
from omnipipe.sfm.step_scale import chain_steps, check_adjusted, run_length, run_scale
from omnipipe.sfm.tasks import (
    FeatureTask,
    matched_rays,
    step_evidence,
    track_into,
)
from omnipipe.sfm.tracking import Tracks, followed_count, track_features
from omnipipe.sfm.types import (
    Keyframes,
    PendingFrame,
    SfmConfig,
    SfmContext,
    SfmInputs,
    SfmResult,
    StepEvidence,
)

if TYPE_CHECKING:
    pass


def run(
    config: SfmConfig,
    inputs: SfmInputs,
    progress: Callable[[int], None] | None = None,
    executor: Executor | None = None,
) -> SfmResult:
    """Estimate every frame's metric pose (world = rig frame of frame 0).

    ``executor`` (:mod:`omnipipe.executor`) does the frame-parallel work: the moving
    frames' features (with ``inputs.moved`` and ``inputs.dataset``) and each keyframe
    step's scale evidence (Eq. 17 template matching, feature depths), while this
    process chains the steps in frame order. Without one, everything runs here; the
    result is the same.

    Raises:
        ReconstructionError: no frame could be read.
    """
    with ImageStore() as kf_gray:  # keyframe grey images, on disk until the run is decided
        return _estimate(config, inputs, progress, executor, kf_gray)


def _estimate(
    config: SfmConfig,
    inputs: SfmInputs,
    progress: Callable[[int], None] | None,
    executor: Executor | None,
    kf_gray: ImageStore,
) -> SfmResult:
    """:func:`run`, with ``kf_gray`` the (empty) store of the keyframes' grey images."""
    from omnipipe.executor import InlineExecutor, parallelism

    rig = inputs.rig
    camera = camera_from_rig(rig)
    n = inputs.n_frames
    if n < 1:
        raise ReconstructionError("no frames")
    ex = executor or InlineExecutor()
    rings = inputs.rings.rings
    warnings: list[str] = []
    mid = np.array([[camera.cx + 0.5 * (camera.radius_min + camera.radius_max), camera.cy]])
    px_angle = float(
        np.arccos(
            np.clip(
                np.sum(camera.unproject(mid) * camera.unproject(mid + np.array([[0.0, 1.0]]))),
                -1,
                1,
            )
        )
    )
    ransac = RansacConfig(
        threshold_rad=config.ransac_threshold_px * px_angle,
        max_iterations=config.ransac_iterations,
        min_inliers=config.min_inliers,
        rotation_only_ratio=config.rotation_only_ratio,
        seed=config.seed,
    )
    moved = np.zeros(n, bool)
    is_kf = np.zeros(n, bool)
    lost = np.zeros(n, bool)
    tracked = np.zeros(n, bool)
    kf_frames: list[int] = []
    prev = None  # (frame index, features, grey)
    kf_features = []
    # Moving frames too close to the last keyframe: (frame, keyframe index, features, matches).
    pending: list[tuple[int, int, FrameFeatures, np.ndarray | None]] = []
    # Pending frame -> its correspondences with the next keyframe (a future of
    # (keyframe feature indices, the frame's rays)).
    next_matches: dict[int, Future] = {}
    pending_views: dict[int, FrameViews] = {}  # tracked pending frames' views, until the next keyframe
    extractor = FeatureExtractor(camera, config.features)
    prev_views: FrameViews | None = None
    # Each keyframe step's evidence, or the future of the worker computing it.
    evidence_parts: list[StepEvidence | tuple[StepEvidence, Future]] = []
    in_flight: deque[Future] = deque()
    min_parallax = math.radians(config.keyframe_min_parallax_deg)
    for i, views, feats, gray in _moving_frames(config, inputs, extractor, executor, moved, progress):
        if prev is None:
            if feats is None:
                feats = extractor.detect(views)
        else:
            a, fa, ga = prev
            if feats is None and i < n - 1:
                step = _tracked_step(extractor, prev_views, fa, views, ransac, config)
                if step is not None and step[2] < min_parallax:
                    # Too little baseline, followed without SIFT: resected after the adjustment.
                    pending.append((i, len(kf_features) - 1, step[0].features, step[1]))
                    pending_views[i] = views
                    tracked[i] = True
                    continue
            if feats is None:
                feats = extractor.detect(views)
            m = match_features(fa, feats, config.features.ratio)
            motion = _relative(a, i, fa, feats, m, ransac, warnings)
            if motion is None:
                lost[i] = True  # its pose (and the chain after it) lacks this step
            if motion is not None and _parallax(fa, feats, m, motion) < min_parallax and i < n - 1:
                # Too little baseline for a reliable step: resected after the adjustment.
                pending.append((i, len(kf_features) - 1, feats, m[motion.inliers]))
                if views is not None:
                    pending_views[i] = views
                continue
            if config.planes.enabled and motion is not None and motion.translation_reliable:
                motion = _refine(
                    np.asarray(ga, np.float32), np.asarray(gray, np.float32), camera, fa, feats, m,
                    motion, ransac, config, warnings, a, i,
                )
            part = _evidence(a, i, ga, gray, camera, rings[a].points_in_rig, fa, feats, m, motion, config, warnings, ex)
            evidence_parts.append(part)
            if isinstance(part, tuple):
                in_flight.append(part[1])
                while len(in_flight) > 2 * parallelism(ex):  # bounded: each holds two images
                    in_flight.popleft().result()
        kf_features.append(feats)
        kf_gray.append(np.clip(gray, 0, 65535).astype(np.uint16))
        kf_frames.append(i)
        is_kf[i] = True
        prev = (i, feats, gray)
        prev_views = views
        # The frames resected between the last keyframe and this one also see this
        # one's tracks: their correspondences with it, in the workers (tracked into the
        # views of a tracked frame, matched to the descriptors of the others).
        k_new = len(kf_features) - 1
        for j in range(len(pending) - 1, -1, -1):
            f, k, pf, inl_f = pending[j]
            if k != k_new - 1:
                break
            if f in pending_views:
                next_matches[f] = ex.submit(
                    track_into, rig, config.features, views, feats, pending_views.pop(f), config.tracking
                )
            else:
                next_matches[f] = ex.submit(matched_rays, feats, pf, config.features.ratio)
            pending[j] = (f, k, _slim(pf), inl_f)  # no more matching: its descriptors go
        pending_views.clear()
        if k_new >= 1:
            kf_features[k_new - 1] = _slim(kf_features[k_new - 1])
    evidence = [_resolve(part) for part in evidence_parts]
    kf = Keyframes(kf_frames, kf_features, kf_gray, [rings[f].points_in_rig for f in kf_frames], evidence)
    ctx = SfmContext(config, camera, ransac, ex, not isinstance(ex, InlineExecutor), warnings)
    # Every step decided with the whole run's evidence (the two sources' systematic
    # offset), then chained.
    scale = run_scale(evidence, config.scale_check, warnings)
    chain = chain_steps(ctx, kf, scale)
    adjusted = adjust_keyframes(ctx, chain.world_from_kf, kf, chain.pair_matches, chain.anchors, scale.wall_anchored)
    checks = check_adjusted(chain.checks, adjusted.world_from_kf, config.scale_check)
    length = run_length(ctx, adjusted.world_from_kf, replace(chain, checks=checks), kf, scale)
    if not math.isnan(length.correction_log):
        # One similarity of the whole run: positions and tracked points alike.
        adjusted = adjusted.scaled(math.exp(length.correction_log))
    # Every station gets a pose: keyframes from the adjustment, the others by resection.
    pending = [PendingFrame(i, k, feats, inl) for i, k, feats, inl in pending]
    resected = resect_pending(ctx, adjusted, kf, pending, next_matches, n)
    stretches = [
        UnreliableStretch(c.first_frame, c.last_frame, c.reason or c.confidence)
        for c in checks
        if not c.reliable
    ]
    stretches += resected.unreliable
    station = np.cumsum(moved) - 1
    first = np.flatnonzero(moved)
    world_from_station = np.empty((len(first), 4, 4))
    kf_of = {f: k for k, f in enumerate(kf_frames)}
    for s_idx, f in enumerate(first):
        world_from_station[s_idx] = adjusted.world_from_kf[kf_of[f]] if f in kf_of else resected.world_from_rig[f]
    world_from_rig = world_from_station[station]
    return SfmResult(
        world_from_rig=world_from_rig,
        registered=~lost[first[station]],
        keyframe=is_kf,
        stationary=~moved,
        station=station,
        wall_scale_log=length.wall_log,
        scale_correction_log=length.correction_log,
        warnings=warnings,
        bundle=adjusted.results[-1] if adjusted.results else None,
        bundle_windows=len(adjusted.results),
        scale_sigma_rel=length.sigma_rel,
        step_checks=checks,
        unreliable=merge_stretches(stretches),
        scale_source=length.source,
        laser_offset=math.exp(scale.offset_log) - 1.0,
        tracked=tracked,
    )


def _relative(a, b, fa, fb, m, ransac, warnings):
    """Relative motion of frame b from keyframe a on matched rays, or None."""
    try:
        return estimate_relative_motion(fa.rays_in_rig[m[:, 0]], fb.rays_in_rig[m[:, 1]], ransac)
    except ReconstructionError as exc:
        warnings.append(f"frames {a}->{b}: {exc}; pose kept from frame {a}")
        return None


def _refine(ga, gb, camera, fa, fb, m, motion, ransac, config, warnings, a, b):
    """Paper Sec. V-A: refine frame b's matched rays on projection planes, re-estimate."""
    inl = m[motion.inliers]
    refined = refine_matches(
        ga, gb, camera, fa.rays_in_rig[inl[:, 0]], fb.rays_in_rig[inl[:, 1]], motion.rig2_from_rig1, config.planes
    )
    fb.rays_in_rig[inl[:, 1]] = refined
    fb.pixels[inl[:, 1]] = camera.project(refined)[0]
    again = _relative(a, b, fa, fb, m, ransac, warnings)
    return again if again is not None else motion


def _tracked_step(
    extractor: FeatureExtractor,
    key_views: FrameViews,
    key_features: FrameFeatures,
    views: FrameViews,
    ransac: RansacConfig,
    config: SfmConfig,
) -> tuple[Tracks, np.ndarray, float] | None:
    """The keyframe's features tracked into a frame: (tracks, (M, 2) RANSAC-verified
    (keyframe feature, frame feature) matches, parallax in rad), or None when too few
    were tracked or no relative motion fits them (the frame then gets SIFT)."""
    tracks = track_features(extractor, key_views, key_features, views, config.tracking)
    followed = followed_count(len(key_features.rays_in_rig), config.tracking)
    if len(tracks.feature) < config.tracking.min_tracked_fraction * followed:
        return None
    m = tracks.matches
    try:
        motion = estimate_relative_motion(
            key_features.rays_in_rig[m[:, 0]], tracks.features.rays_in_rig, ransac
        )
    except ReconstructionError:
        return None
    return tracks, m[motion.inliers], _parallax(key_features, tracks.features, m, motion)


def _parallax(fa, fb, m, motion) -> float:
    """Median angle (rad) between matched rays once the rotation is removed."""
    inl = m[motion.inliers]
    if len(inl) == 0:
        return 0.0
    R = motion.rig2_from_rig1[:3, :3]
    ra = fa.rays_in_rig[inl[:, 0]] @ R.T
    rb = fb.rays_in_rig[inl[:, 1]]
    return float(np.median(np.arccos(np.clip(np.sum(ra * rb, axis=1), -1.0, 1.0))))


def _evidence(
    a, b, ga, gb, camera, laser_points_a, fa, fb, m, motion, config, warnings, executor: Executor
) -> StepEvidence | tuple[StepEvidence, Future]:
    """Both scale sources of one keyframe step (laser Eq. 17 with its peaks, feature
    depths): the evidence, or (the evidence so far, the future of the worker that
    measures the two scales; :func:`_resolve` completes it)."""
    if motion is None:
        return StepEvidence(a, b, np.eye(4), None, None, np.zeros(0), math.nan, 0, "lost")
    inl = m[motion.inliers]
    if not motion.translation_reliable:
        warnings.append(f"frames {a}->{b}: rotation only (no measurable translation)")
        return StepEvidence(a, b, motion.rig2_from_rig1.copy(), inl, None, np.zeros(0), math.nan, 0, "rotation")
    b_from_a = motion.rig2_from_rig1.copy()
    R, d = b_from_a[:3, :3], b_from_a[:3, 3]
    future = executor.submit(
        step_evidence, ga, gb, camera, laser_points_a, R, d,
        fa.rays_in_rig[inl[:, 0]], fb.rays_in_rig[inl[:, 1]], config.laser_scale, config.scale_check,
    )
    return StepEvidence(a, b, b_from_a, inl, None, np.zeros(0), math.nan, 0, "ok"), future


def _slim(features: FrameFeatures) -> FrameFeatures:
    """``features`` without their descriptors (once nothing more is matched to them:
    the rays and pixels are what the adjustment and resection read)."""
    return replace(features, descriptors=np.zeros((0, 128), np.float32))


def _resolve(part: StepEvidence | tuple[StepEvidence, Future]) -> StepEvidence:
    """The complete evidence of a step from :func:`_evidence`."""
    if isinstance(part, StepEvidence):
        return part
    ev, future = part
    lm, log_s, s_feat, n_feat = future.result()
    return replace(ev, laser=lm, log_scales=log_s, feature_scale_mm=s_feat, feature_matches=n_feat)


def _moving_frames(
    config: SfmConfig,
    inputs: SfmInputs,
    extractor: FeatureExtractor,
    executor: Executor | None,
    moved: np.ndarray,
    progress: Callable[[int], None] | None,
) -> Iterator[tuple[int, FrameViews | None, FrameFeatures | None, np.ndarray]]:
    """(frame index, views, features, grey image) of every frame where the rig moved,
    in order; fills ``moved`` (N,) and reports progress over all N frames. With
    ``config.tracking`` the views (features None: detected on the keyframes), else the
    features (views None).

    With ``inputs.moved``, ``inputs.dataset`` and an executor, they come from workers
    that decode the frames themselves (:class:`omnipipe.sfm.tasks.FeatureTask`; the
    grey image as :func:`omnipipe.sfm.tasks.compact_gray` returns it); otherwise
    every frame is read here and the stationary test runs frame by frame.
    """
    from omnipipe.executor import InlineExecutor, iter_frames

    n = inputs.n_frames
    rings = inputs.rings.rings
    channel = inputs.rig.laser.channel
    parallel = executor is not None and not isinstance(executor, InlineExecutor)
    if inputs.moved is not None and inputs.dataset is not None and parallel:
        moved[:] = inputs.moved
        frames = np.flatnonzero(moved)
        stream = iter_frames(
            executor, FeatureTask(config.features, detect=not config.tracking.enabled),
            inputs.dataset, frames, most=4, payload=lambda i: rings[i].pixels,
        )
        for i, (views, feats, gray) in stream:
            yield i, views, feats, gray
            if progress:
                progress(i + 1)
        if progress:
            progress(n)
        return
    tracker = None
    if inputs.moved is None:
        tracker = StationTracker(extractor.camera.valid_mask(), config.stations)
    else:
        moved[:] = inputs.moved
    for i in range(n):
        if tracker is not None or moved[i]:
            img = inputs.read_frame(i)
            gray = gray_without_laser(img, channel)
            if tracker is not None:
                moved[i], _ = tracker.update(gray)
            if moved[i]:
                views = extractor.frame_views(img, channel, rings[i].pixels)
                if config.tracking.enabled:
                    yield i, views, None, gray
                else:
                    yield i, None, extractor.detect(views), gray
        if progress:
            progress(i + 1)
