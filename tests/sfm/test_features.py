"""Feature matching: the mutual ratio-test matches."""

from __future__ import annotations

import cv2
import numpy as np

from omnipipe.sfm.features import FrameFeatures, guided_matches, match_features


def _features(descriptors: np.ndarray) -> FrameFeatures:
    n = len(descriptors)
    return FrameFeatures(np.zeros((n, 3)), np.zeros((n, 2)), descriptors, np.zeros(n, int))


def _match_both_ways(d1: np.ndarray, d2: np.ndarray, ratio: float) -> np.ndarray:
    """The full search both ways (the reference): ratio test each way, mutual check."""
    bf = cv2.BFMatcher(cv2.NORM_L2)

    def one_way(a: np.ndarray, b: np.ndarray) -> dict[int, int]:
        return {
            m[0].queryIdx: m[0].trainIdx
            for m in bf.knnMatch(a, b, k=2)
            if len(m) == 2 and m[0].distance < ratio * m[1].distance
        }

    fwd, bwd = one_way(d1, d2), one_way(d2, d1)
    return np.array([(i, j) for i, j in fwd.items() if bwd.get(j) == i], int).reshape(-1, 2)


def test_backward_search_on_chosen_features_only_gives_the_full_result() -> None:
    rng = np.random.default_rng(4)
    for n1, n2, shared in ((300, 250, 120), (40, 500, 30), (2, 2, 1), (50, 60, 0)):
        base = rng.random((shared, 128)).astype(np.float32) * 100
        d1 = np.vstack([base + rng.normal(0, 2, base.shape), rng.random((n1 - shared, 128)) * 100])
        d2 = np.vstack([base + rng.normal(0, 2, base.shape), rng.random((n2 - shared, 128)) * 100])
        d1, d2 = d1.astype(np.float32), d2[rng.permutation(n2)].astype(np.float32)
        d2[-1] = d2[0]  # a tie: two equal features in f2
        for ratio in (0.8, 1.0):
            got = match_features(_features(d1), _features(d2), ratio)
            assert np.array_equal(got, _match_both_ways(d1, d2, ratio))


def test_track_labels_join_matched_features_across_frames() -> None:
    from omnipipe.sfm.features import track_labels

    rng = np.random.default_rng(7)
    sizes = [30, 25, 40, 35]
    offset = np.concatenate([[0], np.cumsum(sizes)])
    pairs = []
    for a, b in [(0, 1), (1, 2), (2, 3), (0, 2)]:
        m = np.stack([rng.choice(sizes[a], 12, replace=False), rng.choice(sizes[b], 12, replace=False)], axis=1)
        pairs.append((a, b, m))
    labels = track_labels(offset, pairs)
    # Reference: breadth-first search over the matches, by hand.
    n = int(offset[-1])
    neighbours: list[list[int]] = [[] for _ in range(n)]
    for a, b, m in pairs:
        for i, j in m:
            neighbours[offset[a] + i].append(offset[b] + j)
            neighbours[offset[b] + j].append(offset[a] + i)
    expected = np.full(n, -1)
    label = 0
    for start in range(n):  # components numbered by their first feature
        if expected[start] >= 0:
            continue
        expected[start], queue = label, [start]
        while queue:
            for v in neighbours[queue.pop()]:
                if expected[v] < 0:
                    expected[v] = label
                    queue.append(v)
        label += 1
    assert np.array_equal(labels, expected)
    assert labels.max() + 1 < n  # some features were joined
    assert np.array_equal(track_labels(offset, []), np.arange(n))


def _periodic_wall(rng: np.random.Generator, period: float, shift: float):
    """Features on a wall that repeats every ``period`` rad of azimuth (3 kinds of
    texel, 12 periods): frame 2 sees it turned by ``shift`` rad; each kind's
    descriptor is the same in every period (plus noise)."""
    kinds = rng.random((3, 128)).astype(np.float32) * 100
    az = np.concatenate([np.arange(12) * period + k * period / 3 for k in range(3)])
    kind = np.repeat(np.arange(3), 12)

    def frame(offset: float) -> FrameFeatures:
        a = az + offset
        rays = np.column_stack([np.cos(a), np.sin(a), np.zeros_like(a)])
        desc = (kinds[kind] + rng.normal(0, 1, (len(a), 128))).astype(np.float32)
        return FrameFeatures(rays, np.zeros((len(a), 2)), desc, np.zeros(len(a), int))

    return frame(0.0), frame(shift)


