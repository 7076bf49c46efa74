"""Optical-flow tracking of keyframe features (omnipipe.sfm.tracking)."""

from __future__ import annotations

import math
from dataclasses import replace

import numpy as np
import pytest

from omnipipe.camera import camera_from_rig
from omnipipe.config import dataclass_from_dict
from omnipipe.errors import ConfigError
from omnipipe.geometry import invert
from omnipipe.sfm.features import FeatureExtractor, FrameFeatures, FrameViews
from omnipipe.sfm.geometry import triangulate_pairs
from omnipipe.sfm.ransac import estimate_relative_motion
from omnipipe.sfm.tracking import (
    TrackChain,
    TrackConfig,
    Tracks,
    _lk,
    corner_features,
    flow_images,
    spread_order,
    track_features,
)
from omnipipe.sim import make_scenario
from omnipipe.sim.render import Renderer
from omnipipe.sim.scenario import Scenario
from omnipipe.sim.writer import build_renderer


@pytest.fixture(scope="module")
def two_frames():
    """(extractor, views of frame a, views of frame b, rig_b_from_rig_a) of a rendered
    paper-small run, b a few mm of travel after a."""
    scenario = make_scenario("paper-small", frames=12, size=(640, 480), seed=3)
    renderer, poses, _, moving = build_renderer(scenario)
    b = int(np.flatnonzero(moving)[1])
    a = b - 1
    extractor = FeatureExtractor(camera_from_rig(scenario.rig))
    channel = scenario.rig.laser.channel
    views = [
        extractor.frame_views(renderer.expose(renderer.irradiance(poses[f], seed=7 + f)[0], seed=7 + f), channel)
        for f in (a, b)
    ]
    return extractor, views[0], views[1], invert(poses[b]) @ poses[a]


def _epipolar_deg(rays_a: np.ndarray, rays_b: np.ndarray, b_from_a: np.ndarray) -> np.ndarray:
    """Angle (deg) of each ray of b off the epipolar plane of its ray of a."""
    t = b_from_a[:3, 3] / np.linalg.norm(b_from_a[:3, 3])
    normal = np.cross(t, rays_a @ b_from_a[:3, :3].T)
    normal /= np.linalg.norm(normal, axis=1, keepdims=True)
    return np.degrees(np.abs(np.arcsin(np.sum(normal * rays_b, axis=1))))


def test_tracks_lie_on_the_true_epipolar_planes(two_frames) -> None:
    extractor, views_a, views_b, b_from_a = two_frames
    assert np.linalg.norm(b_from_a[:3, 3]) > 1.0  # mm: the frames really moved
    key = extractor.detect(views_a)
    tracks = track_features(extractor, views_a, key, views_b, TrackConfig())
    assert len(tracks.feature) >= 0.5 * min(len(key.view), TrackConfig().max_points)
    err = _epipolar_deg(key.rays_in_rig[tracks.feature], tracks.features.rays_in_rig, b_from_a)
    # As close to the true epipolar planes as SIFT's own matches of the pair (median
    # 0.24, 95 % 1.16 view px here): sub-pixel.
    view = extractor.views[0]
    centre = np.array([[view.width / 2, view.height / 2], [view.width / 2 + 1, view.height / 2]])
    r = view.rays(centre)
    px_deg = math.degrees(math.acos(float(np.clip(r[0] @ r[1], -1, 1))))
    assert np.median(err) < 0.35 * px_deg
    assert np.percentile(err, 95) < 1.5 * px_deg
    # Omni pixels and rays of a track agree through the camera model.
    back, _ = extractor.camera.project(tracks.features.rays_in_rig)
    assert np.allclose(back, tracks.features.pixels)


def test_a_frame_tracked_into_itself_stays_put(two_frames) -> None:
    extractor, views_a, _, _ = two_frames
    key = extractor.detect(views_a)
    config = TrackConfig(max_points=300)
    tracks = track_features(extractor, views_a, key, views_a, config)
    # Every followed feature inside the mask is found where it is.
    assert len(tracks.feature) >= 0.95 * 300
    assert np.max(np.abs(tracks.features.view_pixels - key.view_pixels[tracks.feature])) < 0.01
    assert np.all(tracks.features.view == key.view[tracks.feature])


