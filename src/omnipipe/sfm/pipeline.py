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
from dataclasses import dataclass, field, replace
from typing import TYPE_CHECKING

import numpy as np

from omnipipe.camera import OmniCamera, camera_from_rig
from omnipipe.errors import ReconstructionError
from omnipipe.geometry import invert
from omnipipe.image import gray_without_laser
from omnipipe.rig import Rig
from omnipipe.sfm.bundle import (
    BundleConfig,
    BundleResult,
    build_problem,
    bundle_adjust,
    keyframe_windows,
    resect_rays,
)
from omnipipe.sfm.features import (
    FeatureConfig,
    FeatureExtractor,
    FrameFeatures,
    FrameViews,
    match_features,
)
from omnipipe.sfm.image_store import ImageStore
from omnipipe.sfm.laser_scale import LaserMatches, LaserScaleConfig, match_laser_points
from omnipipe.sfm.planes import PlaneRefineConfig, refine_matches
from omnipipe.sfm.ransac import RansacConfig, estimate_relative_motion
from omnipipe.sfm.scale_check import (
    WALL_SCALE_SIGMA_FLOOR,
    ScaleCheckConfig,
    StepCheck,
    UnreliableStretch,
    decide,
    median_with_sigma,
    merge_stretches,
    wall_cylinder,
    wall_depth,
    wall_scale_correction,
)
from omnipipe.sfm.stations import StationConfig, StationTracker
from omnipipe.sfm.tasks import (
    FeatureTask,
    laser_matches,
    matched_rays,
    step_evidence,
    track_into,
)
from omnipipe.sfm.tracking import TrackConfig, Tracks, followed_count, track_features

if TYPE_CHECKING:
    from omnipipe.dataset import Dataset
    from omnipipe.laser import LaserResult


@dataclass(frozen=True)
class SfmConfig:
    """Camera-motion settings.

    Attributes:
        stations: stationary-frame detection.
        laser_scale: template matching of laser points (scale, Eq. 17).
        features: SIFT on perspective views.
        tracking: optical flow of the last keyframe's features into the moving frames
            after it (the keyframe decision and the resection of the others).
        ransac_threshold_px: RANSAC inlier threshold, in pixels of the omni image at the
            middle of the mirror annulus (converted to an angle through the camera model).
        ransac_iterations: upper bound of RANSAC iterations.
        min_inliers: fewest inliers for a usable relative motion.
        rotation_only_ratio: a step is a pure rotation when the rotation-only model
            explains at least this fraction of the essential-matrix inliers.
        seed: random seed (RANSAC).
        keyframe_min_parallax_deg: a moving frame becomes a keyframe when its matched rays
            turned at least this much (median, rotation removed) since the last keyframe;
            closer frames are resected against the adjusted tracks instead (short
            baselines give poor translation directions and laser scales).
        anchor_reach: laser points are also matched up to this many keyframes ahead for
            the bundle adjustment (1: consecutive keyframes only).
        scale_from_wall: after the bundle adjustment, the run's overall scale is set by
            the matched features placed on the light-section wall (each keyframe step's
            adjusted motion re-triangulates its matches; their depth over the wall
            depth along the same ray gives the step's length): the laser anchors keep
            the shape, the two are combined by :func:`combine_scales`.
        planes: the paper's projection-plane refinement of correspondences (off by
            default: see docs/pipeline.md for the measured comparison).
        bundle: bundle adjustment settings.
        scale_check: when a step's laser length is trusted (feature depth scale,
            consensus peaks; :mod:`omnipipe.sfm.scale_check`).
    """

    stations: StationConfig = field(default_factory=StationConfig)
    laser_scale: LaserScaleConfig = field(default_factory=LaserScaleConfig)
    features: FeatureConfig = field(default_factory=FeatureConfig)
    tracking: TrackConfig = field(default_factory=TrackConfig)
    ransac_threshold_px: float = 1.0
    ransac_iterations: int = 2000
    min_inliers: int = 15
    rotation_only_ratio: float = 0.9
    seed: int = 0
    keyframe_min_parallax_deg: float = 4.0
    anchor_reach: int = 3
    scale_from_wall: bool = True
    planes: PlaneRefineConfig = field(default_factory=PlaneRefineConfig)
    bundle: BundleConfig = field(default_factory=BundleConfig)
    scale_check: ScaleCheckConfig = field(default_factory=ScaleCheckConfig)


@dataclass
class SfmInputs:
    """What camera-motion estimation reads.

    Attributes:
        rig: the calibration.
        read_frame: frame index -> RGB/grey image (the serial path, and frames the
            executor does not decode).
        n_frames: number of frames.
        rings: the light-section result (per-frame ring pixels and metric points).
        moved: (N,) the stationary test's result when it was already made (e.g. by
            :mod:`omnipipe.pipeline.frame_pass`); None: made here, frame by frame.
        dataset: the opened dataset; with ``moved`` and an executor, the moving
            frames' features are extracted frame-parallel, each worker decoding its
            frames itself (:func:`omnipipe.executor.iter_frames`).
    """

    rig: Rig
    read_frame: Callable[[int], np.ndarray]
    n_frames: int
    rings: LaserResult
    moved: np.ndarray | None = None
    dataset: Dataset | None = None