def test_guided_matching_keeps_each_feature_in_its_own_period() -> None:
    rng = np.random.default_rng(7)
    period, shift = 0.3, 0.07  # the wall turned by under a quarter period
    f1, f2 = _periodic_wall(rng, period, shift)
    # Every period looks alike: the global ratio test finds (almost) nothing.
    assert len(match_features(f1, f2, 0.8)) <= 2
    # Predicted a little off the truth (a track's error), searched within under half a
    # third of the period (the nearest other texel of any kind): each finds itself.
    a = np.arctan2(f1.rays_in_rig[:, 1], f1.rays_in_rig[:, 0]) + shift + rng.normal(0, 0.01, 36)
    predicted = np.column_stack([np.cos(a), np.sin(a), np.zeros(36)])
    m = guided_matches(f1, f2, np.arange(36), predicted, radius_rad=0.04, ratio=0.8)
    assert len(m) == 36 and np.array_equal(m[:, 0], m[:, 1])
    # A prediction a whole period off finds the wrong period's twin: the guide decides.
    wrong = predicted @ np.array([[np.cos(period), np.sin(period), 0], [-np.sin(period), np.cos(period), 0], [0, 0, 1]])
    m = guided_matches(f1, f2, np.arange(36), wrong, radius_rad=0.04)
    assert np.all(m[:, 1] != m[:, 0])
    # Features without a descriptor (tracked points, corners) are never matched.
    f2.descriptors[:] = 0
    assert len(guided_matches(f1, f2, np.arange(36), predicted, radius_rad=0.04)) == 0
    assert len(match_features(f1, f2)) == 0


def test_sift_on_a_reduced_view_reports_keypoints_in_the_views_pixels() -> None:
    """SIFT on the view reduced (``detect_scale`` 0.5, 0.35, 0.3), keypoints back in the
    view's pixels: each blob found where it is (within 0.25 px; OpenCV's own full-size
    keypoints lie a quarter pixel off), with no common offset (under 0.05 px)."""
    from omnipipe.sfm.features import _sift_view

    rng = np.random.default_rng(11)
    h, w = 200, 260
    yy, xx = np.mgrid[0:h, 0:w]
    centres = np.array([[x, y] for x in range(40, 240, 50) for y in range(40, 180, 50)], float)
    centres += rng.uniform(-3, 3, centres.shape)
    img = np.full((h, w), 40.0)
    for cx, cy in centres:
        img += 180.0 * np.exp(-((xx - cx) ** 2 + (yy - cy) ** 2) / (2 * 5.0**2))
    img = img.clip(0, 255).astype(np.uint8)
    mask = np.full((h, w), 255, np.uint8)
    sift = cv2.SIFT_create(nfeatures=500, contrastThreshold=0.01)
    for scale, tol in ((1.0, 0.45), (0.5, 0.25), (0.35, 0.25), (0.3, 0.25)):
        pts, desc = _sift_view(sift, img, mask, scale)
        assert desc is not None and len(desc) == len(pts)
        d = pts[:, None] - centres[None]
        near = np.linalg.norm(d, axis=2)
        assert np.all(near.min(axis=0) < tol), (scale, near.min(axis=0))
        if scale < 1:
            offset = d[near.argmin(axis=0), np.arange(len(centres))].mean(axis=0)
            assert np.all(np.abs(offset) < 0.05), (scale, offset)
    # Bit for bit OpenCV's keypoints on the reduced view, mapped to the view's pixels.
    small = cv2.resize(img, (130, 100), interpolation=cv2.INTER_AREA)
    kps, ref_desc = sift.detectAndCompute(small, cv2.resize(mask, (130, 100), interpolation=cv2.INTER_NEAREST))
    ref = np.array([((k.pt[0] + 0.25) * 2.0 - 0.5, (k.pt[1] + 0.25) * 2.0 - 0.5) for k in kps], np.float32)
    pts, desc = _sift_view(sift, img, mask, 0.5)
    assert np.array_equal(pts, ref.astype(float)) and np.array_equal(desc, ref_desc)


def test_sift_at_full_size_is_opencvs_detection() -> None:
    """At scale 1 (small views) the detection is OpenCV's on the view as it is."""
    from omnipipe.sfm.features import _sift_view

    rng = np.random.default_rng(3)
    img = cv2.GaussianBlur(rng.integers(0, 255, (120, 90), dtype=np.uint8), (0, 0), 2.0)
    mask = np.full(img.shape, 255, np.uint8)
    mask[:, :20] = 0
    sift = cv2.SIFT_create(nfeatures=200, contrastThreshold=0.01)
    ka, da = sift.detectAndCompute(img, mask)
    kb, db = _sift_view(sift, img, mask, 1.0)
    assert len(ka) > 10
    assert np.array_equal(np.array([k.pt for k in ka], float), kb) and np.array_equal(da, db)


