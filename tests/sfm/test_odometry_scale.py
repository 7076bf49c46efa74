"""The run's scale bounded by the odometry where vision's own sigma is as large."""

from __future__ import annotations

import math

import numpy as np

from omnipipe.sfm.odometry_scale import with_odometry_scale
from omnipipe.sfm.robot_sensors import OdometrySteps
from omnipipe.sfm.run_length import RunLength
from omnipipe.sfm.scale_check import StepCheck

SLIP_REL = 0.03  # the odometry's stated relative sigma (covers its slip)


def _run(rng: np.random.Generator, vision_error: float, slip: float, k: int = 10):
    """True steps of 8-20 mm; the adjusted keyframes ``vision_error`` long; the
    odometry ``slip`` long with 0.1 mm of noise a step, stated SLIP_REL + 0.1 mm."""
    true = rng.uniform(8.0, 20.0, k)
    z = np.concatenate([[0.0], np.cumsum(true * (1 + vision_error))])
    poses = np.tile(np.eye(4), (k + 1, 1, 1))
    poses[:, 2, 3] = z
    odo = true * (1 + slip) + rng.normal(0.0, 0.1, k)
    sigma = np.hypot(SLIP_REL * odo, 0.1)
    steps = OdometrySteps(odo, sigma, 0.1, noise_mm=np.full(k, 0.1))
    checks = [StepCheck(i, i + 1, v, 0.9, v, 400, v, "high") for i, v in enumerate(np.diff(z))]
    return true, poses, checks, steps


def _scale_error(length: RunLength, poses: np.ndarray, true: np.ndarray) -> float:
    gain = 1.0 if math.isnan(length.correction_log) else math.exp(length.correction_log)
    return gain * float(np.linalg.norm(poses[-1, :3, 3] - poses[0, :3, 3])) / float(true.sum()) - 1.0


def test_a_loose_vision_scale_is_bounded_by_the_odometry_and_its_sigma_covers() -> None:
    """Vision 9-13 % long stating 10 %, the odometry 1-3 % long (its slip) stating 3 %:
    the combined scale lies within 4 % of the truth (the slip and vision's residual share) and within 2 of its sigmas, and a
    warning says what was combined."""
    for seed in (1, 2, 3):
        rng = np.random.default_rng(seed)
        error = rng.uniform(0.09, 0.13)
        true, poses, checks, steps = _run(rng, error, rng.uniform(0.01, 0.03))
        warnings: list[str] = []
        out = with_odometry_scale(RunLength(math.nan, 0.10, math.nan, "laser"), poses, checks, steps, warnings)
        e = _scale_error(out, poses, true)
        assert abs(e) < 0.04, (seed, e)
        assert abs(e) <= 2 * out.sigma_rel, (seed, e, out.sigma_rel)
        assert out.sigma_rel < 0.10
        assert any("combined with the odometry" in w for w in warnings)
        assert "bounded by the odometry" in out.source


def test_a_good_vision_scale_is_not_moved_by_the_odometry() -> None:
    """Vision stating 1 % (under half the odometry's 3 %): nothing changes, however far
    the odometry's slip reads; without odometry nothing changes either."""
    rng = np.random.default_rng(4)
    _, poses, checks, steps = _run(rng, 0.004, 0.03)
    length = RunLength(0.001, 0.01, math.nan, "laser")
    warnings: list[str] = []
    assert with_odometry_scale(length, poses, checks, steps, warnings) == length
    assert with_odometry_scale(length, poses, checks, None, warnings) == length
    assert not warnings


def test_steps_vision_did_not_measure_do_not_read_the_scale() -> None:
    """Steps bridged from the odometry (its own lengths) and flagged ones are left out
    of the odometry's reading: with every step bridged there is none."""
    rng = np.random.default_rng(5)
    _, poses, checks, steps = _run(rng, 0.10, 0.02)
    bridged = [
        StepCheck(c.first_frame, c.last_frame, math.nan, 0.0, math.nan, 10, math.nan, "none",
                  "relative motion not found", bridged_from="odometry")
        for c in checks
    ]
    length = RunLength(math.nan, 0.10, math.nan, "laser")
    assert with_odometry_scale(length, poses, bridged, steps, []) == length


def test_a_reading_over_too_few_steps_is_not_used() -> None:
    """Three vision-measured steps (fewer than MIN_READING_STEPS): no reading, nothing moved."""
    rng = np.random.default_rng(6)
    _, poses, checks, steps = _run(rng, 0.10, 0.02, k=3)
    length = RunLength(math.nan, 0.10, math.nan, "laser")
    assert with_odometry_scale(length, poses, checks, steps, []) == length