@dataclass
class SfmResult:
    """Poses of every frame.

    Attributes:
        world_from_rig: (N, 4, 4) metric poses; world = rig frame of frame 0.
        registered: (N,) True where the pose is valid.
        keyframe: (N,) True for the keyframes (bundle-adjusted; a subset of the stations'
            first frames, the others are resected).
        stationary: (N,) True for frames that share the previous frame's station.
        station: (N,) station index of each frame.
        step_scale_mm: (K-1,) translation length between consecutive keyframes (mm).
        warnings: what went wrong where (frames with few features, rotation-only steps).
        bundle: the bundle adjustment's result (of the last window on a long run), or None.
        bundle_windows: how many windows were adjusted (1: the global adjustment).
        scale_sigma_rel: 1-sigma relative uncertainty of lengths along the run (a length
            L measured along the trajectory has sigma ``L * scale_sigma_rel``); NaN when
            the run could not estimate it.
        step_checks: (K-1,) the evidence and confidence of every keyframe step, in order.
        unreliable: stretches of frames whose motion could not be trusted (merged,
            in frame order).
        scale_source: where the run's metric scale comes from: the laser's template
            matches (Eq. 17) anchoring the bundle adjustment, then (``scale_from_wall``)
            the overall scale set by features placed on the light-section wall; or, when
            the laser runs systematically off the feature depths by more than
            ``scale_check.max_bias_log``, wall-placed features as the anchors too.
        laser_offset: run-wide laser / feature-depth length ratio minus one (removed
            before the per-step check).
        wall_scale_log: log of the factor by which the wall's lengths exceed the
            adjusted run's (NaN: too few reliable steps to tell).
        scale_correction_log: log of the factor applied to every length after the
            adjustment (:func:`combine_scales`; NaN: none).
        tracked: (N,) True for the moving frames placed by optical-flow tracks of their
            keyframe's features (:mod:`omnipipe.sfm.tracking`: no SIFT of their own);
            None: not recorded.
    """

    world_from_rig: np.ndarray
    registered: np.ndarray
    keyframe: np.ndarray
    stationary: np.ndarray
    station: np.ndarray
    step_scale_mm: np.ndarray
    warnings: list[str] = field(default_factory=list)
    bundle: BundleResult | None = None
    bundle_windows: int = 0
    scale_sigma_rel: float = math.nan
    step_checks: list[StepCheck] = field(default_factory=list)
    unreliable: list[UnreliableStretch] = field(default_factory=list)
    scale_source: str = "laser (Eq. 17)"
    laser_offset: float = 0.0
    wall_scale_log: float = math.nan
    scale_correction_log: float = math.nan
    tracked: np.ndarray | None = None


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
    world_from_kf: list[np.ndarray] = []
    kf_frames: list[int] = []
    scales: list[float] = []
    prev = None  # (frame index, features, grey)
    kf_features = []
    pair_matches: list[tuple[int, int, np.ndarray]] = []
    anchors: list[tuple[int, int, np.ndarray, np.ndarray]] = []
    # Moving frames too close to the last keyframe: (frame, keyframe index, features, matches).
    pending: list[tuple[int, int, FrameFeatures, np.ndarray | None]] = []
    # Pending frame -> its correspondences with the next keyframe (a future of
    # (keyframe feature indices, the frame's rays)).
    next_matches: dict[int, Future] = {}
    pending_views: dict[int, FrameViews] = {}  # tracked pending frames' views, until the next keyframe
    extractor = FeatureExtractor(camera, config.features)
    prev_views: FrameViews | None = None
    checks: list[StepCheck] = []
    # Each keyframe step's evidence, or the future of the worker computing it.
    evidence_parts: list[_StepEvidence | tuple[_StepEvidence, Future]] = []
    in_flight: deque[Future] = deque()
    steps_b_from_a: list[np.ndarray] = []  # rig_b_from_rig_a of each keyframe step (mm)
    anchor_logs: list[tuple[float, np.ndarray]] = []  # (length, per-point log lengths)
    min_parallax = math.radians(config.keyframe_min_parallax_deg)
    for i, views, feats, gray in _moving_frames(config, inputs, extractor, executor, moved, progress):
        if prev is None:
            world_from_kf.append(np.eye(4))
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
    # Every step decided with the whole run's evidence (the two sources' systematic
    # offset), then chained.
    offset = _source_offset(evidence, config.scale_check)
    if offset == 0.0 and len(evidence) >= 3:
        raw = _source_offset(evidence, replace(config.scale_check, max_source_offset_log=math.inf))
        if raw != 0.0:
            warnings.append(
                f"laser and feature-depth step lengths differ by {100 * (math.exp(raw) - 1):+.0f} % "
                "throughout the run: too much for a bias, every step is judged as measured"
            )
    systematic = ""
    if abs(offset) > config.scale_check.max_bias_log:
        systematic = (
            f"laser template lengths (Eq. 17) run {100 * (math.exp(offset) - 1):+.0f} % off the "
            "feature depths on the light-section wall throughout the run: the scale is taken "
            "from the feature depths (steps still checked against the laser with that offset "
            "removed)"
        )
        warnings.append(systematic)
    for k, ev in enumerate(evidence):
        b_from_a, scale, inl, lm, check = _decide_step(
            ev, offset, kf_gray[k], kf_gray[k + 1], camera, rings[ev.a].points_in_rig, config, warnings
        )
        checks.append(check)
        if systematic and math.isfinite(scale):
            scale /= math.exp(offset)  # feature-depth units: the laser's bias removed
        if scales and not math.isfinite(scale):
            # A placeholder length keeps the chain going; the step is flagged.
            scale = float(np.median([s for s in scales if s > 0] or [0.0]))
        scale = 0.0 if not math.isfinite(scale) else scale
        scales.append(scale)
        b_from_a[:3, 3] *= scale
        steps_b_from_a.append(b_from_a)
        if inl is not None:
            pair_matches.append((k, k + 1, inl))
        if systematic:
            # The laser's matches carry its bias: the wall itself anchors the scale.
            wall = _wall_anchors(ev, kf_features[k], kf_features[k + 1], rings[ev.a].points_in_rig, scale, config)
            if wall is not None:
                anchors.append((k, k + 1, wall[0], wall[1]))
                anchor_logs.append((scale, wall[2]))
        elif lm is not None and len(lm.index):
            anchors.append((k, k + 1, rings[ev.a].points_in_rig[lm.index], lm.pixels_b))
            anchor_logs.append((scale, np.log(lm.scale_mm)))
    _bridge_lost_steps(steps_b_from_a, evidence, checks)
    for b_from_a in steps_b_from_a:
        world_from_kf.append(world_from_kf[-1] @ invert(b_from_a))
    world_from_kf_arr = np.array(world_from_kf)
    bundle_stats: list[BundleResult] = []
    tracks: list[_WindowTracks | None] = []  # per adjustment window
    window_of = np.zeros(len(world_from_kf_arr), int)  # the window that adjusted each keyframe
    if config.bundle.enabled and len(world_from_kf_arr) >= 3:
        far = None
        if config.anchor_reach > 1 and not systematic:
            # Longer baselines measure the scale better: laser points of keyframe k are
            # also found in k + 2 ... k + reach with the adjusted motion, then adjust again.
            def far(world_from_window: np.ndarray, first: int, fixed: int) -> list:
                return _far_anchors(
                    camera, world_from_window, kf_gray, [rings[f] for f in kf_frames], config, ex,
                    first=first, fixed=fixed,
                )

        world_from_kf_arr, tracks, window_of, bundle_stats = _adjust_windows(
            camera, world_from_kf_arr, kf_features, pair_matches, anchors, far, config.bundle, warnings,
        )
    checks = _check_adjusted(checks, world_from_kf_arr, config.scale_check)
    wall_scale = wall_scale_correction(
        world_from_kf_arr, pair_matches, [f.rays_in_rig for f in kf_features],
        [rings[f].points_in_rig for f in kf_frames], checks, config.scale_check,
    )
    scale_source = "feature depths on the light-section wall" if systematic else "laser (Eq. 17)"
    scale_sigma = _scale_sigma(anchor_logs, offset, bool(systematic))
    applied = math.nan
    if config.scale_from_wall and wall_scale is not None:
        applied, scale_sigma = combine_scales(
            wall_scale[0], math.hypot(wall_scale[1], WALL_SCALE_SIGMA_FLOOR),
            scale_sigma, bool(systematic),
        )
        # One similarity of the whole run: positions and tracked points alike.
        gain = math.exp(applied)
        world_from_kf_arr = world_from_kf_arr.copy()
        world_from_kf_arr[:, :3, 3] *= gain
        tracks = [None if t is None else replace(t, points_in_world=t.points_in_world * gain) for t in tracks]
        scales = [s * gain for s in scales]
        if not systematic:
            scale_source = "laser (Eq. 17), combined with feature depths on the light-section wall"
    # Every station gets a pose: keyframes from the adjustment, the others by resection.
    station = np.cumsum(moved) - 1
    first = np.flatnonzero(moved)
    world_from_station = np.empty((len(first), 4, 4))
    kf_of = {f: k for k, f in enumerate(kf_frames)}
    resected = {}
    stretches = [
        UnreliableStretch(c.first_frame, c.last_frame, c.reason or c.confidence)
        for c in checks
        if not c.reliable
    ]
    # Resections in the workers, gathered in frame order.
    jobs = []
    for i, k, feats, inl in pending:
        # The next keyframe's tracks too: points on both sides of the frame fix its
        # position better than the few tracks of one keyframe (a joints wall: 0.5-0.9 mm
        # off with one side's 15-40 points).
        # The window that adjusted keyframe k + 1 holds k too (its first keyframes are the
        # window before's last): both sides' tracks in one frame of reference.
        w = int(window_of[min(k + 1, len(window_of) - 1)])
        t = tracks[w] if tracks else None
        nxt = next_matches[i].result() if t is not None and i in next_matches else None
        if isinstance(nxt, Tracks):
            nxt = (nxt.feature, nxt.features.rays_in_rig)
        job = None
        if t is not None:
            job = _submit_resection(
                ex, k - t.first, feats, inl, world_from_kf_arr[t.first :], t.feature_point,
                t.points_in_world, nxt,
            )
        jobs.append((i, k, job))
    for i, k, job in jobs:
        n_warn = len(warnings)
        resected[i] = _resection_result(i, k, job, world_from_kf_arr, warnings)
        if len(warnings) > n_warn and warnings[-1].endswith("pose of its keyframe used"):
            # Its pose is its keyframe's: the steps into and out of it are both wrong.
            end = kf_frames[k + 1] if k + 1 < len(kf_frames) else n - 1
            stretches.append(UnreliableStretch(kf_frames[k], end, "frame could not be resected"))
    for s_idx, f in enumerate(first):
        world_from_station[s_idx] = world_from_kf_arr[kf_of[f]] if f in kf_of else resected[f]
    world_from_rig = world_from_station[station]
    return SfmResult(
        world_from_rig=world_from_rig,
        registered=~lost[first[station]],
        keyframe=is_kf,
        stationary=~moved,
        station=station,
        step_scale_mm=np.array(scales),
        wall_scale_log=math.nan if wall_scale is None else wall_scale[0],
        scale_correction_log=applied,
        warnings=warnings,
        bundle=bundle_stats[-1] if bundle_stats else None,
        bundle_windows=len(bundle_stats),
        scale_sigma_rel=math.hypot(scale_sigma, SHARED_SCALE_SIGMA),
        step_checks=checks,
        unreliable=merge_stretches(stretches),
        scale_source=scale_source,
        laser_offset=math.exp(offset) - 1.0,
        tracked=tracked,
    )


