"""What the camera-motion stage (paper Sec. V) reads, returns and hands between its
steps: settings, inputs, the result, and the named records of a keyframe step (its
evidence, matches and metric anchors).

Conventions: lengths in mm, poses ``dst_from_src`` (4, 4); keyframes are counted
``0 .. K-1`` in frame order, a step ``a -> b`` joins two of them.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from concurrent.futures import Executor
from dataclasses import dataclass, field
from typing import TYPE_CHECKING

import numpy as np

from omnipipe.camera import CameraModel
from omnipipe.config import bounded
from omnipipe.rig import Rig
from omnipipe.sfm.bundle import BundleConfig, BundleResult
from omnipipe.sfm.features import FeatureConfig, FrameFeatures
from omnipipe.sfm.image_store import ImageStore
from omnipipe.sfm.laser_scale import LaserMatches, LaserScaleConfig
from omnipipe.sfm.planes import PlaneRefineConfig
from omnipipe.sfm.ransac import RansacConfig
from omnipipe.sfm.rotation_check import GyroCheck
from omnipipe.sfm.scale_check import ScaleCheckConfig, StepCheck, UnreliableStretch
from omnipipe.sfm.stations import StationConfig
from omnipipe.sfm.tracking import TrackConfig

if TYPE_CHECKING:
    from omnipipe.dataset import Dataset
    from omnipipe.inputs.sensors import Imu, Odometry
    from omnipipe.laser import LaserResult
    from omnipipe.sfm.flat_field import FlatFields


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
        keyframe_min_parallax_large_deg: ``keyframe_min_parallax_deg`` in views whose
            shorter side reaches ``tracking.retry_large_side_px`` (1600x1200's; the run's
            config takes it before the first frame, :func:`omnipipe.sfm.pipeline.run`);
            smaller views keep ``keyframe_min_parallax_deg`` (the robustness bench's
            short 640x480 runs lost steps at 6 deg). Both 4 deg by default: 6 deg in
            1600x1200's views cost bend's trajectory 2.4 times its error
            (benchmarks/RESULTS.md, cpu29's entry).
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
        trajectory_from: a TUM trajectory file (absolute, or relative to the dataset)
            whose poses replace the estimated motion (:mod:`omnipipe.sfm.external`);
            empty: the motion is estimated.
    """

    stations: StationConfig = field(default_factory=StationConfig)
    laser_scale: LaserScaleConfig = field(default_factory=LaserScaleConfig)
    features: FeatureConfig = field(default_factory=FeatureConfig)
    tracking: TrackConfig = field(default_factory=TrackConfig)
    ransac_threshold_px: float = bounded(1.0, gt=0)
    ransac_iterations: int = bounded(2000, ge=1)
    min_inliers: int = bounded(15, ge=1)
    rotation_only_ratio: float = bounded(0.9, gt=0, le=1)
    seed: int = bounded(0, ge=0)
    keyframe_min_parallax_deg: float = bounded(4.0, ge=0, lt=180)
    keyframe_min_parallax_large_deg: float = bounded(4.0, ge=0, lt=180)
    anchor_reach: int = bounded(3, ge=1)
    scale_from_wall: bool = True
    planes: PlaneRefineConfig = field(default_factory=PlaneRefineConfig)
    bundle: BundleConfig = field(default_factory=BundleConfig)
    scale_check: ScaleCheckConfig = field(default_factory=ScaleCheckConfig)
    trajectory_from: str = ""


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
        timestamps: (N,) frame times (s); needed to read ``odometry`` and ``imu``.
        odometry: the robot's odometry (bridges steps vision could not measure, is
            compared with the trusted ones; :mod:`omnipipe.sfm.robot_sensors`), or None.
        imu: the robot's IMU (gravity in the world frame), or None.
        station_ratio: (N,) the stationary test's ratio of each frame (its difference
            from its station's first frame over the noise-only expectation;
            :class:`omnipipe.sfm.stations.StationTracker`) when ``moved`` was given;
            None: recorded here (with ``moved``).
        handoff: the folder of a :class:`~omnipipe.handoff.FrameHandoff` where the
            decoding pass left the moving frames (those are not decoded again), or None.
    """

    rig: Rig
    read_frame: Callable[[int], np.ndarray]
    n_frames: int
    rings: LaserResult
    moved: np.ndarray | None = None
    dataset: Dataset | None = None
    timestamps: np.ndarray | None = None
    odometry: Odometry | None = None
    imu: Imu | None = None
    station_ratio: np.ndarray | None = None
    handoff: str | None = None

    @classmethod
    def of_dataset(
        cls,
        dataset: Dataset,
        rings: LaserResult,
        moved: np.ndarray | None = None,
        station_ratio: np.ndarray | None = None,
    ) -> SfmInputs:
        """The inputs of an opened dataset: its rig, frames, times and sensors."""
        return cls(
            rig=dataset.rig,
            read_frame=dataset.read_frame,
            n_frames=len(dataset),
            rings=rings,
            moved=moved,
            dataset=dataset,
            timestamps=dataset.timestamps,
            odometry=dataset.odometry,
            imu=dataset.imu,
            station_ratio=station_ratio,
        )


#: :attr:`SfmResult.scale_source` of a run whose frames the odometry alone placed.
ODOMETRY_ONLY = "odometry (no two frames related: placed along the axis)"


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
            ``scale_check.max_bias_log``, wall-placed features as the anchors too;
            :data:`ODOMETRY_ONLY` when no two frames could be related and the odometry
            placed every moving frame along the axis.
        laser_offset: run-wide laser / feature-depth length ratio minus one (removed
            before the per-step check).
        wall_scale_log: log of the factor by which the wall's lengths exceed the
            adjusted run's (NaN: too few reliable steps to tell).
        scale_correction_log: log of the factor applied to every length after the
            adjustment (:func:`combine_scales`; NaN: none).
        tracked: (N,) True for the moving frames placed by optical-flow tracks of their
            keyframe's features (:mod:`omnipipe.sfm.tracking`: no SIFT of their own);
            None: not recorded.
        gravity_world: (3,) unit vector pointing down in the world frame (from the IMU,
            :func:`omnipipe.sfm.robot_sensors.gravity_world`), or None without one.
        gravity_sigma_rad: its 1-sigma angle (rad; NaN without one).
        gyro_check: the final rotations beside the gyro's
            (:func:`omnipipe.sfm.rotation_check.gyro_check`), or None without a gyro.
    """

    world_from_rig: np.ndarray
    registered: np.ndarray
    keyframe: np.ndarray
    stationary: np.ndarray
    station: np.ndarray
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
    gravity_world: np.ndarray | None = None
    gravity_sigma_rad: float = math.nan
    gyro_check: GyroCheck | None = None


