"""The frame loop's worker jobs and their bookkeeping.

:class:`BackJob` (a keyframe's features to follow back through the frames pending
before it) and :class:`EvidenceJob` (a keyframe step's evidence, completed by a worker);
which pending frames are followed back (:func:`followed_back`) and which features
(:func:`budget`, :func:`matched_only`); futures split or made whole
(:func:`split_future`, :func:`done_future`, :func:`finished`); and the arrays that wait
for the adjustment moved to the run's scratch (:func:`held`, :func:`rays_held`,
:func:`evidence_held`; :class:`omnipipe.spill.Pack`: the same values). Feature
indices index a frame's :class:`~omnipipe.sfm.features.FrameFeatures`; angles in radians.
"""

from __future__ import annotations

import math
from concurrent.futures import Future
from dataclasses import dataclass, replace

import numpy as np

from omnipipe.executor import Pending
from omnipipe.sfm.features import FrameFeatures, FrameViews
from omnipipe.sfm.flow_image import FlowImage
from omnipipe.sfm.tracking import TrackConfig, spread_order
from omnipipe.sfm.types import KeyframeRays, StepEvidence, StepScales
from omnipipe.spill import Pack


@dataclass(frozen=True)
class BackJob:
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
class EvidenceJob:
    """A step's evidence, completed by the worker's ``future`` when there is one."""

    evidence: StepEvidence
    future: Pending[StepScales] | None = None

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


def parallax_share(part: float, whole: float) -> float:
    """``part / whole``; NaN when ``whole`` is not positive or either is NaN."""
    return part / whole if whole > 0 else math.nan


def budget(n_first: int, features: FrameFeatures, config: TrackConfig) -> np.ndarray:
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


def split_future(whole: Future[list[KeyframeRays]], n: int) -> list[Future[KeyframeRays]]:
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


def done_future(value: KeyframeRays) -> Future[KeyframeRays]:
    """A future already holding ``value``."""
    future: Future[KeyframeRays] = Future()
    future.set_result(value)
    return future


def subset(features: FrameFeatures, idx: np.ndarray) -> FrameFeatures:
    """The features ``idx`` of ``features`` (descriptors too when it has them)."""
    desc = features.descriptors[idx] if len(features.descriptors) else np.zeros((len(idx), 128), np.float32)
    vpx = None if features.view_pixels is None else features.view_pixels[idx]
    return FrameFeatures(features.rays_in_rig[idx], features.pixels[idx], desc, features.view[idx], vpx)


def slim(features: FrameFeatures) -> FrameFeatures:
    """``features`` without their descriptors (once nothing more is matched to them:
    the rays and pixels are what the adjustment and resection read)."""
    return replace(features, descriptors=np.zeros((0, 128), np.float32))


def held(pack: Pack, features: FrameFeatures) -> FrameFeatures:
    """``features`` slimmed (:func:`slim`), their arrays in ``pack`` (the run's scratch,
    :class:`omnipipe.spill.Pack`: the same values, resident only while read)."""
    vpx = None if features.view_pixels is None else pack.put(features.view_pixels)
    return FrameFeatures(
        pack.put(features.rays_in_rig), pack.put(features.pixels), np.zeros((0, 128), np.float32),
        pack.put(features.view), vpx,
    )


def finished(future: Pending[object]) -> bool:
    """True when ``future`` (a :class:`~concurrent.futures.Future`, or a flat-fielded
    step's handle holding one once released: :mod:`omnipipe.sfm.flat_field`) holds its
    result: done, neither cancelled nor failed."""
    future = getattr(future, "future", future)
    return (
        isinstance(future, Future) and future.done() and not future.cancelled() and future.exception() is None
    )


def rays_held(pack: Pack, rays: KeyframeRays) -> KeyframeRays:
    """``rays`` with its arrays in ``pack`` (as :func:`held`)."""
    return KeyframeRays(pack.put(rays.feature), pack.put(rays.rays_in_rig))


def evidence_held(pack: Pack, evidence: StepEvidence) -> StepEvidence:
    """``evidence`` with its per-match arrays in ``pack`` (as :func:`held`)."""
    laser = evidence.laser
    if laser is not None:
        laser = replace(
            laser, index=pack.put(laser.index), scale_mm=pack.put(laser.scale_mm),
            pixels_b=pack.put(laser.pixels_b), ncc=pack.put(laser.ncc),
        )
    inliers = None if evidence.inliers is None else pack.put(evidence.inliers)
    return replace(evidence, inliers=inliers, log_scales=pack.put(evidence.log_scales), laser=laser)