def _check_adjusted(
    checks: list[StepCheck], world_from_kf: np.ndarray, config: ScaleCheckConfig
) -> list[StepCheck]:
    """Flag keyframe steps whose adjusted length left what their sources measured.

    Each source is compared after removing its run-wide ratio to the adjusted lengths
    (a consistent bias is not a jump); a step that left either by more than
    ``adjusted_agree_log`` is flagged.
    """
    lengths = np.linalg.norm(np.diff(world_from_kf[:, :3, 3], axis=0), axis=1)
    ok = [
        k for k, c in enumerate(checks)
        if k < len(lengths) and c.reliable and lengths[k] > 1e-9 and math.isfinite(c.scale_mm)
    ]

    def offsets(values: list[float]) -> tuple[np.ndarray, float]:
        v = np.array(values, float)
        with np.errstate(invalid="ignore", divide="ignore"):
            r = np.log(lengths[ok] / v) if ok else np.zeros(0)
        good = r[np.isfinite(r)]
        return r, float(np.median(good)) if len(good) >= 3 else 0.0

    r_laser, m_laser = offsets([checks[k].laser_scale_mm for k in ok])
    r_feat, m_feat = offsets([checks[k].feature_scale_mm for k in ok])
    out = list(checks)
    for j, k in enumerate(ok):
        c = checks[k]
        off = [
            (name, float(r - m))
            for name, r, m in (("laser", r_laser[j], m_laser), ("feature depth", r_feat[j], m_feat))
            if np.isfinite(r) and abs(r - m) > config.adjusted_agree_log
        ]
        if off:
            name, dev = off[0]
            reason = (
                f"bundle adjustment moved the step to {lengths[k]:.1f} mm, {100 * dev:+.0f} % "
                f"from its {name} length"
            )
            out[k] = replace(c, confidence="none", reason=reason)
    return out