@dataclass(frozen=True)
class SfmContext:
    """What every step of one run reads: its settings, the camera, the RANSAC settings
    derived from them, where the frame-parallel work runs, and the run's warnings.

    Attributes:
        config: the stage settings.
        camera: the omni camera of the rig.
        ransac: RANSAC settings with the inlier threshold as an angle (rad).
        executor: runs the workers' tasks (:mod:`omnipipe.executor`; inline: in this
            process).
        parallel: True when ``executor`` runs tasks in other processes.
        warnings: what went wrong where, appended in order (the result's ``warnings``).
    """

    config: SfmConfig
    camera: CameraModel
    ransac: RansacConfig
    executor: Executor
    parallel: bool
    warnings: list[str]


@dataclass(frozen=True)
class StepEvidence:
    """What one keyframe step measured, before the run-level decision.

    Attributes:
        a, b: frame indices of the step's two keyframes.
        b_from_a: (4, 4) rig_b_from_rig_a with unit (or zero) translation (Eq. 10-16).
        inliers: (M, 2) RANSAC-verified (keyframe a feature, keyframe b feature)
            matches; None when no motion was found.
        laser: the laser points' template matches (Eq. 17); None when not measured.
        log_scales: (M,) each inlier match's feature-depth log length (log mm; NaN:
            none).
        feature_scale_mm: the step's feature-depth length (mm, NaN: none).
        feature_matches: matches behind ``feature_scale_mm``.
        status: ``"ok"``, ``"rotation"`` (no measurable translation) or ``"lost"`` (no
            relative motion).
        tracked: True when the matches were verified by tracks followed frame to frame
            (:mod:`omnipipe.sfm.tracking`: no period of a periodic wall skipped).
        lost_reason: why a ``"lost"`` step's relative motion is not used when one was
            found (:func:`omnipipe.sfm.motion_trust.untrusted_motions`); empty: none found.
    """

    a: int
    b: int
    b_from_a: np.ndarray
    inliers: np.ndarray | None
    laser: LaserMatches | None
    log_scales: np.ndarray
    feature_scale_mm: float
    feature_matches: int
    status: str
    tracked: bool = False
    lost_reason: str = ""

    @classmethod
    def unmeasured(
        cls, a: int, b: int, b_from_a: np.ndarray, inliers: np.ndarray | None, status: str
    ) -> StepEvidence:
        """A step's evidence before (or without) its scale measurements."""
        return cls(a, b, b_from_a, inliers, None, np.zeros(0), math.nan, 0, status)