def test_nothing_is_tracked_into_a_blank_frame(two_frames) -> None:
    extractor, views_a, _, _ = two_frames
    key = extractor.detect(views_a)
    blank = FrameViews([np.zeros_like(v) for v in views_a.images], views_a.masks)
    tracks = track_features(extractor, views_a, key, blank, TrackConfig())
    assert len(tracks.feature) < 0.05 * min(len(key.view), TrackConfig().max_points)


@pytest.mark.parametrize(
    ("field", "value"),
    [("window_px", 4), ("window_px", 20), ("levels", -1), ("max_forward_backward_px", 0.0),
     ("min_tracks", 7), ("max_points", 3), ("renew_ratio", 1.5), ("retry_lost_share", -0.1),
     ("retry_lost_share", 1.5), ("retry_lost_share_large", 1.5), ("retry_large_side_px", -1),
     ("max_points_large", 3)],
)
def test_bad_settings_name_their_field(field: str, value: float) -> None:
    with pytest.raises(ConfigError, match=f"sfm.tracking.{field}"):
        dataclass_from_dict(TrackConfig, {field: value}, "sfm.tracking")


def _chain_through(
    scenario: Scenario, renderer: Renderer, poses: np.ndarray
) -> tuple[FeatureExtractor, FrameFeatures, TrackChain, Tracks]:
    """Keyframe features of frame 0 followed frame to frame through every rendered pose:
    (extractor, keyframe features, the chain, the tracks in the last frame)."""
    extractor = FeatureExtractor(camera_from_rig(scenario.rig))
    channel = scenario.rig.laser.channel
    views = [
        extractor.frame_views(renderer.expose(renderer.irradiance(p, seed=5 + i)[0], seed=5 + i), channel)
        for i, p in enumerate(poses)
    ]
    key = extractor.detect(views[0])
    chain = TrackChain(extractor, views[0], key, TrackConfig())
    for v in views[1:]:
        tracks = chain.advance(v)
    return extractor, key, chain, tracks


@pytest.mark.slow
def test_chained_tracks_follow_a_tiled_wall_without_skipping_a_period() -> None:
    """tiled-culvert-small: 30 mm tiles, 2-7 mm of travel between frames, 22.7 mm over
    the first 5: a track that jumped a tile would put its step a period (30 mm) off.
    Followed frame to frame, the tracks land on the true wall points, and the step
    their triangulation gives is the true one."""
    scenario = make_scenario("tiled-culvert-small", frames=6, seed=0)
    renderer, poses, _, _ = build_renderer(scenario)
    extractor, key, chain, tracks = _chain_through(scenario, renderer, poses)
    assert len(tracks.feature) >= 0.5 * chain.n_followed
    # The true ray in frame 5 of each keyframe feature: where its ray meets the 600 mm wall.
    radius = 0.5 * scenario.pipe.inner_diameter_mm
    rays_w = key.rays_in_rig[tracks.feature] @ poses[0][:3, :3].T
    o = poses[0][:3, 3]
    a, b = np.sum(rays_w[:, :2] ** 2, axis=1), 2 * rays_w[:, :2] @ o[:2]
    s = (-b + np.sqrt(b * b - 4 * a * (o[:2] @ o[:2] - radius**2))) / (2 * a)
    in_b = (o + s[:, None] * rays_w - poses[5][:3, 3]) @ poses[5][:3, :3]
    true_b = in_b / np.linalg.norm(in_b, axis=1, keepdims=True)
    err_px = np.arccos(np.clip(np.sum(true_b * tracks.features.rays_in_rig, axis=1), -1, 1))
    err_px /= extractor.camera.angular_resolution()
    # A tile is about 10 px here: the tracks are on their own tile, to a fraction of a px.
    assert np.median(err_px) < 0.3 and np.mean(err_px > 3.0) < 0.1
    # The step from the tracks alone (Eq. 10-16 with RANSAC; its length from the
    # wall's true depth along each ray): within 3 % of the true 22.7 mm, where tracks
    # a tile off would make it a different step altogether.
    true_len = float(np.linalg.norm((invert(poses[5]) @ poses[0])[:3, 3]))
    unit = estimate_relative_motion(key.rays_in_rig[tracks.feature], tracks.features.rays_in_rig).rig2_from_rig1
    _, depth = triangulate_pairs(key.rays_in_rig[tracks.feature], tracks.features.rays_in_rig, unit)
    ok = depth[:, 0] > 0
    # Each track's depth with a unit step, against the wall's true depth along its ray.
    length = float(np.median(s[ok] / depth[ok, 0]))
    assert abs(length - true_len) < 0.03 * true_len


