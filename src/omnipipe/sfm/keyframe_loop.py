"""The keyframe decision of the frame loop (paper Sec. V, steps 2-3): :class:`KeyframeLoop`.

Each moving frame (:class:`~omnipipe.sfm.step_records.MovingFrame`, in order) is tracked
or matched to the last keyframe, and its rays' parallax (rotation removed, radians)
decides whether it is left pending or becomes the next keyframe. The steps' scale
evidence goes to :class:`~omnipipe.sfm.evidence_queue.EvidenceQueue`, the pending
frames' correspondences with the keyframe after them to
:class:`~omnipipe.sfm.pending_matches.PendingMatches`; what waits for the adjustment is
kept in the run's scratch (:class:`omnipipe.spill.Pack`).
"""

from __future__ import annotations

import math
from dataclasses import replace

import numpy as np

from omnipipe.errors import ReconstructionError
from omnipipe.executor import default_workers
from omnipipe.sfm.evidence_queue import EvidenceQueue
from omnipipe.sfm.features import (
    FeatureExtractor,
    FrameFeatures,
    FrameViews,
    match_features,
)
from omnipipe.sfm.flow_image import FlowImage
from omnipipe.sfm.image_store import ImageStore
from omnipipe.sfm.keyframe_jobs import (
    BackJob,
    budget,
    followed_back,
    held,
    parallax_share,
    slim,
    subset,
)
from omnipipe.sfm.keyframe_tracks import KeyframeTracks
from omnipipe.sfm.pair_geometry import (
    pair_parallax,
    refined_motion,
    relative_motion,
    verified,
)
from omnipipe.sfm.pending_matches import PendingMatches
from omnipipe.sfm.scale_check import TRACKED_MIN_MATCHES
from omnipipe.sfm.step_records import Followed, LastKeyframe, MovingFrame, StepPair
from omnipipe.sfm.tasks import handed_gray, handed_gray_file
from omnipipe.sfm.types import Keyframes, PendingFrame, SfmContext, SfmInputs
from omnipipe.spill import Pack


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
        # The last keyframe's tracks and the keyframe decision.
        self._tracks = KeyframeTracks(ctx, self.extractor)
        self.grays = grays
        self.moved = np.zeros(n, bool)  # filled by moving_frames
        self.keyframe = np.zeros(n, bool)
        self.lost = np.zeros(n, bool)
        self.tracked = np.zeros(n, bool)
        self.frames: list[int] = []
        self.features: list[FrameFeatures] = []
        self.pending: list[PendingFrame] = []
        # The tracked pending frames' views, until the next keyframe.
        self._pending_views: dict[int, FrameViews] = {}
        # Their flow images as the chain made them (sent with the views to be followed back).
        self._pending_images: dict[int, list[FlowImage]] = {}
        # The pending frames' parallax (rad) from their keyframe, until the next keyframe.
        self._pending_parallax: dict[int, float] = {}
        # The steps' evidence jobs, and the pending frames' correspondences with the
        # keyframe after them.
        self.evidence = EvidenceQueue(ctx, inputs, grays)
        self.matches = PendingMatches(ctx, inputs)
        # What waits for the adjustment and the resection (features of the keyframes and
        # pending frames once nothing more is matched to them): in the run's scratch.
        self._pack = Pack()
        self._last: LastKeyframe | None = None
        self._latest: MovingFrame | None = None  # the last moving frame added

    def add(self, frame: MovingFrame, closing: bool = False) -> None:
        """One moving frame: pending (too little parallax) or the next keyframe (always
        with ``closing``)."""
        self._latest = frame
        last = self._last
        features = frame.features
        if last is None:
            gray = self._gray_of(frame)
            self._keep_gray(gray, frame)
            self._add_keyframe(frame, self._tracks.keyframe_features(frame, features), 0, gray)
            return
        closing = closing or frame.frame == self.inputs.n_frames - 1  # always a keyframe
        step = self._tracks.step(last, frame)
        least = self._tracks.least_parallax(step)
        if step is not None and step.parallax_rad < least and not closing:
            # Too little baseline, followed without SIFT: resected after the adjustment.
            self._defer(frame, step.tracks.features, step.inliers, step.parallax_rad)
            self.tracked[frame.frame] = True
            return
        if step is not None:
            features, m, n_continued = self._tracks.matches(last, frame, step, self._redo_pending)
            tracked = not self._tracks.direct  # chained tracks, or descriptors they verified
        else:
            tracked = False
            if features is None:
                features = self._tracks.keyframe_features(frame, None)
            n_continued = 0
            m = match_features(last.features, features, self.ctx.config.features.ratio)
        pair = StepPair(last.frame, frame.frame, last.features, features, m)
        motion = relative_motion(self.ctx, pair)
        if motion is None:
            self.lost[frame.frame] = True  # its pose (and the chain after it) lacks this step
        parallax = pair_parallax(pair, motion) if motion is not None else math.nan
        if motion is not None and parallax < least and not closing:
            # Too little baseline for a reliable step: resected after the adjustment.
            self._defer(frame, features, m[motion.inliers], parallax)
            return
        gray = self._gray_of(frame)  # a keyframe: its grey image is needed now
        if self.ctx.config.planes.enabled and motion is not None and motion.translation_reliable:
            motion = refined_motion(self.ctx, pair, motion, last.gray, gray)
        self._keep_gray(gray, frame)  # before the step's evidence, which may read it from there
        self.evidence.measure(pair, motion, last.gray, gray, tracked)
        self._tracks.step_inliers = int(np.count_nonzero(motion.inliers)) if motion is not None else 0
        self._add_keyframe(frame, features, n_continued, gray, parallax)

    def _redo_pending(self, last: LastKeyframe) -> None:
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
            inliers = verified(self.ctx, last.features, features, match_features(last.features, features, ratio))
            self.pending[j] = replace(p, features=features, inliers=inliers)
            self.tracked[p.frame] = False

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
        self.matches.follow_back(self.evidence.step)
        self.evidence.finish()
        rings = self.inputs.rings.rings
        keyframes = Keyframes(
            self.frames,
            self.features,
            self.grays,
            [self._pack.put(rings[f].points_in_rig) for f in self.frames],
            self.evidence.held(self._pack),
            self.evidence.flat.fields,
        )
        return Followed(
            keyframes,
            self.pending,
            self.matches.next_matches,
            self.moved,
            self.keyframe,
            self.lost,
            self.tracked,
        )

    def _defer(self, frame: MovingFrame, features: FrameFeatures, inliers: np.ndarray, parallax: float) -> None:
        """``frame`` pending, with its ``inliers`` to the last keyframe and the
        ``parallax`` (rad) of its rays from it."""
        self.pending.append(PendingFrame(frame.frame, len(self.features) - 1, features, inliers))
        self._pending_parallax[frame.frame] = parallax
        if frame.views is not None:
            self._pending_views[frame.frame] = frame.views
            if self._tracks.chain is not None and self._tracks.chain.views is frame.views:
                self._pending_images[frame.frame] = self._tracks.chain.images

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
        self.evidence.add_keyframe(gray, self.inputs.rings.rings[frame.frame].pixels)

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
        self._last = LastKeyframe(frame.frame, features, gray, frame.views)
        self._tracks.start(frame, features, n_continued)
        k_new = len(self.features) - 1
        since = [j for j, p in enumerate(self.pending) if p.keyframe == k_new - 1]
        back = self._back_frames(since, parallax)
        self.matches.follow_back(self.evidence.step)  # the keyframe before: its steps to either side are matched now
        if back and frame.views is not None:
            self.matches.back = self._back_job(k_new, frame.views, features, n_continued, back)
        self._hand_over(since, features)
        if k_new >= 1:
            self.features[k_new - 1] = held(self._pack, self.features[k_new - 1])
        self.evidence.settle(self._pack)
        self.matches.settle(self._pack)

    def _back_frames(self, since: list[int], parallax: float) -> list[int]:
        """Which of the pending frames ``since`` (positions in :attr:`pending`) the new
        keyframe's features are followed back into (:func:`followed_back`; ``parallax``:
        the step's, rad), latest first."""
        viewed = [j for j in since if self.pending[j].frame in self._pending_views]
        return [
            viewed[i]
            for i in followed_back(
                [len(self.pending[j].inliers) for j in viewed],
                [parallax_share(self._pending_parallax.get(self.pending[j].frame, math.nan), parallax) for j in viewed],
                self.ctx.config.tracking,
            )
        ]

    def _back_job(
        self, k_new: int, views: FrameViews, features: FrameFeatures, n_continued: int, back: list[int]
    ) -> BackJob:
        """Keyframe ``k_new``'s new features (after its first ``n_continued``, within the
        budget) to follow back through the pending frames ``back`` (positions in
        :attr:`pending`, latest first), with the flow images the chain made of them."""
        fresh = np.arange(n_continued, len(features.view))
        return BackJob(
            k_new,
            views,
            slim(features),
            fresh[budget(0, subset(features, fresh), self.ctx.config.tracking)],
            [self._pending_views[self.pending[j].frame] for j in back],
            [self.pending[j].frame for j in back],
            self._tracks.chain.images if self._tracks.chain is not None and self._tracks.chain.views is views else None,
            [self._pending_images.get(self.pending[j].frame) for j in back],
        )

    def _hand_over(self, since: list[int], features: FrameFeatures) -> None:
        """The pending frames ``since`` (positions in :attr:`pending`) once the next
        keyframe (``features``) has come: those neither followed back nor matched yet
        matched to it by descriptors in a worker; their features and inliers into the
        run's scratch; the views, images and parallax kept for them dropped."""
        waiting = self.matches.waiting()
        for j in since:
            p = self.pending[j]
            if p.frame not in self.matches.next_matches and p.frame not in waiting and len(p.features.descriptors):
                self.matches.match(p.frame, features, p.features)
            self.pending[j] = replace(
                p, features=held(self._pack, p.features), inliers=self._pack.put(p.inliers)
            )
        self._pending_views.clear()
        self._pending_images.clear()
        self._pending_parallax.clear()
