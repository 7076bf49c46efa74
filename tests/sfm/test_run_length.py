"""The run's scale combination (sfm.run_length: the laser's decided correction, the
wall-placed features, the wall's own shift): continuous in its inputs, and its sigma
covering the truth on seeded synthetic readings."""

from __future__ import annotations

import math

import numpy as np
import pytest

from omnipipe.sfm.run_length import (
    DECIDED_SIGMAS,
    SOURCES_BIAS_SIGMA,
    combine_scales,
    combine_shift,
    laser_say,
    mix,
    ramp,
)
from omnipipe.sfm.shift_scale import ShiftScale


def _combined(decided: float, laser_sigma: float, wall: tuple[float, float], shift: ShiftScale) -> tuple[float, float]:
    """run_length's combination of its readings (no wall anchors)."""
    log, sig = laser_say(decided, laser_sigma)
    applied, sigma = combine_scales(wall[0], wall[1], sig, False, log)
    return combine_shift(applied, sigma, shift)


def _largest_jump(values: np.ndarray, f) -> tuple[float, float]:
    """The largest change of f's (log, sigma) between neighbouring inputs of the sweep."""
    out = np.array([f(v) for v in values])
    return float(np.abs(np.diff(out[:, 0])).max()), float(np.abs(np.diff(out[:, 1])).max())


def test_ramp_and_mix() -> None:
    assert ramp(0.5, 1.0, 3.0) == 0.0 and ramp(2.0, 1.0, 3.0) == 0.5 and ramp(9.0, 1.0, 3.0) == 1.0
    # The mixture's sigma carries the spread between the two readings.
    mean, sigma = mix(0.5, (0.0, 0.01), (0.02, 0.01))
    assert mean == pytest.approx(0.01)
    assert sigma == pytest.approx(math.sqrt(0.01**2 + 0.25 * 0.02**2))
    assert mix(0.0, (0.1, 0.2), (0.3, 0.4)) == (0.1, 0.2)


def test_the_laser_s_correction_grows_with_its_significance() -> None:
    # Within DECIDED_SIGMAS[0] of its sigma: the adjusted run's (0); beyond [1]: all of it.
    assert laser_say(0.009, 0.01) == (0.0, 0.01)
    assert laser_say(0.04, 0.01) == (0.04, 0.01)
    mid = 0.5 * (DECIDED_SIGMAS[0] + DECIDED_SIGMAS[1]) * 0.01
    log, sigma = laser_say(mid, 0.01)
    assert log == pytest.approx(mid / 2) and sigma > 0.01  # halfway, the spread in the sigma
    assert laser_say(0.05, math.nan)[0] == 0.0


@pytest.mark.parametrize("sweep", ["decided", "shift", "wall"])
def test_a_small_input_change_gives_a_small_output_change(sweep: str) -> None:
    """Each reading swept in steps of 0.001 % across every former switch (the laser's
    2 sigma, the shared bias's chi-square 1, the shift's 3 sigma): the combined log scale
    and its sigma move by at most a few times the step (the hard gates jumped by up to the
    sources' whole gap, 0.5-7 %)."""
    step = 1e-5
    values = np.arange(-0.08, 0.08, step)
    fs = {
        "decided": lambda v: _combined(v, 0.006, (0.004, 0.004), ShiftScale(0.01, 0.008, 10)),
        "shift": lambda v: _combined(0.003, 0.006, (0.004, 0.004), ShiftScale(v, 0.008, 10)),
        "wall": lambda v: _combined(0.003, 0.006, (v, 0.004), ShiftScale(0.02, 0.008, 10)),
    }
    jump_log, jump_sigma = _largest_jump(values, fs[sweep])
    assert jump_log < 5 * step and jump_sigma < 5 * step


def test_the_combination_covers_the_truth_on_seeded_readings() -> None:
    """Seeded readings of a run whose adjusted length is off by ``c`` (log): the laser's
    decided correction and the wall-placed features read c with their own noise plus,
    on a third of the runs, a shared bias (SOURCES_BIAS_SIGMA); the wall's shift reads c
    without it. The combined correction is within 2 of its sigmas of c on >= 90 % of
    the runs, and its median error below that of the wall-placed features alone and of the
    shift alone."""
    rng = np.random.default_rng(7)
    errors, covered, walls, shifts = [], 0, [], []
    n = 2000
    for _ in range(n):
        c = rng.normal(0.0, 0.01)
        bias = rng.normal(0.0, SOURCES_BIAS_SIGMA) if rng.random() < 1 / 3 else 0.0
        s_laser, s_wall, s_shift = rng.uniform(0.002, 0.01), rng.uniform(0.002, 0.01), rng.uniform(0.004, 0.015)
        decided = c + bias + rng.normal(0.0, s_laser)
        wall = c + bias + rng.normal(0.0, s_wall)
        shift = c + rng.normal(0.0, s_shift)
        # The adjusted run is not the truth: the laser's gate keeps it (0) when decided is
        # within the laser's sigma, so the truth is read as the run's own error c.
        log, sigma = _combined(decided, s_laser, (wall, s_wall), ShiftScale(shift, s_shift, 10))
        errors.append(abs(log - c))
        covered += abs(log - c) <= 2 * sigma
        walls.append(abs(wall - c))
        shifts.append(abs(shift - c))
    assert covered / n >= 0.9
    assert np.median(errors) < min(np.median(walls), np.median(shifts))