def test_corners_top_up_a_keyframe_with_few_sift_features(two_frames) -> None:
    extractor, views_a, views_b, b_from_a = two_frames
    key = extractor.detect(views_a)
    few = replace(key, rays_in_rig=key.rays_in_rig[:50], pixels=key.pixels[:50], descriptors=key.descriptors[:50],
                  view=key.view[:50], view_pixels=key.view_pixels[:50])  # fmt: skip
    config = TrackConfig(min_corner_points=400)
    corners = corner_features(extractor, views_a, few, config)
    assert 200 <= len(corners.view) <= 400 + len(extractor.views)
    assert not np.any(corners.descriptors)  # never matched by descriptor
    # Each corner keeps its distance from the SIFT features of its view.
    for k in range(len(extractor.views)):
        c, s = corners.view_pixels[corners.view == k], few.view_pixels[few.view == k]
        if len(c) and len(s):
            assert np.min(np.linalg.norm(c[:, None] - s[None], axis=2)) >= config.min_corner_distance_px - 1
    # Followed frame to frame, the corners' tracks are as good as SIFT keypoints'.
    chain = TrackChain(extractor, views_a, corners, TrackConfig())
    tracks = chain.advance(views_b)
    assert len(tracks.feature) >= 0.5 * chain.n_followed
    err = _epipolar_deg(corners.rays_in_rig[tracks.feature], tracks.features.rays_in_rig, b_from_a)
    view = extractor.views[0]
    r = view.rays(np.array([[view.width / 2, view.height / 2], [view.width / 2 + 1, view.height / 2]]))
    px_deg = math.degrees(math.acos(float(np.clip(r[0] @ r[1], -1, 1))))
    assert np.median(err) < 0.35 * px_deg
    # Enough SIFT features: no corners.
    assert len(corner_features(extractor, views_a, key, TrackConfig(min_corner_points=len(key.view))).view) == 0


@pytest.fixture(scope="module")
def far_step():
    """(renderer, poses of a and b, extractor, views of a and b) of other-rig at 800x640:
    b two moving frames after a: the 150 mm pipe's wall moves about 34 view px, so far
    that a high-passed view's pyramid has nothing left at its coarse levels."""
    scenario = make_scenario("other-rig", frames=4, size=(800, 640), seed=0)
    renderer, poses, _, moving = build_renderer(scenario)
    a = int(np.flatnonzero(moving)[0]) - 1
    b = int(np.flatnonzero(moving)[1])
    extractor = FeatureExtractor(camera_from_rig(scenario.rig))
    channel = scenario.rig.laser.channel
    views = [
        extractor.frame_views(renderer.expose(renderer.irradiance(poses[f], seed=3 + f)[0], seed=3 + f), channel)
        for f in (a, b)
    ]
    return renderer, poses[a], poses[b], extractor, views[0], views[1]


@pytest.mark.parametrize("highpass_px", [0.0, 8.0])
def test_tracks_follow_a_step_larger_than_the_highpass(far_step, highpass_px: float) -> None:
    """The pyramid's coarse levels read the views as they are, the fine ones the
    high-passed views: over a step of about four times the high-pass sigma (two frames'
    travel, followed in one flow) the tracks kept are where the wall really went
    (high-passed views alone kept 5 %, every one of them about 44 px off; full-size
    other-rig lost its resection that way, 28 px a frame)."""
    renderer, pose_a, pose_b, extractor, views_a, views_b = far_step
    key = extractor.detect(views_a)
    config = TrackConfig(highpass_px=highpass_px)
    tracks = track_features(extractor, views_a, key, views_b, config)
    # The true view pixel in b of each tracked feature: its ray from a onto the true wall.
    hits = renderer.hit(pose_a, key.rays_in_rig[tracks.feature]).points_in_world
    in_b = (hits - pose_b[:3, 3]) @ pose_b[:3, :3]
    err = np.empty(len(in_b))
    for k in np.unique(tracks.features.view):
        sel = tracks.features.view == k
        true_px, _ = extractor.views[k].pixels_of_rays(in_b[sel] / np.linalg.norm(in_b[sel], axis=1, keepdims=True))
        err[sel] = np.linalg.norm(true_px - tracks.features.view_pixels[sel], axis=1)
    moved = []
    for k in np.unique(key.view):
        sel = np.flatnonzero(key.view == k)
        pts = renderer.hit(pose_a, key.rays_in_rig[sel]).points_in_world
        q = (pts - pose_b[:3, 3]) @ pose_b[:3, :3]
        px, _ = extractor.views[k].pixels_of_rays(q / np.linalg.norm(q, axis=1, keepdims=True))
        moved.append(np.linalg.norm(px - key.view_pixels[sel], axis=1))
    assert np.median(np.concatenate(moved)) > 3.0 * 8.0  # view px: the step is large
    # This far LK loses most tracks (the wall's perspective changes too); the ones kept
    # are right.
    assert len(tracks.feature) >= 0.1 * min(len(key.view), config.max_points)
    assert np.median(err) < 1.0 and np.mean(err > 3.0) < 0.15

