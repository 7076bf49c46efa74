"""Trajectory alignment and errors."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from omnipipe.evaluation.trajectory import align, trajectory_errors
from omnipipe.geometry import make_transform


def _straight_run(n: int, rng: np.random.Generator) -> np.ndarray:
    poses = np.empty((n, 4, 4))
    for i in range(n):
        rot = Rotation.from_euler("xyz", rng.normal(0, 0.01, 3)).as_matrix()
        poses[i] = make_transform(rot, [rng.normal(0, 1.0), rng.normal(0, 1.0), 10.0 * i])
    return poses


def test_alignment_recovers_a_rigid_offset_on_a_straight_path() -> None:
    rng = np.random.default_rng(0)
    gt = _straight_run(30, rng)
    offset = make_transform(
        Rotation.from_euler("zyx", [40, -20, 10], degrees=True).as_matrix(), [5, -3, 100]
    )
    est = np.linalg.inv(offset)[None] @ gt  # est world = offset^-1 gt world
    errs = trajectory_errors(est, gt)
    assert errs.ate_rmse_mm < 1e-9 and errs.rotation_rmse_deg < 1e-6 and errs.scale_error < 1e-9
    assert np.allclose(errs.gt_from_est, offset)


def test_scale_and_noise_are_measured() -> None:
    rng = np.random.default_rng(1)
    gt = _straight_run(40, rng)
    est = gt.copy()
    est[:, :3, 3] *= 1.02
    _, s = align(est, gt, with_scale=True)
    assert s == pytest.approx(1 / 1.02, rel=1e-9)
    assert trajectory_errors(est, gt).scale_error == pytest.approx(1 - 1 / 1.02, rel=1e-9)
    noisy = gt.copy()
    noisy[:, :3, 3] += rng.normal(0, 0.5, (40, 3))
    errs = trajectory_errors(noisy, gt)
    assert 0.5 < errs.ate_rmse_mm < 1.2  # sqrt(3) * 0.5 = 0.87 expected
