"""The second scale source and the step decision (omnipipe.sfm.scale_check), no rendering."""

from __future__ import annotations

import math

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from omnipipe.geometry import make_transform
from omnipipe.sfm.laser_scale import consensus_peaks
from omnipipe.sfm.scale_check import (
    FEATURE_ONLY,
    MIN_BEND_TURN_RAD,
    WALL_SCALE_SIGMA_FLOOR,
    ScaleCheckConfig,
    StepCheck,
    UnreliableStretch,
    bent_wall,
    decide,
    feature_log_scales,
    feature_scale,
    merge_stretches,
    steady_turn,
    steps_checked,
    wall_cylinder,
    wall_depth,
    wall_scale_correction,
)

CFG = ScaleCheckConfig()


def _wall_points(rng: np.random.Generator, n: int, centre, radius: float, z: tuple[float, float]):
    phi = rng.uniform(0, 2 * np.pi, n)
    zz = rng.uniform(*z, n)
    return np.column_stack([centre[0] + radius * np.cos(phi), centre[1] + radius * np.sin(phi), zz])


def test_wall_cylinder_recovers_the_ring_circle() -> None:
    rng = np.random.default_rng(0)
    ring = _wall_points(rng, 400, (1.5, -2.0), 101.0, (-82.0, -82.0))
    ring[:, :2] += rng.normal(0, 0.1, (400, 2))
    wall = wall_cylinder(ring)
    assert wall is not None
    assert np.allclose(wall.centre_xy, [1.5, -2.0], atol=0.05)
    assert wall.radius_mm == pytest.approx(101.0, abs=0.05)
    assert wall_cylinder(ring[:5]) is None


def test_wall_depth_round_trip() -> None:
    rng = np.random.default_rng(1)
    pts = _wall_points(rng, 200, (2.0, 1.0), 80.0, (-150.0, 150.0))
    depth = np.linalg.norm(pts, axis=1)
    rays = pts / depth[:, None]
    wall = wall_cylinder(_wall_points(rng, 100, (2.0, 1.0), 80.0, (-82.0, -82.0)))
    assert np.allclose(wall_depth(rays, wall), depth, rtol=1e-6)


@pytest.mark.parametrize("length_mm", [2.0, 11.0, 37.0])
def test_feature_scale_is_the_true_step(length_mm: float) -> None:
    """Matched rays of points on the wall give the step length without any laser match."""
    rng = np.random.default_rng(int(length_mm))
    centre, radius = (1.0, -0.5), 100.0
    pts_a = _wall_points(rng, 150, centre, radius, (-200.0, 200.0))
    R = Rotation.from_rotvec(rng.normal(0, 0.01, 3)).as_matrix()
    direction = np.array([0.05, -0.02, -1.0])
    direction /= np.linalg.norm(direction)
    b_from_a = make_transform(R, length_mm * direction)
    pts_b = pts_a @ R.T + length_mm * direction
    rays_a = pts_a / np.linalg.norm(pts_a, axis=1)[:, None]
    rays_b = pts_b / np.linalg.norm(pts_b, axis=1)[:, None]
    rays_b += rng.normal(0, 2e-4, rays_b.shape)  # about 0.2 px of noise
    rays_b /= np.linalg.norm(rays_b, axis=1)[:, None]
    ring = _wall_points(rng, 300, centre, radius, (-82.0, -82.0))
    ls = feature_log_scales(rays_a, rays_b, b_from_a[:3, :3], direction, wall_cylinder(ring), CFG)
    s, n = feature_scale(ls, CFG)
    assert n >= CFG.min_feature_matches
    assert s == pytest.approx(length_mm, rel=0.03)
    # A match to the wrong course (shifted along the pipe) implies another length.
    shifted = pts_a + np.array([0.0, 0.0, -14.0])
    wrong_b = shifted @ R.T + length_mm * direction
    wrong_b /= np.linalg.norm(wrong_b, axis=1)[:, None]
    ls_wrong = feature_log_scales(rays_a, wrong_b, b_from_a[:3, :3], direction, wall_cylinder(ring), CFG)
    assert np.nanmedian(np.abs(ls_wrong - math.log(length_mm))) > CFG.keep_match_log


def test_consensus_peaks_finds_every_course() -> None:
    scales = np.geomspace(0.2, 200.0, 96)
    rng = np.random.default_rng(2)

    def bump(centre: float, height: float) -> np.ndarray:
        return height * np.exp(-0.5 * (np.log(scales / centre) / 0.08) ** 2)

    ncc = np.stack([bump(4.4, 0.9) + bump(18.4, 0.85) + rng.normal(0, 0.02, 96) for _ in range(40)])
    peaks, scores = consensus_peaks(scales, ncc)
    assert len(peaks) >= 2
    for true in (4.4, 18.4):  # within the 7.5 % candidate spacing
        assert np.min(np.abs(np.log(peaks[:2] / true))) < 0.075
    assert scores[1] / scores[0] > 0.8