def test_views_on_threads_give_the_serial_features_and_tracks(two_frames) -> None:
    extractor, views_a, views_b, _ = two_frames
    out = []
    for threads in (1, 2):
        extractor.threads = threads
        key = extractor.detect(views_a)
        tracks = TrackChain(extractor, views_a, key, TrackConfig()).advance(views_b)
        out.append((key, tracks))
    extractor.threads = 1
    (k1, t1), (k2, t2) = out
    assert len(k1.view) > 100
    for a, b in ((k1.rays_in_rig, k2.rays_in_rig), (k1.descriptors, k2.descriptors), (k1.view, k2.view),
                 (t1.feature, t2.feature), (t1.features.view_pixels, t2.features.view_pixels)):
        assert np.array_equal(a, b)


def test_a_chain_given_the_flow_images_tracks_as_one_that_makes_them(two_frames, monkeypatch) -> None:
    """The flow images a chain made (their second-try coarse levels too) handed to another
    chain (``key_images``, ``advance(views, images)``: the workers' ``track_back``) are
    not made again, and its tracks are the same to the bit."""
    import omnipipe.sfm.tracking as tracking

    extractor, views_a, views_b, _ = two_frames
    key = extractor.detect(views_a)
    config = TrackConfig()
    made = TrackChain(extractor, views_a, key, config).advance(views_b)
    images = [flow_images(v, config.highpass_px, config.levels) for v in (views_a, views_b)]
    for im in images[0] + images[1]:
        assert im.coarse_band is not None  # as a chain whose tracks took a second try holds them
    calls = []
    monkeypatch.setattr(tracking, "flow_images", lambda *a, **k: calls.append(a) or flow_images(*a, **k))
    given = TrackChain(extractor, views_a, key, config, key_images=images[0]).advance(views_b, images[1])
    assert calls == []
    assert len(made.feature) > 100
    assert np.array_equal(made.feature, given.feature)
    assert np.array_equal(made.features.view_pixels, given.features.view_pixels)
    assert np.array_equal(made.features.rays_in_rig, given.features.rays_in_rig)


def _true_view_pixels(renderer, extractor, pose_a, pose_b, rays_a, view):
    """(M, 2) view pixels in frame b of the wall points that rays ``rays_a`` (M, 3) of
    frame a meet, in views ``view`` (M,)."""
    hits = renderer.hit(pose_a, rays_a).points_in_world
    in_b = (hits - pose_b[:3, 3]) @ pose_b[:3, :3]
    out = np.full((len(view), 2), np.nan)
    for k in np.unique(view):
        sel = view == k
        out[sel], _ = extractor.views[k].pixels_of_rays(in_b[sel] / np.linalg.norm(in_b[sel], axis=1, keepdims=True))
    return out


@pytest.mark.slow
def test_tracks_keep_their_tile_when_a_frame_step_exceeds_half_the_period() -> None:
    """random-wide seed 22: mosaic tiles 11.8 mm apart along the pipe, frame steps of
    2.2, 6.1 and 8.4 mm: the last is more than half the period. Each flow starts from
    the track's last step, so the tracks stay on their own tile (started from rest,
    they landed a tile back: that step came out 3.5 mm, backwards)."""
    scenario = make_scenario("random-wide", frames=4, size=(640, 480), seed=22)
    assert scenario.random is not None and scenario.random["family"] == "mosaic"
    renderer, poses, _, _ = build_renderer(scenario)
    steps = np.linalg.norm(np.diff(poses[:, :3, 3], axis=0), axis=1)
    period = scenario.random["axial_period_mm"]
    assert steps[-1] > 0.6 * period  # mm: the last frame step skips more than half a tile
    extractor, key, chain, tracks = _chain_through(scenario, renderer, poses)
    truth = _true_view_pixels(
        renderer, extractor, poses[0], poses[-1], key.rays_in_rig[tracks.feature], tracks.features.view
    )
    err = np.linalg.norm(truth - tracks.features.view_pixels, axis=1)
    assert len(tracks.feature) >= 0.3 * chain.n_followed
    assert np.median(err) < 1.0 and np.mean(err > 3.0) < 0.1


