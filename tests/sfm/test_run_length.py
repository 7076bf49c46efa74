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
