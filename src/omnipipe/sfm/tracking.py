"""Optical-flow tracking of a keyframe's features into the frames after it.

A moving frame that is not a keyframe needs only two things from its image: how far the
rig moved since the last keyframe (the keyframe decision, :mod:`omnipipe.sfm.keyframes`)
and its rays to the keyframes' tracked points (its resection). Both come from the
keyframe's SIFT keypoints followed into the frame by pyramidal Lucas-Kanade
(``cv2.calcOpticalFlowPyrLK``) on the same perspective views: about a tenth of the cost
of SIFT and descriptor matching on the frame (bend, 1600x1200: 16-19 ms for 1000
keypoints against about 270 ms). A track is kept only when the flow back from the
frame returns to within ``max_forward_backward_px`` of where it started and it lands
inside the frame's feature mask (annulus, off the laser band).

When too few of the keyframe's features are tracked (a long step, a blurred frame) the
caller falls back to SIFT on the frame.
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

from omnipipe.config import bounded
from omnipipe.errors import ConfigError, ShapeError
from omnipipe.sfm.features import FeatureExtractor, FrameFeatures, FrameViews


@dataclass(frozen=True)
class TrackConfig:
    """Lucas-Kanade tracking between keyframes.

    Attributes:
        enabled: track the keyframe's features into the frames after it (False: SIFT
            on every moving frame).
        window_px: side of the square flow window (view px, odd).
        levels: pyramid levels above the view's own resolution.
        max_forward_backward_px: largest distance between a keypoint and where its
            track, followed back to the keyframe, ends (view px).
        min_tracked_fraction: a frame whose tracks keep fewer than this fraction of
            the followed features is matched by SIFT instead.
        max_points: at most this many of the keyframe's features are followed (evenly
            over its list; the flow's cost is proportional to their number).
    """

    enabled: bool = True
    window_px: int = bounded(21, ge=5)
    levels: int = bounded(3, ge=0)
    max_forward_backward_px: float = bounded(0.5, gt=0)
    min_tracked_fraction: float = bounded(0.4, gt=0, le=1)
    max_points: int = bounded(1000, ge=8)

    def __post_init__(self) -> None:
        if self.window_px < 5 or self.window_px % 2 == 0:
            raise ConfigError("sfm.tracking.window_px", f"must be an odd number >= 5, got {self.window_px}")


@dataclass
class Tracks:
    """A keyframe's features found again in a later (or earlier) frame.

    Attributes:
        feature: (M,) index of each tracked keyframe feature.
        features: the tracks as the frame's features: (M, 3) unit rays in the frame's
            rig, (M, 2) omni pixels, no descriptors, the view and view pixels.
    """

    feature: np.ndarray
    features: FrameFeatures

    @property
    def matches(self) -> np.ndarray:
        """(M, 2) (keyframe feature, frame feature) index pairs."""
        return np.stack([self.feature, np.arange(len(self.feature))], axis=1)


def followed_count(n_features: int, config: TrackConfig) -> int:
    """How many of a keyframe's ``n_features`` features :func:`track_features` follows."""
    return min(n_features, config.max_points)


def track_features(
    extractor: FeatureExtractor,
    key_views: FrameViews,
    key_features: FrameFeatures,
    views: FrameViews,
    config: TrackConfig,
) -> Tracks:
    """Follow ``key_features`` (with their ``view_pixels``; at most ``config.max_points``
    of them, evenly over the list) from ``key_views`` into ``views`` of another frame
    of the same camera.

    Raises:
        ShapeError: ``key_features`` without view pixels.
    """
    if key_features.view_pixels is None:
        raise ShapeError("key_features.view_pixels: missing (features from FeatureExtractor.detect have them)")
    win = (config.window_px, config.window_px)
    criteria = (cv2.TERM_CRITERIA_EPS | cv2.TERM_CRITERIA_COUNT, 30, 0.01)
    n = len(key_features.view)
    followed = np.unique(np.linspace(0, n - 1, min(n, config.max_points)).round().astype(int))
    idx_parts, px_parts, view_parts, ray_parts = [], [], [], []
    for k, view in enumerate(extractor.views):
        sel = followed[key_features.view[followed] == k]
        if len(sel) == 0:
            continue
        p0 = np.ascontiguousarray(key_features.view_pixels[sel], np.float32).reshape(-1, 1, 2)
        a, b = key_views.images[k], views.images[k]
        p1, st1, _ = cv2.calcOpticalFlowPyrLK(a, b, p0, None, winSize=win, maxLevel=config.levels, criteria=criteria)
        back, st2, _ = cv2.calcOpticalFlowPyrLK(b, a, p1, None, winSize=win, maxLevel=config.levels, criteria=criteria)
        p1 = p1.reshape(-1, 2)
        ok = (st1.ravel() == 1) & (st2.ravel() == 1)
        ok &= np.linalg.norm((back - p0).reshape(-1, 2), axis=1) <= config.max_forward_backward_px
        col, row = np.round(p1[:, 0]), np.round(p1[:, 1])
        ok &= (col >= 0) & (row >= 0) & (col <= view.width - 1) & (row <= view.height - 1)
        mask = views.masks[k]
        inside = np.zeros(len(p1), bool)
        inside[ok] = mask[row[ok].astype(int), col[ok].astype(int)] > 0
        ok &= inside
        idx_parts.append(sel[ok])
        px_parts.append(p1[ok])
        view_parts.append(np.full(int(ok.sum()), k))
        ray_parts.append(view.rays(p1[ok].astype(float)))
    if not idx_parts:
        return Tracks(np.zeros(0, int), FrameFeatures.empty())
    feature = np.concatenate(idx_parts)
    vpx = np.concatenate(px_parts).astype(np.float32)
    vidx = np.concatenate(view_parts)
    rays = np.concatenate(ray_parts)
    pixels, _ = extractor.camera.project(rays)
    return Tracks(feature, FrameFeatures(rays, pixels, np.zeros((0, 128), np.float32), vidx, vpx))