def test_a_keyframe_is_renewed_when_its_tracks_run_out() -> None:
    """The last keyframe step had 511 verified matches; a frame tracked with 80 (random-
    wide seed 17 at 11 mm frame steps, 16 one frame later and the step lost) is running
    out of tracks, one with 400 is not; with ``renew_ratio`` 0, never."""
    from types import SimpleNamespace

    from omnipipe.sfm import SfmConfig
    from omnipipe.sfm.keyframe_tracks import KeyframeTracks
    from omnipipe.sfm.step_records import TrackedStep

    def loop(config: SfmConfig, inliers: int) -> KeyframeTracks:
        out = object.__new__(KeyframeTracks)  # only what the rule reads
        out.ctx = SimpleNamespace(config=config)
        out.step_inliers = inliers
        return out

    def step(n: int) -> TrackedStep:
        return TrackedStep(Tracks(np.arange(n), None), np.zeros((n, 2), int), math.radians(3.0))

    config = SfmConfig()
    assert loop(config, 511).running_out(step(80))
    assert not loop(config, 511).running_out(step(400))
    assert not loop(config, 0).running_out(step(80))  # no keyframe step yet
    off = replace(config, tracking=replace(config.tracking, renew_ratio=0.0))
    assert not loop(off, 511).running_out(step(80))


@pytest.fixture(scope="module")
def dim_concrete():
    """(renderer, poses, extractor, views) of frames 0-2 of random-wide seed 31 at 640x480:
    a dim concrete wall in a 108 mm pipe, frame steps 2.3 and 6.4 mm (the wall's near
    part moves tens of view px a frame)."""
    scenario = make_scenario("random-wide", seed=31, size=(640, 480), frames=3)
    renderer, poses, _, _ = build_renderer(scenario)
    extractor = FeatureExtractor(camera_from_rig(scenario.rig))
    channel = scenario.rig.laser.channel
    views = [
        extractor.frame_views(renderer.expose(renderer.irradiance(poses[f], seed=5 + f)[0], seed=5 + f), channel)
        for f in range(3)
    ]
    return renderer, poses, extractor, views


def _true_view_px_error(renderer, pose_a, pose_b, extractor, rays_a, tracks: Tracks) -> np.ndarray:
    """(M,) view px between each track and where its keyframe ray's wall point is in b."""
    hits = renderer.hit(pose_a, rays_a).points_in_world
    in_b = (hits - pose_b[:3, 3]) @ pose_b[:3, :3]
    err = np.empty(len(in_b))
    for k in np.unique(tracks.features.view):
        sel = tracks.features.view == k
        true_px, _ = extractor.views[k].pixels_of_rays(in_b[sel] / np.linalg.norm(in_b[sel], axis=1, keepdims=True))
        err[sel] = np.linalg.norm(true_px - tracks.features.view_pixels[sel], axis=1)
    return err


def test_lost_tracks_get_a_second_try_on_band_passed_coarse_levels(dim_concrete, monkeypatch) -> None:
    """On a dim fine-grained wall the coarse levels of the views as they are show mostly
    the rig's own light, which moves with it: a 6.4 mm frame step loses most tracks. The
    second try (coarse levels high-passed at COARSE_HIGHPASS_FACTOR x the sigma) keeps
    far more, and they are where the wall really went."""
    import omnipipe.sfm.tracking as tracking

    renderer, poses, extractor, views = dim_concrete
    key = extractor.detect(views[0])
    errors = {}
    for factor in (0.0, tracking.COARSE_HIGHPASS_FACTOR):
        monkeypatch.setattr(tracking, "COARSE_HIGHPASS_FACTOR", factor)
        chain = TrackChain(extractor, views[0], key, TrackConfig())
        chain.advance(views[1])
        tracks = chain.advance(views[2])
        errors[factor] = _true_view_px_error(
            renderer, poses[0], poses[2], extractor, key.rays_in_rig[tracks.feature], tracks
        )
    second = tracking.COARSE_HIGHPASS_FACTOR
    right = {f: int(np.sum(errors[f] <= 3.0)) for f in errors}
    # Measured: 157 tracks, 27 % more than 3 px off, without; 287, 17 % with.
    assert right[second] >= 1.5 * right[0.0]
    assert np.mean(errors[second] > 3.0) <= np.mean(errors[0.0] > 3.0)
    assert np.median(errors[second]) < 1.0