@dataclass(frozen=True)
class StepScales:
    """Both scale measurements of one keyframe step a -> b (made in a worker).

    Attributes:
        laser: the laser's template matches (Eq. 17).
        log_scales: (M,) each inlier match's feature-depth log length (log mm; NaN:
            none).
        feature_scale_mm: the step's feature-depth length (mm, NaN: none).
        feature_matches: matches behind ``feature_scale_mm``.
    """

    laser: LaserMatches
    log_scales: np.ndarray
    feature_scale_mm: float
    feature_matches: int


@dataclass(frozen=True)
class PairMatches:
    """RANSAC inlier matches of one keyframe step, the bundle adjustment's tracks.

    Attributes:
        a, b: keyframe indices.
        matches: (M, 2) (feature in a, feature in b) index pairs.
    """

    a: int
    b: int
    matches: np.ndarray


@dataclass(frozen=True)
class Anchor:
    """Metric anchors of the bundle adjustment: points known in keyframe a's rig, seen
    at pixels of keyframe b (laser points found by template matching, Eq. 17, or
    features placed on the light-section wall).

    Attributes:
        a, b: keyframe indices.
        points_in_a: (L, 3) points in rig a, mm.
        pixels_b: (L, 2) their omni pixels in keyframe b.
        log_lengths: (L,) the step length each point alone gives (log mm); empty when
            not measured (anchors between keyframes further apart).
        epipolar: the pixels were searched along the epipolar curve of an assumed
            motion (laser matches): only their position along it is measured.
    """

    a: int
    b: int
    points_in_a: np.ndarray
    pixels_b: np.ndarray
    log_lengths: np.ndarray = field(default_factory=lambda: np.zeros(0))
    epipolar: bool = False


@dataclass(frozen=True)
class KeyframeRays:
    """A frame's correspondences with a keyframe's features.

    Attributes:
        feature: (M,) keyframe feature indices.
        rays_in_rig: (M, 3) the frame's unit rays of them.
    """

    feature: np.ndarray
    rays_in_rig: np.ndarray


@dataclass
class Keyframes:
    """The keyframes of a run and their steps (paper Sec. V, steps 2-4's measurements).

    Attributes:
        frames: (K,) frame index of each keyframe, increasing.
        features: per keyframe, its features (rays, pixels; descriptors dropped once
            nothing more is matched to them).
        grays: per keyframe, the (H, W) uint8 or uint16 grey image without the laser (the
            template matching of Eq. 17 reads them).
        ring_points: per keyframe, (N_k, 3) its laser-ring points in its rig, mm.
        evidence: (K-1,) each step's evidence, in order.
        flats: the flat fields the steps' Eq. 17 readings divide by
            (:mod:`omnipipe.sfm.flat_field`); None or empty: none.
    """

    frames: list[int]
    features: list[FrameFeatures]
    grays: ImageStore
    ring_points: list[np.ndarray]
    evidence: list[StepEvidence]
    flats: FlatFields | None = None


@dataclass(frozen=True)
class PendingFrame:
    """A moving frame too close to its keyframe to be one: resected after the bundle
    adjustment against the tracks of its keyframe and the next.

    Attributes:
        frame: its frame index.
        keyframe: its keyframe's index k (the last keyframe before it).
        features: its features (tracked or detected; descriptors dropped once matched
            to keyframe k + 1).
        inliers: (M, 2) RANSAC-verified (keyframe k feature, frame feature) matches.
    """

    frame: int
    keyframe: int
    features: FrameFeatures
    inliers: np.ndarray
