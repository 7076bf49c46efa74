"""Camera-motion work done in the executor's workers (:mod:`omnipipe.executor`).

Each task is a pure function of its arguments, so the motion does not depend on
where it ran:

- :class:`FeatureTask`: a chunk of moving frames, each decoded in the worker (or read
  as the decoding pass left it, :mod:`omnipipe.handoff`): its perspective views (:mod:`omnipipe.sfm.features`; SIFT on them too when nothing is
  tracked between keyframes) and its grey image (for the later template matching,
  Eq. 17);
- :func:`track_back` and :func:`matched_rays`: the pending frames' correspondences with
  the next keyframe's features (optical flow back frame by frame through their views,
  :mod:`omnipipe.sfm.tracking`, or descriptor matches), for their resection;
- :func:`step_evidence`: one keyframe step's two scale measurements, the laser points'
  template matches along the epipolar curves (Eq. 17) and the matched features' depths
  on the light-section wall (:mod:`omnipipe.sfm.scale_check`).

The grey images of :func:`step_evidence` and :func:`laser_matches` come either as arrays
or, for a local pool's workers, as :class:`~omnipipe.sfm.image_store.StoredImage`
references to the run's keyframe image store, read by the worker itself.
"""

from __future__ import annotations

from dataclasses import replace
from typing import TYPE_CHECKING

import cv2
import numpy as np

from omnipipe.camera import CameraModel, camera_from_rig
from omnipipe.errors import ReconstructionError
from omnipipe.executor import worker_cached
from omnipipe.handoff import handed, handoff_path
from omnipipe.image import CHANNEL_INDEX, gray_without_laser
from omnipipe.rig import Rig
from omnipipe.sfm.features import (
    FeatureConfig,
    FeatureExtractor,
    FrameFeatures,
    FrameViews,
    match_features,
)
from omnipipe.sfm.flat_field import FlatField, as_field, divided
from omnipipe.sfm.flow_image import FlowImage
from omnipipe.sfm.image_store import StoredImage, load_image
from omnipipe.sfm.laser_scale import (
    LaserMatches,
    LaserScaleConfig,
    match_laser_points,
    match_laser_points_near,
)
from omnipipe.sfm.ransac import RansacConfig, estimate_relative_motion
from omnipipe.sfm.scale_check import (
    ScaleCheckConfig,
    feature_log_scales,
    feature_scale,
    wall_cylinder,
)
from omnipipe.sfm.tracking import TrackChain, TrackConfig, flow_images
from omnipipe.sfm.types import KeyframeRays, StepScales

if TYPE_CHECKING:
    from omnipipe.executor import FrameSource


def compact_gray(gray: np.ndarray) -> np.ndarray:
    """``gray`` (H, W) float32 as uint8 or uint16, the smallest that holds it exactly
    (whole numbers in 0..255: the green channel of an 8-bit frame; in 0..65535: of a
    16-bit one), else unchanged: a quarter or half the bytes to send between processes,
    the same values once back in float32."""
    if gray.dtype == np.float32 and gray.size:
        for dtype in (np.uint8, np.uint16):
            small = gray.astype(dtype)
            if np.array_equal(small, gray):
                return small
    return gray


def frame_gray(image: np.ndarray, channel: str) -> np.ndarray:
    """``compact_gray(gray_without_laser(image, channel))``, the same array: an 8-bit
    frame whose grey image is one channel (a red laser's green, a one-channel frame) is
    read as that channel directly (0.2 ms at 1600x1200, not 2 ms through float32)."""
    if image.dtype == np.uint8:
        if image.ndim == 2:
            return image
        if image.ndim == 3 and image.shape[2] >= 2 and CHANNEL_INDEX.get(channel) == 0:
            return cv2.extractChannel(image, 1)
    return compact_gray(gray_without_laser(image, channel))


def _extractor(rig: Rig, config: FeatureConfig) -> FeatureExtractor:
    """The feature extractor of ``rig`` with ``config``, built once per process
    (:func:`~omnipipe.executor.worker_cached`; its perspective maps take 0.5 s to build
    at 1600x1200)."""
    return worker_cached(
        "sfm.tasks.feature_extractor", (rig, config),
        lambda: FeatureExtractor(camera_from_rig(rig), config),
    )