def test_second_try_only_where_a_view_lost_a_share_of_its_tracks(two_frames, dim_concrete, monkeypatch) -> None:
    """A view that lost a few tracks in the first flow keeps the rest without the second
    try; on the dim wall, where the first flow loses most, every view still gets it."""
    import omnipipe.sfm.tracking as tracking

    calls = []
    checked = tracking._checked_flow

    def counted(a, b, q0, v, config, coarse_highpassed=False):
        calls.append((coarse_highpassed, len(q0)))
        return checked(a, b, q0, v, config, coarse_highpassed)

    monkeypatch.setattr(tracking, "_checked_flow", counted)
    extractor, views_a, views_b, _ = two_frames
    key = extractor.detect(views_a)
    tracks, tries = {}, {}
    for share in (0.0, 0.25):
        calls.clear()
        tracks[share] = track_features(extractor, views_a, key, views_b, TrackConfig(retry_lost_share=share))
        tries[share] = [n for second, n in calls if second]
    # Here 12-42 of each view's ~125 tracks are lost: the views that lost fewer than a
    # quarter keep their first flow's tracks, the same as with every view retried.
    assert 0 < len(tries[0.25]) < len(tries[0.0])
    same = np.isin(tracks[0.0].feature, tracks[0.25].feature)
    assert np.all(np.isin(tracks[0.25].feature, tracks[0.0].feature))
    assert np.array_equal(
        tracks[0.0].features.view_pixels[same],
        tracks[0.25].features.view_pixels[np.searchsorted(tracks[0.25].feature, tracks[0.0].feature[same])],
    )
    assert len(tracks[0.25].feature) >= 0.95 * len(tracks[0.0].feature)

    _, _, extractor, views = dim_concrete
    key = extractor.detect(views[0])
    calls.clear()
    TrackChain(extractor, views[0], key, TrackConfig(retry_lost_share=0.1)).advance(views[1])
    firsts = [n for second, n in calls if not second]
    seconds = [n for second, n in calls if second]
    assert len(seconds) == len(firsts)  # every view lost at least a tenth


def test_large_views_take_their_own_share_for_the_second_try(two_frames) -> None:
    """Views whose shorter side reaches ``retry_large_side_px`` follow
    ``retry_lost_share_large``, smaller ones ``retry_lost_share``: the 640x480 views here
    (131 px) are small by default (every view retried, as with the share 0), large at a
    100 px bound (as with the share itself)."""
    from omnipipe.sfm.tracking import _retry_share

    default = TrackConfig()
    assert _retry_share((335, 484), default) == default.retry_lost_share_large == 0.1
    assert _retry_share((285, 398), default) == default.retry_lost_share == 0.0
    assert _retry_share((335, 484), replace(default, retry_large_side_px=0)) == 0.0
    extractor, views_a, views_b, _ = two_frames
    assert min(views_a.images[0].shape) < default.retry_large_side_px
    key = extractor.detect(views_a)

    def tracks(config: TrackConfig) -> Tracks:
        return track_features(extractor, views_a, key, views_b, config)

    for got, want in (
        (tracks(default), tracks(TrackConfig(retry_lost_share=0.0, retry_large_side_px=0))),
        (
            tracks(TrackConfig(retry_large_side_px=100, retry_lost_share_large=0.25)),
            tracks(TrackConfig(retry_lost_share=0.25, retry_large_side_px=0)),
        ),
    ):
        assert np.array_equal(got.feature, want.feature)
        assert np.array_equal(got.features.view_pixels, want.features.view_pixels)


def test_large_views_follow_their_own_number_of_points() -> None:
    """A run's tracking config takes ``max_points_large`` in views whose shorter side
    reaches ``retry_large_side_px`` (1600x1200's 335x484) and keeps ``max_points`` in
    smaller ones (other-rig's 285x398, 640x480's 131x189) or with the bound at 0; the
    run's views' size is the extractor's."""
    from omnipipe.sfm.features import FeatureConfig, view_size
    from omnipipe.sfm.tracking import sized_for_views

    default = TrackConfig()
    assert (default.max_points, default.max_points_large) == (1000, 600)
    assert sized_for_views(default, (484, 335)) == replace(default, max_points=600, back_below=200)
    assert sized_for_views(default, (398, 285)) == default
    assert sized_for_views(default, (189, 131)) == default
    assert sized_for_views(replace(default, retry_large_side_px=0), (484, 335)).max_points == 1000
    rig = make_scenario("paper", frames=2, size=(640, 480)).rig
    camera = camera_from_rig(rig)
    extractor = FeatureExtractor(camera)
    assert view_size(camera, FeatureConfig()) == (extractor.views[0].height, extractor.views[0].width)