def test_decide_agreeing_sources_are_trusted() -> None:
    c = decide(3, 9, 4.4, np.array([4.4, 18.4]), np.array([0.8, 0.3]), 4.5, 40, CFG)
    assert c.confidence == "high" and c.reliable and c.scale_mm == 4.4


def test_decide_wrong_best_peak_is_resolved_by_the_features() -> None:
    """The field failure: the wrong brick course scores best (4x too long)."""
    c = decide(3, 9, 18.4, np.array([18.4, 4.4]), np.array([0.9, 0.85]), 4.5, 40, CFG)
    assert c.confidence == "resolved" and c.reliable
    assert c.scale_mm == pytest.approx(4.4)


def test_decide_disagreement_without_an_alternative_is_flagged() -> None:
    c = decide(3, 9, 18.4, np.array([18.4]), np.array([0.9]), 4.5, 40, CFG)
    assert c.confidence == "none" and not c.reliable and math.isnan(c.scale_mm)
    assert "disagree" in c.reason


def test_decide_best_peak_left_by_the_points_median_is_resolved() -> None:
    """Corrugation: best peak 19.5 mm, the points' median 30.8 mm, features 18.3 mm."""
    c = decide(3, 9, 30.8, np.array([19.5, 43.4]), np.array([0.47, 0.41]), 18.3, 108, CFG)
    assert c.confidence == "resolved" and c.scale_mm == pytest.approx(19.5)


def test_decide_ambiguous_laser_leaves_the_features_alone_but_unreliable() -> None:
    """Tiles: every course scores alike; many agreeing feature depths give the length,
    flagged until the gait confirms it (step_window); too few matches do not."""
    peaks, scores = np.array([10.2, 6.6, 32.5]), np.array([0.94, 0.94, 0.93])
    c = decide(3, 9, 21.6, peaks, scores, 16.6, 37, CFG)
    assert c.confidence == "low" and not c.reliable and c.reason.startswith(FEATURE_ONLY)
    assert c.scale_mm == pytest.approx(16.6)
    c = decide(3, 9, 21.6, peaks, scores, 16.6, 12, CFG)
    assert c.confidence == "none" and math.isnan(c.scale_mm)
    c = decide(3, 9, 21.6, np.array([21.6, 10.2]), np.array([0.9, 0.3]), 16.6, 37, CFG)
    assert c.confidence == "none"  # an unambiguous laser contradicting the features


def test_decide_ambiguous_laser_without_features_is_flagged() -> None:
    c = decide(3, 9, 18.4, np.array([18.4, 4.4]), np.array([0.9, 0.85]), math.nan, 3, CFG)
    assert not c.reliable and "ambiguous" in c.reason
    c = decide(3, 9, 4.4, np.array([4.4, 18.4]), np.array([0.9, 0.2]), math.nan, 3, CFG)
    assert c.confidence == "low" and not c.reliable  # one unconfirmed source is flagged


def test_stretches_merge_and_steps_checked() -> None:
    merged = merge_stretches(
        [UnreliableStretch(9, 12, "b"), UnreliableStretch(3, 9, "a"), UnreliableStretch(20, 21, "a")]
    )
    assert [(m.first_frame, m.last_frame, m.reason) for m in merged] == [(3, 12, "a; b"), (20, 21, "a")]
    checks = [
        decide(0, 2, 4.4, np.array([4.4]), np.array([0.9]), 4.4, 30, CFG),
        decide(2, 5, 18.0, np.array([18.0]), np.array([0.9]), 4.4, 30, CFG),
    ]
    stationary = np.array([False, False, False, False, False, False, True, True])
    assert steps_checked(checks, stationary) == 2 + 2  # frames 0->2 and two standstills


def _reliable(k: int) -> StepCheck:
    return StepCheck(k, k + 1, 4.0, 0.0, 4.0, 50, 4.0, "high")