class FeatureTask:
    """Picklable task: (views or None, features or None, grey image or None) of each
    frame of a chunk.

    With ``detect`` the frame's SIFT features (views None: nothing more is read from
    them), else its :class:`~omnipipe.sfm.features.FrameViews` (features None: the
    caller tracks into them, and detects on the keyframes; with ``flow``, the tracker's
    :func:`~omnipipe.sfm.tracking.flow_images` of them at that configuration's
    ``highpass_px`` and ``levels`` too, :attr:`FrameViews.flow`: made beside the views,
    off the caller's frame-by-frame chain). The chunk's ``payload``
    holds each frame's laser-ring pixels (N, 2), masked out of the features. The grey
    image is :func:`frame_gray`; None for a frame read from the chunk's
    :attr:`~omnipipe.executor.FrameSource.handoff` (the caller, which needs the grey
    images of the keyframes only, reads it there: :func:`handed_gray`), so that no
    frame's 2 MB grey image goes through the pipe for nothing.
    """

    def __init__(self, config: FeatureConfig, detect: bool = True, flow: TrackConfig | None = None) -> None:
        self.config = config
        self.detect = detect
        self.flow = flow

    def __call__(
        self, source: FrameSource
    ) -> list[tuple[FrameViews | None, FrameFeatures | None, np.ndarray | None]]:
        rig = source.rig
        extractor = _extractor(rig, self.config)
        channel = rig.laser.channel
        out: list[tuple[FrameViews | None, FrameFeatures | None, np.ndarray | None]] = []
        for k in range(len(source)):
            image, was_handed = _read(source, k)
            ring_pixels = None if source.payload is None else source.payload[k]
            views = extractor.frame_views(image, channel, ring_pixels)
            gray = None if was_handed else frame_gray(image, channel)
            if self.detect:
                out.append((None, extractor.detect(views), gray))
            else:
                if self.flow is not None:  # the tracker's images of them, made here
                    views = replace(views, flow=flow_images(views, self.flow.highpass_px, self.flow.levels))
                out.append((views, None, gray))
        return out


def _read(source: FrameSource, k: int) -> tuple[np.ndarray, bool]:
    """Frame ``k`` of ``source`` and whether it came from the source's hand-off folder."""
    if source.arrays is None and source.handoff is not None:
        # Mapped, not copied: the views take only its grey channel.
        image = handed(source.handoff, int(source.frames[k]), mapped=True)
        if image is not None:
            return image, True
    return source.read(k), False


def handed_gray(folder: str, frame: int, channel: str) -> np.ndarray:
    """:func:`frame_gray` of ``frame`` as the decoding pass left it in a
    :class:`~omnipipe.handoff.FrameHandoff`'s ``folder`` (where :class:`FeatureTask`
    read it, so it is there).

    Raises:
        ReconstructionError: the frame is not there (the hand-off closed under the run).
    """
    image = handed(folder, frame, mapped=True)  # mapped, not copied: one channel is taken
    if image is None:
        raise ReconstructionError(f"frame {frame}: no longer in the run's hand-off folder {folder}")
    gray = frame_gray(image, channel)
    return np.array(gray) if gray is image else gray  # a copy, not the file's pages


def handed_gray_file(folder: str, frame: int) -> str | None:
    """The file of ``frame`` in the hand-off ``folder`` when its first array is the
    frame's grey image as :func:`handed_gray` reads it (a red laser's planar 8-bit frame:
    its green plane; an 8-bit grey frame), so that the keyframe store can refer to it
    rather than write a copy (:meth:`~omnipipe.sfm.image_store.ImageStore.append_file`);
    else None (a colour frame handed on whole, another dtype, not handed on)."""
    image = handed(folder, frame, mapped=True)
    if image is None or image.ndim != 2 or image.dtype != np.uint8:
        return None
    return handoff_path(folder, frame)


def verified_matches(fa: FrameFeatures, fb: FrameFeatures, m: np.ndarray, ransac: RansacConfig) -> np.ndarray:
    """The (M, 2) (feature in a, feature in b) matches ``m`` one relative motion
    explains (RANSAC inliers, :func:`omnipipe.sfm.ransac.estimate_relative_motion`;
    none when no motion fits)."""
    try:
        motion = estimate_relative_motion(fa.rays_in_rig[m[:, 0]], fb.rays_in_rig[m[:, 1]], ransac)
    except ReconstructionError:
        return np.zeros((0, 2), int)
    return m[motion.inliers]