# Relative 1-sigma both scale sources share, added to every run's: the laser (Eq. 17)
# and the wall-placed features both rest on the light-section ring and the relative
# motion, and on random rigs runs whose two sources agreed still came out 0.35-0.54 %
# off (bench_robustness seeds 15, 24, 25 at 800x600; cause not found). 0.25 % makes
# the +-2 sigma interval cover those runs; their spread alone does not.
SHARED_SCALE_SIGMA = 0.0025


def combine_scales(
    wall_log: float, wall_sigma: float, laser_sigma: float, wall_anchored: bool
) -> tuple[float, float]:
    """The run's scale from its two metric sources, after the bundle adjustment.

    The adjusted run (laser anchors, Eq. 17) has log scale 0 with relative sigma
    ``laser_sigma`` (its matches' spread and its run-wide gap to the feature depths);
    the wall (:func:`omnipipe.sfm.scale_check.wall_scale_correction`) says ``wall_log``
    with ``wall_sigma``. Inverse-variance weighted mean; when the two disagree by more
    than their sigmas explain (chi-square per degree of freedom > 1), the combined
    sigma is scaled by its square root (the Particle Data Group's scale factor), so a
    disagreement widens the stated uncertainty instead of hiding. A run already
    anchored on the wall (``wall_anchored``) takes the wall's value: the two are one
    source then.

    Measured (path-length error, laser alone -> combined, full-size datasets): paper
    -0.01 -> +0.05 %, bend +0.41 -> +0.07 % (docs/pipeline.md); bench_robustness
    seeds 0-29: median scale error 0.29 % (0.31 % before the stripe fix and this).

    Returns:
        (log correction to apply to every length, relative 1-sigma of the result).
    """
    if wall_anchored or not (math.isfinite(laser_sigma) and laser_sigma > 0):
        return wall_log, wall_sigma
    w_wall, w_laser = 1.0 / wall_sigma**2, 1.0 / laser_sigma**2
    mean = w_wall * wall_log / (w_wall + w_laser)
    sigma = 1.0 / math.sqrt(w_wall + w_laser)
    chi2 = wall_log**2 / (wall_sigma**2 + laser_sigma**2)
    return mean, sigma * math.sqrt(max(chi2, 1.0))


