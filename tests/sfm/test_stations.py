"""Stationary-frame detection on a simulated stop-and-go run."""

from __future__ import annotations

import numpy as np

from omnipipe.sfm.stations import StationTracker, noise_sigma
from omnipipe.sim import make_scenario
from omnipipe.sim.writer import build_renderer


def test_noise_estimate_on_pure_noise() -> None:
    rng = np.random.default_rng(0)
    img = 100.0 + rng.normal(0, 2.0, (300, 400))
    assert abs(noise_sigma(img) - 2.0) < 0.1


def test_stops_are_found_exactly() -> None:
    scenario = make_scenario("bend-small", frames=20, seed=2)
    renderer, poses, _, moving = build_renderer(scenario)
    tracker = StationTracker(renderer.camera.valid_mask())
    flags, ratios = [], []
    for i, pose in enumerate(poses):
        image, _ = renderer.render(pose, seed=100 + i)
        moved, ratio = tracker.update(image[..., 1])
        flags.append(moved)
        ratios.append(ratio)
    flags = np.array(flags)
    assert flags[0]  # the first frame starts a station
    assert np.array_equal(flags[1:], moving[1:])
    still = np.array(ratios[1:])[~moving[1:]]
    assert np.all(still < 2.0)  # the noise model explains stationary pairs


def test_counted_median_equals_numpy_median() -> None:
    from omnipipe.sfm.stations import _median_abs

    rng = np.random.default_rng(5)
    for n in (1, 2, 3, 10, 999, 1000):
        whole = rng.integers(-900, 900, n).astype(np.float32)  # the counting path
        half = whole + np.float32(0.5)  # not whole numbers: numpy's path
        for values in (whole, half):
            assert _median_abs(values) == np.median(np.abs(values))
