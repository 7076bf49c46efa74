"""Eight-point on ray vectors, decomposition, triangulation and RANSAC (Eq. 10-16)."""

from __future__ import annotations

import math

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from omnipipe.errors import ReconstructionError
from omnipipe.geometry import apply, make_transform, rotation_angle
from omnipipe.sfm.geometry import (
    decompose_essential,
    eight_point,
    epipolar_angle,
    triangulate_pairs,
)
from omnipipe.sfm.ransac import RansacConfig, estimate_relative_motion


def _scene(rng: np.random.Generator, n: int, translation: np.ndarray, rot_deg: float = 5.0):
    """Points all around the rig (both hemispheres), a motion, and the rays of both views."""
    dirs = rng.normal(size=(n, 3))
    dirs /= np.linalg.norm(dirs, axis=1, keepdims=True)
    pts1 = dirs * rng.uniform(60.0, 300.0, (n, 1))
    R = Rotation.from_rotvec(rng.normal(size=3) * math.radians(rot_deg) / math.sqrt(3)).as_matrix()
    T = make_transform(R, translation)
    pts2 = apply(T, pts1)
    r1 = pts1 / np.linalg.norm(pts1, axis=1, keepdims=True)
    r2 = pts2 / np.linalg.norm(pts2, axis=1, keepdims=True)
    return r1, r2, T, pts1


def _noisy(rays: np.ndarray, rng: np.random.Generator, sigma_rad: float) -> np.ndarray:
    out = rays + rng.normal(0, sigma_rad, rays.shape)
    return out / np.linalg.norm(out, axis=1, keepdims=True)


@pytest.mark.parametrize("seed", range(5))
def test_exact_rays_recover_the_motion(seed: int) -> None:
    rng = np.random.default_rng(seed)
    t = rng.normal(size=3) * 10.0
    r1, r2, T, pts1 = _scene(rng, 50, t)
    E = eight_point(r1, r2)
    assert np.abs(np.einsum("ij,jk,ik->i", r2, E, r1)).max() < 1e-10  # Eq. (10)
    est, n_front = decompose_essential(E, r1, r2)
    assert n_front == 50
    assert rotation_angle(est[:3, :3].T @ T[:3, :3]) < 1e-8
    assert np.allclose(est[:3, 3], t / np.linalg.norm(t), atol=1e-8)
    scaled = est.copy()
    scaled[:3, 3] *= np.linalg.norm(t)
    pts, depth = triangulate_pairs(r1, r2, scaled)
    assert np.all(depth > 0) and np.abs(pts - pts1).max() < 1e-6


def test_noisy_rays_within_bands() -> None:
    rng = np.random.default_rng(10)
    t = np.array([0.5, -0.3, 20.0])  # mostly along the pipe, as the robot moves
    r1, r2, T, _ = _scene(rng, 400, t)
    sigma = math.radians(0.03)  # about 0.5 px
    est, _ = decompose_essential(
        eight_point(_noisy(r1, rng, sigma), _noisy(r2, rng, sigma)), r1, r2
    )
    assert math.degrees(rotation_angle(est[:3, :3].T @ T[:3, :3])) < 0.05
    assert math.degrees(math.acos(est[:3, 3] @ t / np.linalg.norm(t))) < 0.5


def test_ransac_with_outliers() -> None:
    rng = np.random.default_rng(3)
    t = np.array([1.0, 2.0, 15.0])
    r1, r2, T, _ = _scene(rng, 500, t)
    sigma = math.radians(0.02)
    r1n, r2n = _noisy(r1, rng, sigma), _noisy(r2, rng, sigma)
    bad = rng.random(500) < 0.4
    r2n[bad] = _noisy(rng.normal(size=(bad.sum(), 3)), rng, 0.0)
    res = estimate_relative_motion(r1n, r2n, RansacConfig(threshold_rad=math.radians(0.1), seed=1))
    assert res.translation_reliable
    assert np.mean(res.inliers[~bad]) > 0.95 and np.mean(res.inliers[bad]) < 0.02
    assert math.degrees(rotation_angle(res.rig2_from_rig1[:3, :3].T @ T[:3, :3])) < 0.05
    assert math.degrees(math.acos(res.rig2_from_rig1[:3, 3] @ t / np.linalg.norm(t))) < 0.5
    assert epipolar_angle(res.essential, r1n[~bad], r2n[~bad]).max() < math.radians(0.2)


