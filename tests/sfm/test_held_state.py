"""What the camera motion keeps per frame and per keyframe goes to the run's scratch with
the same values: the wall cylinders :func:`omnipipe.sfm.pipeline.nearest_wall` caches, a
finished step's evidence and a pending frame's correspondences
(:mod:`omnipipe.sfm.keyframe_jobs`)."""

from __future__ import annotations

import math
from concurrent.futures import Future

import numpy as np

from omnipipe.laser.ring import LaserRing
from omnipipe.sfm.flat_field import _Later
from omnipipe.sfm.keyframe_jobs import evidence_held, finished, rays_held
from omnipipe.sfm.laser_scale import LaserMatches
from omnipipe.sfm.pipeline import nearest_wall
from omnipipe.sfm.scale_check import wall_cylinder
from omnipipe.sfm.types import KeyframeRays, StepEvidence
from omnipipe.spill import Pack, is_on_disk


def _ring(rng: np.random.Generator, n: int, centre: tuple[float, float], radius: float) -> LaserRing:
    t = rng.uniform(0, 2 * math.pi, n)
    pts = np.column_stack(
        [centre[0] + radius * np.cos(t), centre[1] + radius * np.sin(t), rng.normal(80.0, 0.1, n)]
    ) + rng.normal(0, 0.05, (n, 3))
    return LaserRing(rng.uniform(0, 400, (n, 2)), t, np.ones(n), np.ones(n), points_in_rig=pts)


def test_nearest_wall_caches_each_cylinder_with_its_points_on_disk() -> None:
    rng = np.random.default_rng(3)
    rings = [_ring(rng, 200, (rng.normal(), rng.normal()), 50.0 + i) for i in range(6)]
    rings[2] = _ring(rng, 5, (0.0, 0.0), 50.0)  # too few points: the nearest frame's wall
    read = nearest_wall(rings)
    for i in range(6):
        got = read(i)
        want = wall_cylinder(rings[1 if i == 2 else i].points_in_rig)
        assert got is not None and want is not None
        np.testing.assert_array_equal(got.centre_xy, want.centre_xy)
        assert got.radius_mm == want.radius_mm and got.ring_z_mm == want.ring_z_mm
        np.testing.assert_array_equal(got.ring_points, want.ring_points)
        assert is_on_disk(got.ring_points)
        assert read(i) is got  # cached


def test_finished_evidence_and_rays_held_with_their_values() -> None:
    rng = np.random.default_rng(5)
    m, L = 57, 31
    laser = LaserMatches(
        rng.integers(0, 500, L), rng.normal(10, 1, L), rng.uniform(0, 400, (L, 2)), rng.uniform(0, 1, L), 10.2
    )
    ev = StepEvidence(3, 7, np.eye(4), rng.integers(0, 300, (m, 2)), laser, rng.normal(2.3, 0.1, m), 9.8, m, "ok")
    held = evidence_held(Pack(), ev)
    for got, want in (
        (held.inliers, ev.inliers), (held.log_scales, ev.log_scales), (held.laser.index, laser.index),
        (held.laser.scale_mm, laser.scale_mm), (held.laser.pixels_b, laser.pixels_b), (held.laser.ncc, laser.ncc),
    ):
        np.testing.assert_array_equal(got, want)
        assert got.dtype == want.dtype and is_on_disk(got)
    assert (held.a, held.b, held.feature_scale_mm, held.status) == (3, 7, 9.8, "ok")
    rays = KeyframeRays(rng.integers(0, 300, m), rng.normal(size=(m, 3)))
    kept = rays_held(Pack(), rays)
    np.testing.assert_array_equal(kept.feature, rays.feature)
    np.testing.assert_array_equal(kept.rays_in_rig, rays.rays_in_rig)
    assert is_on_disk(kept.feature) and is_on_disk(kept.rays_in_rig)


def test_only_futures_holding_a_result_count_as_finished() -> None:
    waiting, done, failed, cancelled = Future(), Future(), Future(), Future()
    done.set_result(1)
    failed.set_exception(ValueError("worker"))
    cancelled.cancel()
    later, released = _Later(), _Later()
    released.future = done
    assert [finished(f) for f in (waiting, done, failed, cancelled, later, released)] == [
        False, True, False, False, False, True,
    ]


def test_scaled_tracks_on_disk_with_the_whole_products() -> None:
    from omnipipe.sfm.adjust import Adjusted, WindowTracks

    rng = np.random.default_rng(11)
    tracks = [WindowTracks(0, [rng.integers(-1, 50, 40)], rng.normal(size=(50, 3)) * 100), None]
    adj = Adjusted(rng.normal(size=(3, 4, 4)), tracks, np.zeros(3, int), [])
    got = adj.scaled(1.0137)
    np.testing.assert_array_equal(got.tracks[0].points_in_world, tracks[0].points_in_world * 1.0137)
    assert is_on_disk(got.tracks[0].points_in_world) and got.tracks[1] is None
    want = adj.world_from_kf.copy()
    want[:, :3, 3] *= 1.0137
    np.testing.assert_array_equal(got.world_from_kf, want)


def test_chain_held_on_disk_with_its_values() -> None:
    from omnipipe.sfm.pipeline import _chain_held
    from omnipipe.sfm.step_chain import ChainedSteps
    from omnipipe.sfm.types import Anchor, PairMatches

    rng = np.random.default_rng(13)
    pairs = [PairMatches(k, k + 1, rng.integers(0, 300, (40 + k, 2))) for k in range(3)]
    anchors = [
        Anchor(0, 1, rng.normal(size=(20, 3)), rng.uniform(0, 400, (20, 2)), rng.normal(2, 0.1, 20), True),
        Anchor(1, 2, rng.normal(size=(9, 3)), rng.uniform(0, 400, (9, 2))),
    ]
    chain = ChainedSteps(rng.normal(size=(4, 4, 4)), [1.0, 2.0, 3.0], pairs, anchors, [])
    held = _chain_held(chain)
    for p, q in zip(held.pair_matches, pairs, strict=True):
        assert (p.a, p.b) == (q.a, q.b) and is_on_disk(p.matches)
        np.testing.assert_array_equal(p.matches, q.matches)
    for p, q in zip(held.anchors, anchors, strict=True):
        assert (p.a, p.b, p.epipolar) == (q.a, q.b, q.epipolar) and is_on_disk(p.points_in_a)
        for x, y in ((p.points_in_a, q.points_in_a), (p.pixels_b, q.pixels_b), (p.log_lengths, q.log_lengths)):
            np.testing.assert_array_equal(x, y)
            assert x.dtype == y.dtype
    assert held.world_from_kf is chain.world_from_kf and held.scales_mm == chain.scales_mm
