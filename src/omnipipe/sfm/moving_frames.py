"""The frames where the rig moved, in order (paper Sec. V, step 1), for the frame loop.

:func:`moving_frames` yields each as a :class:`~omnipipe.sfm.step_records.MovingFrame`:
from workers that decode the frames themselves, or read here with the stationary test
frame by frame (:mod:`omnipipe.sfm.stations`); frames the robot's odometry counted
moving are moving frames too. Frame indices count all N frames of the run.
"""

from __future__ import annotations

from collections.abc import Callable, Iterator

import numpy as np

from omnipipe.executor import iter_frames, shares_files
from omnipipe.image import gray_without_laser
from omnipipe.sfm.features import FeatureExtractor
from omnipipe.sfm.robot_sensors import odometry_moved
from omnipipe.sfm.stations import StationTracker
from omnipipe.sfm.step_records import MovingFrame
from omnipipe.sfm.tasks import FeatureTask
from omnipipe.sfm.types import SfmContext, SfmInputs


def moving_frames(
    ctx: SfmContext,
    inputs: SfmInputs,
    extractor: FeatureExtractor,
    moved: np.ndarray,
    progress: Callable[[int], None] | None,
    ratios: np.ndarray | None = None,
) -> Iterator[MovingFrame]:
    """Every frame where the rig moved, in order; fills ``moved`` (N,) (and ``ratios``
    (N,), the stationary test's, when it runs here) and reports progress over all N
    frames. With ``config.tracking`` their views (features None: detected on the
    keyframes; from a local pool's workers with their flow images), else their features.

    With ``inputs.moved``, ``inputs.dataset`` and a parallel executor, they come from
    workers that decode the frames themselves (:class:`omnipipe.sfm.tasks.FeatureTask`;
    the grey image as :func:`omnipipe.sfm.tasks.compact_gray` returns it); otherwise
    every frame is read here and the stationary test runs frame by frame (paper
    Sec. V, step 1). Frames the robot's odometry counted moving
    (:func:`omnipipe.sfm.robot_sensors.odometry_moved`) are moving frames too.
    """
    config = ctx.config
    n = inputs.n_frames
    rings = inputs.rings.rings
    # Where the images cannot tell (a plain wall), the odometry's count moves the rig too.
    by_odometry = (
        odometry_moved(inputs.odometry, inputs.timestamps)
        if inputs.odometry is not None and inputs.timestamps is not None
        else np.zeros(n, bool)
    )
    if inputs.moved is not None and inputs.dataset is not None and ctx.parallel:
        moved[:] = inputs.moved | by_odometry
        flow = config.tracking if config.tracking.enabled and shares_files(ctx.executor) else None
        stream = iter_frames(
            ctx.executor,
            FeatureTask(config.features, not config.tracking.enabled, flow),
            inputs.dataset,
            np.flatnonzero(moved),
            most=4,
            payload=lambda i: rings[i].pixels,
            handoff=inputs.handoff,
        )
        for i, (views, feats, gray) in stream:
            yield MovingFrame(i, views, feats, gray)
            if progress:
                progress(i + 1)
        if progress:
            progress(n)
        return
    channel = inputs.rig.laser.channel
    tracker = None
    if inputs.moved is None:
        tracker = StationTracker(extractor.camera.valid_mask(), config.stations)
    else:
        moved[:] = inputs.moved | by_odometry

    def moving(i: int, img: np.ndarray, gray: np.ndarray) -> MovingFrame:
        views = extractor.frame_views(img, channel, rings[i].pixels)
        if config.tracking.enabled:
            return MovingFrame(i, views, None, gray)
        return MovingFrame(i, None, extractor.detect(views), gray)

    held: tuple[int, np.ndarray, np.ndarray] | None = None  # a creeping stationary frame
    for i in range(n):
        if tracker is not None or moved[i]:
            img = inputs.read_frame(i)
            gray = gray_without_laser(img, channel)
            if tracker is not None:
                moved[i], ratio = tracker.update(gray)
                if ratios is not None:
                    ratios[i] = ratio
                moved[i] |= by_odometry[i]
                if moved[i] and held is not None:  # stations.promote_creep, one frame late
                    moved[held[0]] = True
                    yield moving(*held)
                creeping = not moved[i] and ratio > config.stations.creep_factor
                held = (i, img, gray) if creeping else None
            if moved[i]:
                yield moving(i, img, gray)
        if progress:
            progress(i + 1)
