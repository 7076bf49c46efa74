"""The frame loop of camera motion (paper Sec. V, steps 1-3 and step 4's measurements).

Frames come in order (:func:`~omnipipe.sfm.moving_frames.moving_frames`: stationary
ones, whose robot stood still, are left out, :mod:`omnipipe.sfm.stations`).
:class:`~omnipipe.sfm.keyframe_loop.KeyframeLoop` takes each moving frame:

- the last keyframe's features are tracked into it by optical flow from the frame
  before (:class:`omnipipe.sfm.tracking.TrackChain`), or matched by SIFT descriptors
  (:mod:`omnipipe.sfm.features`) when too few were tracked or tracking is off; a new
  keyframe's correspondences are the best RANSAC-verified of its descriptor matches
  (global, or guided by the tracks) and the tracks themselves;
- the relative motion of the matched rays (eight-point algorithm with RANSAC,
  Eq. 10-16, :mod:`omnipipe.sfm.ransac`, :mod:`omnipipe.sfm.pair_geometry`) tells how
  far the rays turned, rotation removed: under ``keyframe_min_parallax_deg`` the frame
  is *pending* (resected after the bundle adjustment), else it becomes the next
  keyframe; when its tracks are running out (``tracking.renew_ratio``), from half that
  angle on;
- each keyframe step's two scale measurements (laser template matches, Eq. 17; feature
  depths on the light-section wall) are submitted to the executor's workers, a bounded
  number at a time (:mod:`omnipipe.sfm.evidence_queue`); the pending frames'
  correspondences with the keyframe after them too (:mod:`omnipipe.sfm.pending_matches`).

What the parts hand each other is in :mod:`omnipipe.sfm.step_records`, the worker jobs'
bookkeeping in :mod:`omnipipe.sfm.keyframe_jobs`.
"""

from __future__ import annotations

from collections.abc import Callable

import numpy as np

from omnipipe.sfm.image_store import ImageStore
from omnipipe.sfm.keyframe_loop import KeyframeLoop
from omnipipe.sfm.moving_frames import moving_frames
from omnipipe.sfm.step_records import Followed
from omnipipe.sfm.types import SfmContext, SfmInputs


def follow_keyframes(
    ctx: SfmContext,
    inputs: SfmInputs,
    grays: ImageStore,
    progress: Callable[[int], None] | None,
    ratio: np.ndarray | None = None,
) -> Followed:
    """Every moving frame through :class:`KeyframeLoop`; ``grays`` (empty) receives the
    keyframes' grey images; ``progress`` is told the frames done, over all N; ``ratio``
    (N,) receives the stationary test's ratios when it runs here (:func:`moving_frames`)."""
    loop = KeyframeLoop(ctx, inputs, grays)
    for frame in moving_frames(ctx, inputs, loop.extractor, loop.moved, progress, ratio):
        loop.add(frame)
    loop.finish()
    return loop.result()