@pytest.mark.parametrize("wrong_scale", [0.97, 1.0, 1.05])
def test_wall_scale_correction_recovers_the_true_scale(wrong_scale: float) -> None:
    """Keyframes in a 200 mm pipe whose adjusted run is `wrong_scale` too long: the wall
    seen by the matched features gives the factor back, and a sigma that covers it."""
    rng = np.random.default_rng(7)
    centre, radius = np.array([1.5, -1.0]), 100.0
    n_kf = 8
    world_from_kf = np.stack([
        make_transform(Rotation.from_rotvec(rng.normal(0, 0.01, 3)).as_matrix(), [0.3 * k, 0.0, 6.0 * k])
        for k in range(n_kf)
    ])
    wall_world = _wall_points(rng, 3000, centre, radius, (-250.0, 300.0))
    rays, rings, matches = [], [], []
    for k in range(n_kf):
        kf_from_world = np.linalg.inv(world_from_kf[k])
        p = wall_world @ kf_from_world[:3, :3].T + kf_from_world[:3, 3]
        r = p / np.linalg.norm(p, axis=1)[:, None]
        r += rng.normal(0, 2e-4, r.shape)  # about 0.2 px
        rays.append(r / np.linalg.norm(r, axis=1)[:, None])
        phi = rng.uniform(0, 2 * np.pi, 300)  # its laser ring on the wall, 82 mm ahead
        ring_w = np.column_stack([centre[0] + radius * np.cos(phi), centre[1] + radius * np.sin(phi),
                                  np.full(300, 6.0 * k - 82.0)])
        rings.append(ring_w @ kf_from_world[:3, :3].T + kf_from_world[:3, 3])
    idx = np.arange(len(wall_world))
    for k in range(n_kf - 1):
        matches.append((k, k + 1, np.column_stack([idx, idx])[::10]))
    wrong = world_from_kf.copy()
    wrong[:, :3, 3] *= wrong_scale
    got = wall_scale_correction(wrong, matches, rays, rings, [_reliable(k) for k in range(n_kf - 1)], CFG)
    assert got is not None
    log_gain, sigma = got
    assert abs(log_gain + math.log(wrong_scale)) < 0.003  # 0.3 %
    assert abs(log_gain + math.log(wrong_scale)) < 3 * math.hypot(sigma, WALL_SCALE_SIGMA_FLOOR)
    # Unreliable steps do not count: too few left, no correction.
    few = [_reliable(k) if k < 2 else StepCheck(k, k + 1, 4.0, 0, 9.0, 50, 4.0, "low") for k in range(n_kf - 1)]
    assert wall_scale_correction(wrong, matches, rays, rings, few, CFG) is None


def test_bent_wall_corrects_the_straight_cylinder_in_an_elbow() -> None:
    """A 200 mm pipe bent at R 300 mm, the rig on its axis at the bend's start, its ring
    78 mm ahead: the straight cylinder through the ring puts the wall by the rig ~10 mm
    off; the wall bent by a step's turn per length is within 0.3 mm."""
    rng = np.random.default_rng(11)
    bend_r, radius = 300.0, 100.0
    theta = rng.uniform(-0.1, 0.4, 20000)
    phi = rng.uniform(0, 2 * np.pi, len(theta))
    out = np.column_stack([-np.cos(theta), np.zeros_like(theta), np.sin(theta)])
    axis = bend_r * np.column_stack([1 - np.cos(theta), np.zeros_like(theta), np.sin(theta)])
    tube = axis + radius * (np.cos(phi)[:, None] * out + np.sin(phi)[:, None] * [0.0, 1.0, 0.0])
    ring = tube[np.abs(tube[:, 2] - 78.0) < 0.3]
    near = tube[np.abs(tube[:, 2]) < 15.0][:500]
    rays, depth = near / np.linalg.norm(near, axis=1)[:, None], np.linalg.norm(near, axis=1)
    straight = wall_cylinder(ring)
    assert straight is not None
    assert np.nanmax(np.abs(wall_depth(rays, straight) - depth)) > 8.0
    # A 12 mm step along the axis: the rig turns 12 / 300 rad about its y axis.
    step = 12.0 / bend_r
    a_from_b = make_transform(Rotation.from_rotvec([0.0, step, 0.0]).as_matrix(),
                              bend_r * np.array([1 - np.cos(step), 0.0, np.sin(step)]))
    b_from_a = np.linalg.inv(a_from_b)
    bent = bent_wall(straight, b_from_a[:3, :3], b_from_a[:3, 3], 12.0)
    assert bent is not None and bent.curvature_xy is not None
    assert np.allclose(bent.curvature_xy, [1 / bend_r, 0.0], atol=1e-5)
    err = np.abs(wall_depth(rays, bent) - depth)
    assert np.isfinite(err).all() and err.max() < 0.3
    # A turn below MIN_BEND_TURN_RAD (straight pipe noise) leaves the wall straight.
    tiny = Rotation.from_rotvec([0.0, 0.5 * MIN_BEND_TURN_RAD, 0.0]).as_matrix()
    assert bent_wall(straight, tiny.T, b_from_a[:3, 3], 12.0).curvature_xy is None


def test_steady_turn_tells_a_bend_from_tilt_noise() -> None:
    """Keyframes 12 mm apart along an R 300 mm arc turn one way; a straight run whose
    rig tilts 0.6 deg at random does not."""
    rng = np.random.default_rng(5)
    arc = np.stack([
        make_transform(Rotation.from_rotvec([0.0, 12.0 * k / 300.0, 0.0]).as_matrix(),
                       300.0 * np.array([1 - np.cos(12.0 * k / 300.0), 0.0, np.sin(12.0 * k / 300.0)]))
        for k in range(8)
    ])
    noisy = np.stack([
        make_transform(Rotation.from_rotvec(rng.normal(0, 0.01, 3)).as_matrix(), [0.0, 0.0, 12.0 * k])
        for k in range(8)
    ])
    assert steady_turn(arc)
    assert not steady_turn(noisy)