def _scale_sigma(anchor_logs, offset: float, wall_anchored: bool) -> float:
    """Relative 1-sigma of lengths: the anchors' statistical part, plus the systematic
    part. With laser anchors, the run-wide gap to the feature depths (which source is
    right within it is unknown: measured bend 0.43 % scale error, gap 0.4 %; paper
    0.02 %, gap 0.1 %). With wall anchors, 0.1 % (the scale errors of the wall-anchored
    bench_robustness runs were 0.09-0.11 %)."""
    stat = _scale_sigma_rel(anchor_logs)
    if not math.isfinite(stat):
        return stat
    return math.hypot(stat, 0.001 if wall_anchored else abs(offset))


def _scale_sigma_rel(anchor_logs: list[tuple[float, np.ndarray]]) -> float:
    """Relative 1-sigma of lengths along the run from the spread of the laser matches.

    Each step's length is the median of its points' log lengths: sigma_k from their
    robust spread over sqrt(n); independent steps add in quadrature.
    """
    var, total = 0.0, 0.0
    for length, logs in anchor_logs:
        if len(logs) < 3 or length <= 0:
            continue
        _, sig = median_with_sigma(logs)
        var += (length * sig) ** 2
        total += length
    return math.sqrt(var) / total if total > 0 else math.nan


def _relative(a, b, fa, fb, m, ransac, warnings):
    """Relative motion of frame b from keyframe a on matched rays, or None."""
    try:
        return estimate_relative_motion(fa.rays_in_rig[m[:, 0]], fb.rays_in_rig[m[:, 1]], ransac)
    except ReconstructionError as exc:
        warnings.append(f"frames {a}->{b}: {exc}; pose kept from frame {a}")
        return None


def _far_anchors(
    camera, world_from_kf, grays, rings, config, executor: Executor, first: int = 0, fixed: int = 1
) -> list:
    """Laser matches from keyframe k to k + 2 .. k + anchor_reach (adjusted relative
    poses), matched in the executor's workers, a bounded number at a time (each task
    holds two images); in (k, k + j) order.

    ``world_from_kf``: (W, 4, 4) the poses of keyframes ``first .. first + W - 1`` (an
    adjustment window; ``grays`` and ``rings`` count from keyframe 0); pairs of two of
    its first ``fixed`` keyframes (held fixed there) are left out. Returns (a, b, laser
    points in a, pixels in b) with a, b counted from ``first``.
    """
    from omnipipe.executor import ordered_map

    pairs = []
    for a in range(len(world_from_kf)):
        pts = rings[first + a].points_in_rig
        if len(pts) == 0:
            continue
        for b in range(max(a + 2, fixed), min(a + config.anchor_reach, len(world_from_kf) - 1) + 1):
            b_from_a = invert(world_from_kf[b]) @ world_from_kf[a]
            length = float(np.linalg.norm(b_from_a[:3, 3]))
            if length >= 1e-6:
                pairs.append((a, b, pts, b_from_a, length))
    # The adjusted length is known to a few per cent: search only around it, so that a
    # periodic wall cannot offer the next course.
    w = math.exp(config.scale_check.agree_log)
    jobs = (
        (grays[first + a], grays[first + b], camera, pts, b_from_a[:3, :3],
         b_from_a[:3, 3] / length, config.laser_scale, (length / w, length * w))
        for a, b, pts, b_from_a, length in pairs
    )
    out = []
    for (a, b, pts, _, _), lm in zip(pairs, ordered_map(executor, _laser_job, jobs), strict=True):
        if len(lm.index):
            out.append((a, b, pts[lm.index], lm.pixels_b))
    return out


