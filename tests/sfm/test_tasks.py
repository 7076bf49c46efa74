"""What the camera-motion workers send back (omnipipe.sfm.tasks)."""

from __future__ import annotations

import numpy as np

from omnipipe.sfm.tasks import compact_gray


def test_compact_gray_is_the_smallest_exact_integer_type() -> None:
    rng = np.random.default_rng(4)
    eight = rng.integers(0, 256, (20, 30)).astype(np.float32)
    sixteen = rng.integers(0, 65536, (20, 30)).astype(np.float32)
    fractional = eight + np.float32(0.5)
    negative = eight - np.float32(300.0)
    for gray, dtype in ((eight, np.uint8), (sixteen, np.uint16), (fractional, np.float32), (negative, np.float32)):
        small = compact_gray(gray)
        assert small.dtype == dtype
        assert np.array_equal(small.astype(np.float32), gray)  # the same values back


def test_frame_gray_is_the_compact_grey_image_without_the_laser() -> None:
    from omnipipe.image import gray_without_laser
    from omnipipe.sfm.tasks import frame_gray

    rng = np.random.default_rng(5)
    rgb8 = rng.integers(0, 256, (20, 30, 3)).astype(np.uint8)
    rgb16 = rng.integers(0, 65536, (20, 30, 3)).astype(np.uint16)
    for image in (rgb8, rgb8[..., 0], rgb16, rgb16[..., 2]):
        for channel in ("red", "green", "blue", "none"):
            fast = frame_gray(image, channel)
            slow = compact_gray(gray_without_laser(image, channel))
            assert fast.dtype == slow.dtype and np.array_equal(fast, slow), (image.dtype, image.ndim, channel)


def test_gray_for_worker_sends_a_reference_only_where_the_store_holds_the_same_values() -> None:
    """Keyframe grey images go to a local pool's workers as references into the keyframe
    store when its uint16 copy is exact (8- or 16-bit); the pixels themselves inline
    (nothing to send), to other executors, and for a float grey image (fallback)."""
    from omnipipe.executor import InlineExecutor, open_executor
    from omnipipe.sfm.evidence_queue import gray_for_worker
    from omnipipe.sfm.image_store import ImageStore, StoredImage

    rng = np.random.default_rng(6)
    eight = rng.integers(0, 256, (24, 32)).astype(np.uint8)
    fractional = eight.astype(np.float32) + np.float32(0.25)
    with ImageStore() as store, open_executor(workers=2) as pool:
        for gray in (eight, fractional):
            store.append(np.clip(gray, 0, 65535).astype(np.uint16))
        ref = gray_for_worker(store, 0, eight, pool)
        assert isinstance(ref, StoredImage)
        assert np.array_equal(ref.load().astype(np.float32), eight.astype(np.float32))
        assert gray_for_worker(store, 1, fractional, pool) is fractional
        assert gray_for_worker(store, 0, eight, InlineExecutor()) is eight


def test_laser_matches_read_by_reference_in_a_worker_equal_those_sent_as_arrays() -> None:
    """Eq. 17 matched in a local worker that reads both keyframes' stored grey images
    itself gives bit for bit the matches of the grey images sent as arrays."""
    from omnipipe.executor import open_executor
    from omnipipe.geometry import invert
    from omnipipe.sfm.image_store import ImageStore
    from omnipipe.sfm.laser_scale import LaserScaleConfig
    from omnipipe.sfm.tasks import frame_gray, laser_matches
    from omnipipe.sim import make_scenario
    from omnipipe.sim.writer import build_renderer

    scenario = make_scenario("paper", frames=12, size=(640, 480), seed=4)
    renderer, poses, _, moving = build_renderer(scenario)
    b = int(np.flatnonzero(moving)[2])
    a = b - 2
    (img_a, truth_a), (img_b, _) = renderer.render(poses[a], seed=1), renderer.render(poses[b], seed=2)
    ring = truth_a["points_in_rig"][np.abs(truth_a["laser_h"]) < 0.3]
    b_from_a = invert(poses[b]) @ poses[a]
    direction = b_from_a[:3, 3] / np.linalg.norm(b_from_a[:3, 3])
    gray_a, gray_b = frame_gray(img_a, "red"), frame_gray(img_b, "red")
    assert gray_a.dtype == np.uint8
    rest = (renderer.camera, ring, b_from_a[:3, :3], direction, LaserScaleConfig())
    sent = laser_matches(gray_a, gray_b, *rest)
    with ImageStore() as store, open_executor(workers=2) as pool:
        for gray in (gray_a, gray_b):
            store.append(np.clip(gray, 0, 65535).astype(np.uint16))
        read = pool.submit(laser_matches, store.ref(0), store.ref(1), *rest).result()
    assert len(sent.index) > 20
    for name in ("index", "scale_mm", "pixels_b", "ncc", "peak_scales_mm", "peak_scores"):
        assert np.array_equal(getattr(read, name), getattr(sent, name), equal_nan=True), name
    assert read.scale == sent.scale or (np.isnan(read.scale) and np.isnan(sent.scale))


