"""The run's scale read off the wall's own shift (sfm.shift_scale) and its combination with
the other sources (sfm.run_length.combine_shift), on seeded synthetic walls rendered
through the camera model: the truth is the travel the images were rendered with."""

from __future__ import annotations

import math

import numpy as np
import pytest
from test_wall_shift import _bricks, _context, _faint, _forward, _render, _ring

from omnipipe.camera import OmniCamera
from omnipipe.sfm.run_length import SOURCES_BIAS_SIGMA, combine_shift
from omnipipe.sfm.scale_check import StepCheck
from omnipipe.sfm.shift_scale import MIN_SHIFT_STEPS, ShiftScale, shift_scale
from omnipipe.sfm.types import Keyframes, StepEvidence


def _run(
    camera: OmniCamera, seed: int, adjusted_gain: float
) -> tuple[Keyframes, np.ndarray, list[StepCheck], np.ndarray]:
    """Five keyframes 4-9 mm apart on a seeded wall (a rig off the axis by up to 2 mm);
    the "adjusted" poses are the true ones with every length times ``adjusted_gain``
    (a bundle adjustment that shortened the run). Returns the keyframes, the adjusted
    (K, 4, 4) world_from_kf, the steps' checks (decided on the adjusted lengths) and the
    true (K-1,) lengths."""
    rng = np.random.default_rng(seed)
    wall = _bricks(rng, rng.uniform(12, 30)) if seed % 2 else _faint(rng)
    steps = rng.uniform(4.0, 9.0, 5)
    z = np.concatenate([[0.0], np.cumsum(steps)])
    offsets = [tuple(rng.normal(0, 1.0, 2)) for _ in z]
    grays = [_render(camera, wall, zk, off, 0.0, rng) for zk, off in zip(z, offsets, strict=True)]
    world_from_kf = np.repeat(np.eye(4)[None], len(z), axis=0)
    world_from_kf[:, 2, 3] = adjusted_gain * z
    evidence, checks = [], []
    for k, s in enumerate(steps):
        evidence.append(StepEvidence(k, k + 1, _forward(), None, None, np.zeros(0), s, 80, "ok"))
        checks.append(StepCheck(k, k + 1, s, 0.1, s, 80, adjusted_gain * s, "high"))
    kf = Keyframes(list(range(len(z))), [], grays, [_ring(o) for o in offsets], evidence)
    return kf, world_from_kf, checks, steps


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_the_wall_s_shift_finds_the_run_s_true_scale_within_its_sigma(
    small_camera: OmniCamera, seed: int
) -> None:
    # The adjusted run 6 % short (random-wide seed 32's tiles: 7 %).
    kf, world_from_kf, checks, _ = _run(small_camera, seed, 0.94)
    got = shift_scale(_context(small_camera), kf, world_from_kf, checks)
    assert got is not None and got.steps >= MIN_SHIFT_STEPS
    truth = math.log(1 / 0.94)
    assert abs(got.log - truth) <= 2 * got.sigma, (got, truth)
    assert got.sigma <= 0.02  # a reading, not a shrug


def test_untrusted_steps_are_not_read(small_camera: OmniCamera) -> None:
    kf, world_from_kf, checks, _ = _run(small_camera, 4, 1.0)
    checks = [StepCheck(c.first_frame, c.last_frame, c.laser_scale_mm, 0.1, c.feature_scale_mm, 80, c.scale_mm, "none", "x") for c in checks]
    assert shift_scale(_context(small_camera), kf, world_from_kf, checks) is None


def test_a_disagreeing_shift_overrules_with_a_sigma_that_spans_both() -> None:
    # Laser and features say +0.3 % +- 0.9 %, the wall's shift +6.9 % +- 0.8 % (seed 32):
    # their shared bias (3 %) leaves the shift most of the weight (the gap 2 of the widened
    # sigmas: barely any of the shift-alone reading mixed in).
    mean, sigma = combine_shift(0.003, 0.009, ShiftScale(0.069, 0.008, 10))
    w1, w2 = 1 / (0.009**2 + SOURCES_BIAS_SIGMA**2), 0.008**-2
    assert mean == pytest.approx((w1 * 0.003 + w2 * 0.069) / (w1 + w2), abs=5e-4)
    assert abs(mean - 0.069) <= 0.005 and sigma >= 0.008
    # Further apart than even the shared bias explains: the shift, with half the gap
    # in its sigma (the other stays within 2 sigma).
    mean, sigma = combine_shift(0.003, 0.009, ShiftScale(0.15, 0.008, 10))
    assert mean == pytest.approx(0.15)
    assert abs(mean - 0.003) <= 2 * sigma
    # Sources within their own sigmas (a full-size clean run: no bias shown): the
    # inverse-variance mean of their own sigmas, between them, below either's sigma.
    mean, sigma = combine_shift(0.010, 0.004, ShiftScale(0.013, 0.008, 10))
    w1, w2 = 0.004**-2, 0.008**-2
    assert mean == pytest.approx((w1 * 0.010 + w2 * 0.013) / (w1 + w2))
    assert sigma == pytest.approx((w1 + w2) ** -0.5)
    # A gap beyond their own sigmas (1.5 sigma) but within the widened ones: the
    # others widened by their shared bias, then the inverse-variance mean.
    base_sigma = math.hypot(0.004, SOURCES_BIAS_SIGMA)
    mean, sigma = combine_shift(0.004, 0.004, ShiftScale(0.0174, 0.008, 10))
    w1, w2 = base_sigma**-2, 0.008**-2
    assert mean == pytest.approx((w1 * 0.004 + w2 * 0.0174) / (w1 + w2))
    assert sigma == pytest.approx((w1 + w2) ** -0.5)
    # No other source: the shift alone.
    assert combine_shift(math.nan, math.nan, ShiftScale(0.02, 0.01, 5)) == (0.02, 0.01)