def _laser_job(job: tuple) -> LaserMatches:
    """Executor task: :func:`omnipipe.sfm.tasks.laser_matches` of one argument tuple."""
    return laser_matches(*job)


@dataclass
class _WindowTracks:
    """The feature tracks of one adjustment window (for the resection of the frames
    between its keyframes).

    Attributes:
        first: the window's first keyframe.
        feature_point: per keyframe of the window, (N_k,) each feature's track (-1: none).
        points_in_world: (P, 3) the adjusted track points, mm.
    """

    first: int
    feature_point: list[np.ndarray]
    points_in_world: np.ndarray


def _adjust_windows(
    camera: OmniCamera,
    world_from_kf: np.ndarray,
    kf_features: list[FrameFeatures],
    pair_matches: list[tuple[int, int, np.ndarray]],
    anchors: list[tuple[int, int, np.ndarray, np.ndarray]],
    far: Callable[[np.ndarray, int, int], list] | None,
    config: BundleConfig,
    warnings: list[str],
) -> tuple[np.ndarray, list[_WindowTracks | None], np.ndarray, list[BundleResult]]:
    """Bundle adjustment of the keyframes, in consecutive windows on a long run.

    A run of up to 1.25 ``config.window_keyframes`` keyframes is adjusted at once (the
    global adjustment, keyframe 0 fixed). A longer one window by window
    (:func:`omnipipe.sfm.bundle.keyframe_windows`): each window starts from the chained
    poses carried on from its first keyframes, which the window before adjusted and
    which it holds fixed; its tracks and laser anchors are those within it. Cost and
    memory grow linearly with the run.

    Args:
        world_from_kf: (K, 4, 4) chained keyframe poses, mm.
        kf_features: the keyframes' features (pixels, rays).
        pair_matches, anchors: the steps' inlier matches and laser anchors (keyframe
            indices a, b).
        far: ``far(world_from_window, first, fixed)`` -> more laser anchors of the
            window, with its adjusted poses (then it is adjusted again); None: none.

    Returns:
        (K, 4, 4) adjusted poses; each window's tracks (None: not adjusted); (K,) the
        window that adjusted each keyframe; the windows' adjustment results.
    """
    K = len(world_from_kf)
    adjusted = world_from_kf.copy()
    tracks: list[_WindowTracks | None] = []
    window_of = np.zeros(K, int)
    stats: list[BundleResult] = []
    windows = keyframe_windows(K, config.window_keyframes, config.window_overlap)
    if len(windows) > 1 and config.solver == "auto":
        config = replace(config, solver="schur")  # see BundleConfig.solver
    for w, (s, e, fixed) in enumerate(windows):
        init = adjusted[s:e].copy()
        if w > 0:
            # The chain carried on from the last held keyframe's adjusted pose.
            j = s + fixed - 1
            carry = adjusted[j] @ invert(world_from_kf[j])
            init[fixed:] = np.einsum("ij,njk->nik", carry, world_from_kf[s + fixed : e])
        problem = build_problem(
            camera, init, [f.pixels for f in kf_features[s:e]], [f.rays_in_rig for f in kf_features[s:e]],
            [(a - s, b - s, m) for a, b, m in pair_matches if a >= s and b < e],
            [(a - s, b - s, q, px) for a, b, q, px in anchors if a >= s and b < e],
            config,
        )
        problem.fixed = fixed
        window_of[s + (fixed if w else 0) : e] = w
        if len(problem.points_in_world) < 10 or not len(problem.anchor_a):
            where = "" if len(windows) == 1 else f" of keyframes {s}-{e - 1}"
            warnings.append(f"bundle adjustment{where} skipped: too few feature tracks or laser anchors")
            adjusted[s:e] = init
            tracks.append(None)
            continue
        ba = bundle_adjust(camera, problem, config)
        extra = far(ba.world_from_rig, s, fixed) if far is not None else []
        if extra:
            problem.world_from_rig, problem.points_in_world = ba.world_from_rig, ba.points_in_world
            _append_anchors(problem, extra)
            ba = bundle_adjust(camera, problem, config)
        adjusted[s:e] = ba.world_from_rig
        stats.append(ba)
        tracks.append(_WindowTracks(s, problem.feature_point, ba.points_in_world))
    return adjusted, tracks, window_of, stats