def test_large_views_take_their_own_keyframe_parallax_and_follow_back() -> None:
    """A run's keyframe parallax and ``back_below`` are ``keyframe_min_parallax_large_deg``
    and ``back_below_large`` where its views are large (1600x1200's) and the plain
    settings in smaller ones (640x480's) or with the bound at 0; the CLI's
    ``--keyframe-parallax`` sets both parallaxes."""
    from types import SimpleNamespace

    from omnipipe.pipeline.cli import _overrides
    from omnipipe.sfm.pipeline import _sized_views
    from omnipipe.sfm.types import SfmConfig

    assert TrackConfig().back_below_large == 200
    config = SfmConfig(keyframe_min_parallax_large_deg=6.0)
    large = SimpleNamespace(rig=make_scenario("paper", frames=2, size=(1600, 1200)).rig)
    small = SimpleNamespace(rig=make_scenario("paper", frames=2, size=(640, 480)).rig)
    sized = _sized_views(config, large)
    assert sized.keyframe_min_parallax_deg == 6.0
    assert (sized.tracking.max_points, sized.tracking.back_below) == (600, 200)
    assert _sized_views(config, small) == config
    off = replace(config, tracking=replace(config.tracking, retry_large_side_px=0))
    assert _sized_views(off, large) == off
    args = SimpleNamespace(features=None, keyframe_parallax=3.0, mesher=None)
    assert _overrides(args)["sfm"] == {"keyframe_min_parallax_deg": 3.0, "keyframe_min_parallax_large_deg": 3.0}


def test_followed_back_only_down_to_the_earliest_frame_short_of_tracks_or_far() -> None:
    """The new keyframe's features are followed back (latest pending frame first) only
    as far as the earliest pending frame with fewer than ``back_below`` verified tracks
    of its own keyframe, or whose rays turned ``back_beyond`` of the step's parallax or
    more (or an unknown share); none when every frame has enough tracks and is near its
    own keyframe."""
    from omnipipe.sfm.keyframe_jobs import followed_back

    near = [0.1, 0.2, 0.3, 0.4]
    by_count = TrackConfig(back_below=200, back_beyond=1.0)
    assert followed_back([800, 650, 420, 150], near, by_count) == [3]
    assert followed_back([800, 120, 420, 600], near, by_count) == [3, 2, 1]
    assert followed_back([800, 650], near[:2], by_count) == []
    assert followed_back([], [], by_count) == []
    always = TrackConfig(back_below=1_000_000, back_beyond=1.0)
    assert followed_back([800, 650, 20], near[:3], always) == [2, 1, 0]
    assert followed_back([800, 650], near[:2], TrackConfig(back_below=0, back_beyond=1.0)) == []
    by_share = TrackConfig(back_below=200, back_beyond=0.5)
    assert followed_back([800, 650, 420, 600], [0.2, 0.45, 0.55, 0.8], by_share) == [3, 2]
    assert followed_back([800, 650, 420], [0.2, 0.3, 0.4], by_share) == []
    assert followed_back([800, 150, 420], [0.2, 0.3, 0.4], by_share) == [2, 1]
    assert followed_back([800, 650, 420], [float("nan"), 0.3, 0.4], by_share) == [2, 1, 0]
    assert followed_back([800, 650], [0.1, 0.2], TrackConfig(back_below=0, back_beyond=0.0)) == [1, 0]