def test_detection_scale_keeps_small_views_at_full_size() -> None:
    """0.3 where the reduced view's shorter side keeps ``detect_min_side_px`` (the
    1600x1200 views, 335x484 px); full size for other-rig's (285x398 px), 640x480's
    (131x189 px) and when off."""
    from omnipipe.sfm.features import FeatureConfig, detection_scale

    cfg = FeatureConfig()
    assert cfg.detect_scale == 0.3 and cfg.detect_min_side_px == 96
    assert detection_scale(cfg, 335, 484) == 0.3
    assert detection_scale(cfg, 320, 400) == 0.3
    assert detection_scale(cfg, 319, 400) == 1.0
    assert detection_scale(cfg, 285, 398) == 1.0
    assert detection_scale(cfg, 131, 189) == 1.0
    assert detection_scale(FeatureConfig(detect_scale=1.0), 335, 484) == 1.0
    assert detection_scale(FeatureConfig(detect_min_side_px=80), 285, 398) == 0.3


def test_views_pickle_their_masks_one_bit_a_pixel_and_come_back_the_same() -> None:
    """FrameViews go between processes with their 0/255 masks packed (a third of their
    bytes before); any other mask is sent as it is. Both come back value for value."""
    import pickle

    from omnipipe.sfm.features import FrameViews, PackedMasks, pack_masks

    rng = np.random.default_rng(3)
    images = [rng.integers(0, 256, (37, 29), dtype=np.uint8) for _ in range(3)]
    masks = [np.where(rng.random((37, 29)) < 0.7, 255, 0).astype(np.uint8) for _ in range(3)]
    masks.append(np.zeros((0, 5), np.uint8))
    images.append(np.zeros((0, 5), np.uint8))
    views = FrameViews(images, masks)
    assert isinstance(pack_masks(masks), PackedMasks)
    back = pickle.loads(pickle.dumps(views))
    assert all(b.dtype == np.uint8 and np.array_equal(a, b) for a, b in zip(masks, back.masks, strict=True))
    assert all(np.array_equal(a, b) for a, b in zip(images, back.images, strict=True))
    assert views.masks is masks  # pickling leaves the object's own masks alone
    grey = [m // 255 * 7 for m in masks]  # not 0/255: sent unpacked
    assert pack_masks(grey) is grey
    again = pickle.loads(pickle.dumps(FrameViews(images, grey)))
    assert all(np.array_equal(a, b) for a, b in zip(grey, again.masks, strict=True))


def test_view_masks_resample_the_laser_band_only_where_it_reaches_and_equal_the_whole_view() -> None:
    """frame_views resamples a frame's laser band only in the view rows whose omni radii
    it can reach (ViewMask.with_band): the masks equal those of resampling and eroding
    every view whole, for rings, rings with gaps (chords inside the ring), scattered
    points, one point and none."""
    from omnipipe.sfm.features import FeatureExtractor
    from omnipipe.sfm.tasks import camera_from_rig
    from omnipipe.sim import make_scenario

    rig = make_scenario("paper-small", frames=2, seed=0).rig
    extractor = FeatureExtractor(camera_from_rig(rig))
    cam = extractor.camera
    rng = np.random.default_rng(11)
    image = rng.integers(0, 255, (cam.height, cam.width, 3), np.uint8)

    def whole(laser_pixels: np.ndarray | None) -> list[np.ndarray]:
        mask = extractor.annulus.copy()
        if laser_pixels is not None and len(laser_pixels):
            pts = np.round(laser_pixels * 4).astype(np.int32).reshape(-1, 1, 2)
            cv2.polylines(mask, [pts], False, 0, thickness=int(2 * extractor.config.laser_margin_px + 1), shift=2)
        out = []
        for mx, my, valid in extractor.maps:
            vmask = cv2.remap(mask, mx, my, cv2.INTER_NEAREST)
            vmask[~valid] = 0
            out.append(cv2.erode(vmask, np.ones((5, 5), np.uint8)))
        return out

    cases: list[np.ndarray | None] = [None, np.zeros((0, 2)), np.array([[cam.cx + 0.5 * cam.radius_max, cam.cy]])]
    for j in range(24):
        k = int(rng.integers(2, 80))
        if j % 4 == 0:  # anywhere in the image
            cases.append(rng.uniform([0, 0], [cam.width, cam.height], size=(k, 2)))
        else:  # a ring at some radius, its samples with gaps
            ang = np.sort(rng.uniform(0, 2 * np.pi, k))
            r = rng.uniform(cam.radius_min - 10, cam.radius_max + 10) + rng.normal(0, 2, k)
            cases.append(np.column_stack([cam.cx + r * np.cos(ang), cam.cy + r * np.sin(ang)]))
    reached = 0
    for laser_pixels in cases:
        masks = extractor.frame_views(image, rig.laser.channel, laser_pixels).masks
        expected = whole(laser_pixels)
        assert all(np.array_equal(m, e) for m, e in zip(masks, expected, strict=True))
        reached += sum(not np.array_equal(e, b.eroded) for e, b in zip(expected, extractor.view_masks, strict=True))
    assert reached > 20  # the bands did cut the views