def _append_anchors(problem, extra) -> None:
    problem.anchor_a = np.concatenate([problem.anchor_a] + [np.full(len(q), a) for a, _, q, _ in extra])
    problem.anchor_b = np.concatenate([problem.anchor_b] + [np.full(len(q), b) for _, b, q, _ in extra])
    problem.anchor_points_in_a = np.concatenate([problem.anchor_points_in_a] + [q for *_, q, _ in extra])
    problem.anchor_pixels_b = np.concatenate([problem.anchor_pixels_b] + [p for *_, p in extra])


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


def _submit_resection(
    executor: Executor, k, feats, inl, world_from_kf, feature_point, track_points, next_matches=None
) -> Future | None:
    """Resection of a non-keyframe from its matches to the tracks of keyframes k and k + 1,
    submitted to ``executor`` (None: too few tracked points). ``k``, ``world_from_kf``
    and ``feature_point`` count from the first keyframe of the tracks' window.

    ``inl``: (M, 2) RANSAC-verified matches (keyframe k feature, frame feature);
    ``next_matches``: ((M',) keyframe k + 1 feature indices, (M', 3) the frame's rays)
    from descriptor matching or tracking, verified by the resection itself (rays more
    than 2 deg off are refitted without).
    """
    rays, points = [], []
    sides = []
    if inl is not None and len(inl):
        sides.append((k, inl[:, 0], feats.rays_in_rig[inl[:, 1]]))
    if next_matches is not None and len(next_matches[0]):
        sides.append((k + 1, next_matches[0], next_matches[1]))
    for kk, idx, frame_rays in sides:
        if feature_point is None or kk >= len(feature_point):
            continue
        pid = feature_point[kk][idx]
        ok = pid >= 0
        rays.append(frame_rays[ok])
        points.append(track_points[pid[ok]])
    n_first = len(points[0]) if points and inl is not None and len(inl) else 0
    if rays and sum(len(r) for r in rays) >= 12 and n_first >= 6:
        return executor.submit(resect_rays, np.concatenate(rays), np.concatenate(points), world_from_kf[k])
    return None


def _resection_result(i: int, k: int, job: Future | None, world_from_kf, warnings) -> np.ndarray:
    """The pose of non-keyframe i from :func:`_submit_resection`; its keyframe k's pose,
    with a warning, when it could not be resected."""
    if job is not None:
        try:
            return job.result()
        except ReconstructionError as exc:
            warnings.append(f"frame {i}: {exc}")
    warnings.append(f"frame {i}: too few tracked points to resect; pose of its keyframe used")
    return world_from_kf[k].copy()


@dataclass
class _StepEvidence:
    """What one keyframe step measured, before the run-level decision."""

    a: int
    b: int
    b_from_a: np.ndarray  # (4, 4), unit translation (or zero)
    inliers: np.ndarray | None  # (M, 2) feature matches
    laser: LaserMatches | None
    log_scales: np.ndarray  # (M,) feature depth log lengths per match (NaN: none)
    feature_scale_mm: float
    feature_matches: int
    status: str  # "ok", "rotation", "lost"


def _evidence(
    a, b, ga, gb, camera, laser_points_a, fa, fb, m, motion, config, warnings, executor: Executor
) -> _StepEvidence | tuple[_StepEvidence, Future]:
    """Both scale sources of one keyframe step (laser Eq. 17 with its peaks, feature
    depths): the evidence, or (the evidence so far, the future of the worker that
    measures the two scales; :func:`_resolve` completes it)."""
    if motion is None:
        return _StepEvidence(a, b, np.eye(4), None, None, np.zeros(0), math.nan, 0, "lost")
    inl = m[motion.inliers]
    if not motion.translation_reliable:
        warnings.append(f"frames {a}->{b}: rotation only (no measurable translation)")
        return _StepEvidence(a, b, motion.rig2_from_rig1.copy(), inl, None, np.zeros(0), math.nan, 0, "rotation")
    b_from_a = motion.rig2_from_rig1.copy()
    R, d = b_from_a[:3, :3], b_from_a[:3, 3]
    future = executor.submit(
        step_evidence, ga, gb, camera, laser_points_a, R, d,
        fa.rays_in_rig[inl[:, 0]], fb.rays_in_rig[inl[:, 1]], config.laser_scale, config.scale_check,
    )
    return _StepEvidence(a, b, b_from_a, inl, None, np.zeros(0), math.nan, 0, "ok"), future


def _slim(features: FrameFeatures) -> FrameFeatures:
    """``features`` without their descriptors (once nothing more is matched to them:
    the rays and pixels are what the adjustment and resection read)."""
    return replace(features, descriptors=np.zeros((0, 128), np.float32))


def _resolve(part: _StepEvidence | tuple[_StepEvidence, Future]) -> _StepEvidence:
    """The complete evidence of a step from :func:`_evidence`."""
    if isinstance(part, _StepEvidence):
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