def _anchor(a: int, epipolar: bool, n: int = 60, spread: float = 0.02, seed: int = 0, b: int | None = None):
    from omnipipe.sfm.types import Anchor

    rng = np.random.default_rng(seed)
    return Anchor(a, a + 1 if b is None else b, np.zeros((n, 3)), np.zeros((n, 2)), rng.normal(0.0, spread, n), epipolar)


def test_a_run_anchored_on_feature_depths_states_their_shared_bias() -> None:
    """Seeded runs of 2-4 steps whose feature depths share a bias drawn at 1 % (their
    per-step floor, one bias over the run): anchored on wall-placed features only, the
    run's sigma (the anchors' spread, the shared part and this share) covers the bias
    within 2 sigma on >= 93 % of 400 runs (without the share: < 85 %); the share is the
    length anchored by features, not laser matches (a far laser anchor a -> a + 2 makes
    no step a laser one)."""
    from omnipipe.sfm.run_length import (
        FEATURE_ANCHOR_SIGMA,
        SHARED_SCALE_SIGMA,
        feature_share,
        scale_sigma,
    )

    rng = np.random.default_rng(7)
    z_new, z_old = [], []
    for i in range(400):
        n = int(rng.integers(2, 5))
        bias = rng.normal(0.0, FEATURE_ANCHOR_SIGMA)
        anchors = [_anchor(k, False, n=600, spread=0.03, seed=i * 10 + k) for k in range(n)]
        scales = list(rng.uniform(10, 30, n))
        before = math.hypot(scale_sigma(anchors, scales, 0.0, False), SHARED_SCALE_SIGMA)
        after = math.hypot(before, FEATURE_ANCHOR_SIGMA * feature_share(anchors, scales))
        z_new.append(abs(bias) / after)
        z_old.append(abs(bias) / before)
    assert (np.array(z_new) <= 2).mean() >= 0.93
    assert (np.array(z_old) <= 2).mean() < 0.85
    laser = [_anchor(k, True, seed=k) for k in range(3)]
    feats = [_anchor(k, False, seed=k) for k in range(3)]
    scales = [20.0, 20.0, 20.0]
    assert feature_share(laser, scales) == 0.0 and feature_share(feats, scales) == 1.0
    assert abs(feature_share([laser[0], feats[1], laser[2]], scales) - 1 / 3) < 1e-12
    assert feature_share([_anchor(0, True, b=2), *feats], scales) == 1.0


def test_bridged_steps_add_their_sigma_to_the_run_s() -> None:
    """A run of odometry-bridged steps only (a plain wall) states their summed sigma over
    their length, which covers a slip drawn at the stated 3 % within 2 sigma on >= 93 %
    of 400 seeded runs (the assumed 1 % fallback covered about half); a mixed run lies
    between its measured part's sigma and the bridges'; without bridges nothing changes."""
    from omnipipe.sfm.run_length import with_bridged
    from omnipipe.sfm.scale_check import StepCheck

    def check(k: int, bridged: float | None, sigma: float = math.nan) -> StepCheck:
        c = StepCheck(k, k + 1, math.nan, 0.0, math.nan, 0, math.nan, "none" if bridged else "high", "")
        if bridged is None:
            return c
        from dataclasses import replace

        return replace(c, bridged_mm=bridged, bridged_sigma_mm=sigma, bridged_from="odometry")

    rng = np.random.default_rng(3)
    z = []
    for _ in range(400):
        n = int(rng.integers(2, 8))
        truth = rng.uniform(5, 20, n)
        slip = rng.normal(0.0, 0.03)
        stated = 0.03 * truth + 0.1
        checks = [check(k, float(t * (1 + slip)), float(s)) for k, (t, s) in enumerate(zip(truth, stated, strict=True))]
        s = with_bridged(math.nan, checks, [0.0] * n)
        z.append(abs(slip) / s)
    assert (np.array(z) <= 2).mean() >= 0.93
    measured = [check(0, None), check(1, None), check(2, 10.0, 0.5)]
    s = with_bridged(0.005, measured, [20.0, 20.0, 0.0])
    assert 0.005 * 40 / 50 < s < 0.05
    assert with_bridged(0.004, [check(0, None)], [20.0]) == 0.004
    assert math.isnan(with_bridged(math.nan, measured, [20.0, 20.0, 0.0]))
