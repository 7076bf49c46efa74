"""What the frame loop of camera motion hands between its parts and to the pipeline.

:class:`MovingFrame` (a frame where the rig moved, as :mod:`omnipipe.sfm.moving_frames`
yields it), :class:`StepPair` (two frames and their feature matches),
:class:`TrackedStep` (the last keyframe's tracks in a frame), :class:`LastKeyframe` (what
the loop keeps of the last keyframe) and :class:`Followed` (what the loop found,
:func:`omnipipe.sfm.keyframes.follow_keyframes`). Frame indices count all N frames of the
run; matches are (M, 2) (feature in a, feature in b) index pairs; rays are unit vectors
in the rig frame.
"""

from __future__ import annotations

from concurrent.futures import Future
from dataclasses import dataclass

import numpy as np

from omnipipe.sfm.features import FrameFeatures, FrameViews
from omnipipe.sfm.tracking import Tracks
from omnipipe.sfm.types import KeyframeRays, Keyframes, PendingFrame


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
class LastKeyframe:
    """The last keyframe: frame index, features, grey image (as it came) and views."""

    frame: int
    features: FrameFeatures
    gray: np.ndarray
    views: FrameViews | None


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