def _wall_anchors(ev, fa, fb, ring_points_a, scale, config, max_points: int = 120):
    """Matched features of keyframe a placed on the light-section wall: (M, 3) points in
    rig a (mm), (M, 2) their pixels in keyframe b and (M,) log lengths; None if too few.

    Only matches whose own depth ratio agrees with the step (``keep_match_log``).
    """
    if ev.inliers is None or not math.isfinite(scale) or scale <= 0 or len(ev.log_scales) == 0:
        return None
    wall = wall_cylinder(ring_points_a)
    keep = np.isfinite(ev.log_scales) & (
        np.abs(ev.log_scales - math.log(scale)) <= config.scale_check.keep_match_log
    )
    idx = np.flatnonzero(keep)
    if wall is None or len(idx) < config.scale_check.min_feature_matches:
        return None
    idx = idx[np.linspace(0, len(idx) - 1, min(max_points, len(idx))).round().astype(int)]
    rays = fa.rays_in_rig[ev.inliers[idx, 0]]
    depth = wall_depth(rays, wall)
    ok = np.isfinite(depth)
    return rays[ok] * depth[ok, None], fb.pixels[ev.inliers[idx[ok], 1]], ev.log_scales[idx[ok]]


def _source_offset(evidence: list[_StepEvidence], config: ScaleCheckConfig) -> float:
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


def _bridge_lost_steps(
    steps_b_from_a: list[np.ndarray], evidence: list[_StepEvidence], checks: list[StepCheck]
) -> None:
    """Give steps whose relative motion was not found the run's typical step, in place.

    Such a step has no measurement at all (its check says so and the stretch is reported
    unreliable); chaining it as zero length would shorten everything after it. The robot
    moves along its own axis, so the median step of the trusted ones (rotation none,
    translation the median of their translations in the earlier keyframe's frame) is the
    best guess; the report's run length already counts these steps at 100 % uncertainty
    (:func:`omnipipe.pipeline.quality.widen_for_unreliable`).

    Args:
        steps_b_from_a: (4, 4) rig_b_from_rig_a of every keyframe step, mm; lost ones are
            replaced.
        evidence, checks: the steps' evidence and decisions, same order.
    """
    trusted = [
        t[:3, 3]
        for t, ev, c in zip(steps_b_from_a, evidence, checks, strict=True)
        if ev.status == "ok" and c.confidence == "high" and np.linalg.norm(t[:3, 3]) > 0
    ]
    if len(trusted) < 3:
        return
    typical = np.median(np.array(trusted), axis=0)
    for k, ev in enumerate(evidence):
        if ev.status == "lost":
            step = np.eye(4)
            step[:3, 3] = typical
            steps_b_from_a[k] = step


def _decide_step(ev: _StepEvidence, offset, gray_a, gray_b, camera, laser_points_a, config, warnings):
    """rig_b_from_rig_a (unit translation), the length to chain (mm, NaN: none trusted),
    the inlier matches to keep (wrong-course ones dropped), the laser matches to use as
    anchors (None: untrusted) and the step's check."""
    if ev.status != "ok":
        check = StepCheck(
            ev.a, ev.b, math.nan, 0.0, math.nan, 0, 0.0 if ev.status == "rotation" else math.nan,
            "high" if ev.status == "rotation" else "none",
            "" if ev.status == "rotation" else "relative motion not found",
        )
        return ev.b_from_a.copy(), 0.0, ev.inliers, None, check
    lm = ev.laser
    gain = math.exp(offset)  # laser length = gain x feature depth length, run-wide
    check = decide(
        ev.a, ev.b, lm.scale, lm.peak_scales_mm, lm.peak_scores, ev.feature_scale_mm,
        ev.feature_matches, config.scale_check, gain,
    )
    scale = check.scale_mm
    R, d = ev.b_from_a[:3, :3], ev.b_from_a[:3, 3]
    if check.confidence == "resolved" or (check.confidence == "low" and not math.isfinite(lm.scale)):
        # Re-match the laser around the chosen length: no point may pick another course.
        w = math.exp(config.scale_check.agree_log)
        again = match_laser_points(
            gray_a.astype(np.float32), gray_b.astype(np.float32), camera, laser_points_a, R, d,
            config.laser_scale, (scale / w, scale * w),
        )
        if math.isfinite(again.scale):
            lm, scale = again, again.scale
        elif check.confidence == "resolved":
            lm = None
    elif check.confidence == "none":
        lm = None  # its laser matches would pull the adjustment to a wrong length
    elif (
        check.confidence == "high"
        and math.isfinite(ev.feature_scale_mm)
        and abs(math.log(lm.scale / (gain * ev.feature_scale_mm))) > config.scale_check.anchor_agree_log
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
        warnings.append(f"frames {ev.a}->{ev.b}: {check.reason}")
    return ev.b_from_a.copy(), scale, inl, lm, check