def track_back(
    rig: Rig,
    features_config: FeatureConfig,
    key_views: FrameViews,
    key_features: FrameFeatures,
    followed: np.ndarray,
    views: list[FrameViews],
    config: TrackConfig,
    key_images: list[FlowImage] | None = None,
    images: list[list[FlowImage] | None] | None = None,
) -> list[KeyframeRays]:
    """The keyframe's features ``followed`` (indices) tracked frame by frame into each
    of ``views`` in turn (:class:`omnipipe.sfm.tracking.TrackChain`; the frames before
    the keyframe, latest first): per frame, the tracked features and their rays.
    ``key_images`` and ``images`` (per frame, None where not given): the views'
    :func:`~omnipipe.sfm.tracking.flow_images` as the caller's own chain made them (the
    same arrays, not made again here)."""
    chain = TrackChain(_extractor(rig, features_config), key_views, key_features, config, followed, key_images=key_images)
    out = []
    for i, v in enumerate(views):
        tracks = chain.advance(v, None if images is None else images[i])
        out.append(KeyframeRays(tracks.feature, tracks.features.rays_in_rig))
    return out


def matched_rays(key_features: FrameFeatures, features: FrameFeatures, ratio: float) -> KeyframeRays:
    """Descriptor matches of a keyframe's features to a frame's: the matched keyframe
    features and the frame's rays of them."""
    m = match_features(key_features, features, ratio)
    return KeyframeRays(m[:, 0], features.rays_in_rig[m[:, 1]])


def laser_matches(
    gray_a: np.ndarray | StoredImage,
    gray_b: np.ndarray | StoredImage,
    camera: CameraModel,
    laser_points_a: np.ndarray,
    b_from_a_rotation: np.ndarray,
    b_from_a_direction: np.ndarray,
    config: LaserScaleConfig,
    scale_window_mm: tuple[float, float] | None = None,
) -> LaserMatches:
    """:func:`omnipipe.sfm.laser_scale.match_laser_points` (Eq. 17) on grey images of any
    real dtype (sent compact, e.g. uint16, or read here from a
    :class:`~omnipipe.sfm.image_store.StoredImage`; matched as float32)."""
    return match_laser_points(
        np.asarray(load_image(gray_a), np.float32),
        np.asarray(load_image(gray_b), np.float32),
        camera,
        laser_points_a,
        b_from_a_rotation, b_from_a_direction, config, scale_window_mm,
    )


def step_evidence(
    gray_a: np.ndarray | StoredImage,
    gray_b: np.ndarray | StoredImage,
    camera: CameraModel,
    laser_points_a: np.ndarray,
    b_from_a_rotation: np.ndarray,
    b_from_a_direction: np.ndarray,
    rays_a: np.ndarray,
    rays_b: np.ndarray,
    laser_scale: LaserScaleConfig,
    scale_check: ScaleCheckConfig,
    flat: FlatField | StoredImage | None = None,
) -> StepScales:
    """Both scale measurements of one keyframe step a -> b.

    Args:
        gray_a, gray_b: (H, W) grey images of keyframes a and b (any real dtype; used
            as float32), or references to them in the run's keyframe image store.
        camera: the omni camera.
        laser_points_a: (N, 3) keyframe a's laser-ring points in rig a, mm.
        b_from_a_rotation: (3, 3) and b_from_a_direction: (3,) unit translation of
            rig_b_from_rig_a from the relative motion (Eq. 10-16).
        rays_a, rays_b: (M, 2 x 3) the inlier matches' unit rays in rigs a and b.
        flat: the rig-fixed illumination both images are divided by before Eq. 17
            (:mod:`omnipipe.sfm.flat_field`; or a reference to its file); None: as they are.

    Returns:
        the laser's template matches (Eq. 17), each match's feature-depth log length,
        and the step's feature-depth length with its count.
    """
    log_s = feature_log_scales(
        rays_a, rays_b, b_from_a_rotation, b_from_a_direction, wall_cylinder(laser_points_a),
        scale_check,
    )
    s_feat, n_feat = feature_scale(log_s, scale_check)
    # The laser searched first near the feature-depth length (the full range when that
    # answer is weak or there is none): the decision needs only where the two agree.
    field = as_field(flat)  # read once for both images
    ga, gb = (divided(g, field) for g in (gray_a, gray_b))
    lm, _ = match_laser_points_near(
        ga, gb, camera, laser_points_a, b_from_a_rotation, b_from_a_direction, laser_scale,
        s_feat, scale_check.agree_log,
    )
    return StepScales(lm, log_s, s_feat, n_feat)
