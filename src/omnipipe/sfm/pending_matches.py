"""The pending frames' correspondences with the keyframe after them, computed in workers.

A frame left pending (too little parallax from its keyframe) is resected after the
bundle adjustment from its rays of both keyframes around it. :class:`PendingMatches`
holds its correspondences with the next keyframe (:class:`~omnipipe.sfm.types.KeyframeRays`:
feature indices of the keyframe and (M, 3) unit rays in the frame's rig) as futures:
the keyframe's features followed back through the pending frames' views
(:class:`~omnipipe.sfm.keyframe_jobs.BackJob`, :func:`omnipipe.sfm.tasks.track_back`),
or matched to the descriptors of frames without views
(:func:`omnipipe.sfm.tasks.matched_rays`).
"""

from __future__ import annotations

from collections.abc import Callable
from concurrent.futures import Future

import numpy as np

from omnipipe.sfm.features import FrameFeatures
from omnipipe.sfm.keyframe_jobs import (
    BackJob,
    done_future,
    finished,
    matched_only,
    rays_held,
    split_future,
)
from omnipipe.sfm.tasks import matched_rays, track_back
from omnipipe.sfm.types import KeyframeRays, SfmContext, SfmInputs, StepEvidence
from omnipipe.spill import Pack


class PendingMatches:
    """Pending frame -> its correspondences with the keyframe after it (:attr:`next_matches`),
    and the last keyframe's :class:`BackJob` (:attr:`back`), held until its next step."""

    def __init__(self, ctx: SfmContext, inputs: SfmInputs) -> None:
        self.ctx = ctx
        self.inputs = inputs
        self.next_matches: dict[int, Future[KeyframeRays]] = {}
        # The frames of next_matches whose arrays are not in the scratch yet: moved
        # there once the worker has finished (:meth:`settle`).
        self._open: list[int] = []
        self.back: BackJob | None = None  # the last keyframe's, until its next step

    def waiting(self) -> set[int]:
        """The frames the held :class:`BackJob` will follow back."""
        return set(self.back.frames) if self.back is not None else set()

    def match(self, frame: int, features: FrameFeatures, pending: FrameFeatures) -> None:
        """Pending ``frame`` (its features ``pending``, with descriptors) matched by
        descriptors to the next keyframe's ``features`` in a worker."""
        self.next_matches[frame] = self.ctx.executor.submit(
            matched_rays, features, pending, self.ctx.config.features.ratio
        )
        self._open.append(frame)

    def follow_back(self, step: Callable[[int], StepEvidence | None]) -> None:
        """The held :class:`BackJob` submitted to the workers, its features narrowed to
        those a keyframe step matched (its inliers to the keyframes before and after it;
        ``step(k)``: step k -> k + 1's evidence so far): the resection reads a frame's
        rays only of features in the adjustment's tracks,
        which are made of these matches, so the poses are those of following them all
        (each track's flow is its own), for a part of the work (where the chained tracks
        carry the steps, few of the new features are matched on)."""
        job, self.back = self.back, None
        if job is None:
            return
        steps = [(step(job.k - 1), 1), (step(job.k), 0)]
        matched = [e.inliers[:, side] for e, side in steps if e is not None and e.inliers is not None]
        followed = matched_only(job.followed, matched)
        if len(followed) == 0:
            for f in job.frames:
                self.next_matches[f] = done_future(KeyframeRays(np.zeros(0, int), np.zeros((0, 3))))
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
        for f, part in zip(job.frames, split_future(whole, len(job.frames)), strict=True):
            self.next_matches[f] = part
            self._open.append(f)

    def settle(self, pack: Pack) -> None:
        """The correspondences whose workers have finished: their arrays into ``pack``
        (:func:`rays_held`; the same values). A worker's exception is left in its
        future, raised where the result is asked for."""
        still = []
        for f in self._open:
            future = self.next_matches[f]
            if finished(future):
                self.next_matches[f] = done_future(rays_held(pack, future.result()))
            else:
                still.append(f)
        self._open = still