@pytest.mark.parametrize("translation", [np.zeros(3), np.array([0.0, 0.0, 1e-4])])
def test_standstill_and_pure_rotation_are_flagged(translation: np.ndarray) -> None:
    rng = np.random.default_rng(4)
    r1, r2, T, _ = _scene(rng, 300, translation, rot_deg=2.0)
    sigma = math.radians(0.02)
    res = estimate_relative_motion(
        _noisy(r1, rng, sigma), _noisy(r2, rng, sigma), RansacConfig(seed=2)
    )
    assert not res.translation_reliable
    assert np.all(np.isfinite(res.rig2_from_rig1)) and np.allclose(res.rig2_from_rig1[:3, 3], 0.0)
    assert math.degrees(rotation_angle(res.rig2_from_rig1[:3, :3].T @ T[:3, :3])) < 0.05


def test_too_few_correspondences() -> None:
    rng = np.random.default_rng(5)
    r1, r2, _, _ = _scene(rng, 6, np.array([0.0, 0.0, 10.0]))
    with pytest.raises(ReconstructionError, match="correspondences"):
        estimate_relative_motion(r1, r2)


def test_compiled_inlier_test_is_the_angular_epipolar_error_below_the_threshold() -> None:
    """RANSAC's compiled inlier test (:func:`omnipipe.sfm._kernels.epipolar_inliers`)
    against its NumPy reference, :func:`epipolar_angle` below the threshold: the same
    pairs on noisy inliers and outliers, pairs within 1e-9 rad of the threshold aside;
    a zero epipolar normal is no inlier in either."""
    from omnipipe.sfm._kernels import epipolar_inliers

    rng = np.random.default_rng(4)
    r1 = rng.normal(size=(2000, 3))
    r1 /= np.linalg.norm(r1, axis=1)[:, None]
    t = np.array([0.2, -0.1, 1.0])
    r2 = r1 * rng.uniform(50.0, 150.0, len(r1))[:, None] - 4.0 * t
    r2[:500] = rng.normal(size=(500, 3))  # outliers
    r2 += rng.normal(scale=0.003, size=r2.shape) * np.linalg.norm(r2, axis=1)[:, None]
    r2 /= np.linalg.norm(r2, axis=1)[:, None]
    E = eight_point(r1[500:], r2[500:])
    for threshold in (math.radians(0.05), math.radians(0.2), math.radians(2.0)):
        angle = epipolar_angle(E, r1, r2)
        got = epipolar_inliers(E, r1, r2, math.sin(threshold))
        clear = np.abs(angle - threshold) > 1e-9
        assert 0 < np.count_nonzero(got) < len(got)
        assert np.array_equal(got[clear], (angle < threshold)[clear])
    zero = np.zeros((3, 3))
    assert not epipolar_inliers(zero, r1[:5], r2[:5], math.sin(math.radians(0.2))).any()
    assert not (epipolar_angle(zero, r1[:5], r2[:5]) < math.radians(0.2)).any()


@pytest.mark.parametrize("size", [8, 9, 40, 600])
def test_compiled_sample_hypothesis_is_eight_point_and_its_inliers(size: int) -> None:
    """RANSAC's compiled hypothesis (:func:`omnipipe.sfm._kernels.sample_hypothesis`)
    against its NumPy reference: :func:`eight_point` on the sample's rays and
    :func:`epipolar_angle` below the threshold, on samples of minimal and LO-refit size
    from noisy inliers and outliers (E equal up to sign within 1e-12; the same inliers,
    pairs within 1e-9 rad of the threshold aside)."""
    from omnipipe.sfm._kernels import sample_hypothesis

    rng = np.random.default_rng(7)
    r1, r2, _, _ = _scene(rng, 1200, np.array([3.0, -1.0, 10.0]))
    r2 = _noisy(r2, rng, math.radians(0.05))
    r2[:300] = _noisy(rng.normal(size=(300, 3)), rng, 0.0)  # outliers
    threshold = math.radians(0.2)
    for _ in range(20):
        sample = rng.choice(len(r1), size, replace=False)
        E, inl = sample_hypothesis(r1, r2, sample, math.sin(threshold))
        ref = eight_point(r1[sample], r2[sample])
        assert min(np.abs(E - ref).max(), np.abs(E + ref).max()) < 1e-12
        angle = epipolar_angle(ref, r1, r2)
        clear = np.abs(angle - threshold) > 1e-9
        assert np.array_equal(inl[clear], (angle < threshold)[clear])
    _, inl = sample_hypothesis(r1, r2, np.arange(300, len(r1)), math.sin(threshold))
    assert np.count_nonzero(inl[300:]) > 850 and np.count_nonzero(inl[:300]) < 30  # the motion