def test_feature_task_leaves_handed_frames_grey_images_in_the_handoff(tiny_dataset) -> None:
    """A frame the worker read from the hand-off comes back without its grey image (the
    caller reads it there, :func:`handed_gray`, only for the keyframes); a frame it
    decoded comes back with it; the views and the grey image are the same either way."""
    from omnipipe.dataset import open_dataset
    from omnipipe.executor import FrameSource
    from omnipipe.handoff import FrameHandoff, hand_on
    from omnipipe.sfm.features import FeatureConfig
    from omnipipe.sfm.tasks import FeatureTask, frame_gray, handed_gray

    dataset = open_dataset(tiny_dataset)
    channel = dataset.rig.laser.channel
    task = FeatureTask(FeatureConfig(), detect=False)
    plain = task(FrameSource.take(dataset, [1, 2]))
    with FrameHandoff(len(dataset)) as handoff:
        hand_on(handoff.folder, 1, dataset.read_frame(1))
        got = task(FrameSource.take(dataset, [1, 2], handoff=handoff.folder))
        assert got[0][2] is None  # frame 1: handed on, its grey image left there
        assert np.array_equal(handed_gray(handoff.folder, 1, channel), plain[0][2])
    assert np.array_equal(got[1][2], plain[1][2])  # frame 2: decoded, sent back
    assert np.array_equal(plain[0][2], frame_gray(dataset.read_frame(1), channel))
    for (views, _, _), (views0, _, _) in zip(got, plain, strict=True):
        for a, b in zip(views.images + views.masks, views0.images + views0.masks, strict=True):
            assert np.array_equal(a, b)


def test_feature_task_with_flow_sends_the_trackers_own_flow_images(tiny_dataset) -> None:
    """With ``flow`` the worker's views carry the flow images the tracker would make of
    them itself (:func:`omnipipe.sfm.tracking.flow_images` at that configuration), array
    for array; without it they carry none."""
    from omnipipe.dataset import open_dataset
    from omnipipe.executor import FrameSource
    from omnipipe.sfm.features import FeatureConfig
    from omnipipe.sfm.tasks import FeatureTask
    from omnipipe.sfm.tracking import TrackConfig, flow_images

    dataset = open_dataset(tiny_dataset)
    config = TrackConfig(highpass_px=5.0, levels=3)
    got = FeatureTask(FeatureConfig(), detect=False, flow=config)(FrameSource.take(dataset, [1, 2]))
    plain = FeatureTask(FeatureConfig(), detect=False)(FrameSource.take(dataset, [1, 2]))
    for (views, _, _), (views0, _, _) in zip(got, plain, strict=True):
        assert views0.flow is None and views.flow is not None
        want = flow_images(views0, config.highpass_px, config.levels)
        assert len(views.flow) == len(want)
        for f, w in zip(views.flow, want, strict=True):
            for name in ("raw", "highpassed", "coarse"):
                assert np.array_equal(getattr(f, name), getattr(w, name)), name
            assert f.band_px == w.band_px
            assert np.array_equal(f.coarse_band, w.coarse_band)
