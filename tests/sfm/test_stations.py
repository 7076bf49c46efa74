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


def _frame_cases(rng: np.random.Generator) -> list[tuple[np.ndarray, str]]:
    """Frames of every kind the fast signature path takes, and some it must not."""
    rgb8 = rng.normal(120, 9, (64, 96, 3)).clip(0, 255).astype(np.uint8)
    rgb16 = rng.normal(30000, 900, (64, 96, 3)).clip(0, 65535).astype(np.uint16)
    return [
        (rgb8, "red"),  # fast: the green channel
        (rgb16, "red"),  # fast, 16 bit
        (rgb8[..., 1].copy(), "red"),  # fast: one channel
        (rgb8, "green"),  # slow: the mean of red and blue
        (rgb8[:63, :94], "red"),  # fast: sides not divisible by 4 (the resize handles them)
        (np.kron(rng.integers(0, 2, (32, 48, 1)), np.ones((2, 2, 3))).astype(np.uint8) * 255, "red"),  # extremes
        ((rng.integers(0, 2, (64, 96, 3)) * 65535).astype(np.uint16), "red"),  # 16-bit extremes
        (rgb8.astype(np.float32), "red"),  # slow: float frame
        (np.full((64, 96, 3), 255, np.uint8), "red"),  # saturated: all-zero response
    ]


def test_frame_signature_equals_the_grey_image_signature() -> None:
    from omnipipe.image import gray_without_laser
    from omnipipe.sfm.stations import frame_signature, inner_mask, mask_runs, station_signature

    rng = np.random.default_rng(11)
    for image, channel in _frame_cases(rng):
        h, w = image.shape[:2]
        yy, xx = np.mgrid[:h, :w]
        mask = (xx - w / 2) ** 2 + (yy - h / 2) ** 2 < (0.6 * w) ** 2  # cut by the borders
        inner = inner_mask(mask)
        want = station_signature(gray_without_laser(image, channel), inner)
        got = frame_signature(image, channel, inner)
        again = frame_signature(image, channel, inner, runs=mask_runs(inner))
        assert np.array_equal(again.small, got.small) and again.noise_sigma == got.noise_sigma
        assert got.small.dtype == want.small.dtype == np.float32
        assert np.array_equal(got.small, want.small), (image.shape, image.dtype, channel)
        assert got.noise_sigma == want.noise_sigma, (image.shape, image.dtype, channel)


def test_mask_runs_cover_exactly_the_mask() -> None:
    from omnipipe.sfm.stations import mask_runs

    rng = np.random.default_rng(12)
    for shape in ((1, 1), (5, 7), (40, 33)):
        mask = rng.random(shape) > 0.4
        mask[0, :] = True  # a run to the row's end
        runs = mask_runs(mask)
        flat = np.zeros(mask.size, bool)
        for start, end in runs:
            assert start < end and start // shape[1] == (end - 1) // shape[1]  # within one row
            flat[start:end] = True
        assert np.array_equal(flat.reshape(shape), mask)