def test_spread_order_takes_one_feature_per_square_before_a_second() -> None:
    rng = np.random.default_rng(4)
    # 300 features crowded into one corner of view 0, 30 spread over view 1 and 10 over view 2.
    view = np.concatenate([np.zeros(300, int), np.ones(30, int), np.full(10, 2)])
    px = np.concatenate([rng.uniform(0, 30, (300, 2)), rng.uniform(0, 320, (30, 2)), rng.uniform(0, 320, (10, 2))])
    order = spread_order(view, px.astype(np.float32), 32.0)
    assert np.array_equal(np.sort(order), np.arange(len(view)))
    squares = {(int(v), int(x // 32), int(y // 32)) for v, (x, y) in zip(view, px, strict=True)}
    first = order[: len(squares)]
    # The first picks cover every occupied square once, in list order within a rank.
    assert {(int(view[i]), int(px[i, 0] // 32), int(px[i, 1] // 32)) for i in first} == squares
    assert np.all(np.diff(first) > 0)
    # Evenly over the list, a budget of 40 would take 35 of view 0's crowded corner.
    assert np.sum(view[order[:40]] == 0) <= 1 + 40 - len(squares)


def test_the_budget_keeps_the_carried_tracks_then_spreads_the_new_features() -> None:
    from omnipipe.sfm.keyframe_jobs import budget

    rng = np.random.default_rng(5)
    n = 500
    view = rng.integers(0, 4, n)
    px = rng.uniform(0, 200, (n, 2)).astype(np.float32)
    features = FrameFeatures(np.zeros((n, 3)), np.zeros((n, 2)), np.zeros((n, 128), np.float32), view, px)
    even = budget(120, features, TrackConfig(max_points=200))
    assert np.array_equal(even[:120], np.arange(120))
    assert np.array_equal(even[120:], np.unique(np.linspace(120, n - 1, 80).round().astype(int)))
    spread = budget(120, features, TrackConfig(max_points=200, spread_px=50.0))
    assert np.array_equal(spread[:120], np.arange(120))
    assert len(spread) == 200 and np.all(spread[120:] >= 120) and np.all(np.diff(spread[120:]) > 0)
    # The new ones cover as many squares as 80 picks can (64 squares of 50 px in 4 views).
    squares = {(int(view[i]), int(px[i, 0] // 50), int(px[i, 1] // 50)) for i in spread[120:]}
    assert len(squares) == 64
    assert np.array_equal(budget(300, features, TrackConfig(max_points=200)), np.unique(np.linspace(0, 299, 200).round().astype(int)))


def test_lucas_kanade_without_the_error_pass_is_opencvs_with_it() -> None:
    """``_lk`` asks OpenCV for the windows' eigenvalues instead of their error (one pass
    less) and redoes the error pass's bound check: positions and status as OpenCV's
    plain call to the bit, also for tracks that end a window or more outside the image."""
    import cv2

    rng = np.random.default_rng(5)
    config = TrackConfig()
    win = (config.window_px, config.window_px)
    criteria = (cv2.TERM_CRITERIA_EPS | cv2.TERM_CRITERIA_COUNT, 30, 0.01)
    outside = 0
    for _ in range(40):
        h, w = (int(v) for v in rng.integers(40, 200, 2))
        a = cv2.GaussianBlur(rng.integers(0, 255, (h, w), dtype=np.uint8), (0, 0), float(rng.uniform(0.8, 4)))
        shift = np.float32([[1, 0, rng.uniform(-25, 25)], [0, 1, rng.uniform(-25, 25)]])
        b = cv2.warpAffine(a, shift, (w, h), borderMode=cv2.BORDER_REFLECT)
        q0 = np.column_stack([rng.uniform(-5, w + 5, 200), rng.uniform(-5, h + 5, 200)]).astype(np.float32).reshape(-1, 1, 2)
        start = None if rng.integers(0, 2) else q0 + rng.uniform(-40, 40, q0.shape).astype(np.float32)
        levels = int(rng.integers(0, 4))
        flags = 0 if start is None else cv2.OPTFLOW_USE_INITIAL_FLOW
        ref, st, _ = cv2.calcOpticalFlowPyrLK(
            a, b, q0, None if start is None else start.copy(), winSize=win, maxLevel=levels, criteria=criteria, flags=flags
        )
        p1, ok = _lk(a, b, q0, start, levels, config)
        assert np.array_equal(p1, ref) and np.array_equal(ok, st.ravel() == 1)
        _, st_eig, _ = cv2.calcOpticalFlowPyrLK(
            a, b, q0, None if start is None else start.copy(), winSize=win, maxLevel=levels, criteria=criteria,
            flags=flags | cv2.OPTFLOW_LK_GET_MIN_EIGENVALS,
        )
        outside += int(np.sum((st_eig.ravel() == 1) & (st.ravel() == 0)))
    assert outside > 0  # OpenCV's flag alone keeps tracks the error pass fails: the check is needed
