"""The compiled per-line statistics of the ring extraction equal their NumPy formulation."""

from __future__ import annotations

import numpy as np

from omnipipe.laser._kernels import line_statistics


def _numpy_statistics(polar: np.ndarray, clipped: np.ndarray, sep: int, step: int) -> tuple:
    """The NumPy formulation (whole-array medians and masks) the kernel replaces."""
    bg = np.median(polar[:, ::4], axis=1, keepdims=True)
    prof = polar - bg
    diff = prof[:, 1::4] - prof[:, 0:-1:4][:, : prof[:, 1::4].shape[1]]
    mad = np.median(np.abs(diff - np.median(diff, axis=1, keepdims=True)), axis=1)
    k = np.argmax(prof, axis=1)
    rows = np.arange(len(polar))
    idx = np.arange(prof.shape[1])[None, :]
    second = np.where(np.abs(idx - k[:, None]) > sep, prof, -np.inf).max(axis=1)
    win = np.clip(k[:, None] + np.arange(-4, 5)[None, :], 0, prof.shape[1] - 1)
    run = clipped[rows[:, None], win].sum(axis=1)
    near = [prof[rows, np.clip(k + d, 0, prof.shape[1] - 1)] for d in (-step, 0, step)]
    return bg[:, 0], mad, k, second, run, np.stack(near, axis=1)


def test_line_statistics_equal_numpy_bit_for_bit() -> None:
    rng = np.random.default_rng(3)
    for samples in (2, 3, 4, 5, 6, 7, 9, 64, 131, 508):
        polar = rng.normal(10, 4, (50, samples)).astype(np.float32)
        polar[:10] = np.round(polar[:10])  # ties: medians of equal values, repeated maxima
        polar[10:20, :] = 7.0  # flat lines
        peak_at = rng.integers(0, samples, 50)
        polar[np.arange(20, 50), peak_at[20:]] += 80  # a clear peak, anywhere (ends too)
        clipped = polar > 60
        cases = [polar]
        # Whole numbers, as an integer frame gives (counted): narrow, negative, sparse;
        # spread over more values than the count holds (selected); half-integers.
        whole = np.round(rng.normal(0, 30, (50, samples))).astype(np.float32)
        whole[:10] = rng.integers(-3, 3, (10, samples))
        whole[10:20] = rng.choice(np.array([-200, 0, 5, 311], np.float32), (10, samples))
        whole[20:30] = np.round(rng.normal(0, 400, (10, samples)))
        whole[30:40] = np.round(rng.normal(0, 3, (10, samples))) + np.float32(0.5)
        cases.append(whole)
        for polar, sep, step in [(p, a, b) for p in cases for a, b in ((3, 1), (0, 1), (2, 2))]:
            got = line_statistics(polar, clipped, sep, step)
            want = _numpy_statistics(polar, clipped, sep, step)
            for name, a, b in zip(
                ("background", "mad", "peak_index", "second", "clipped_run", "around"),
                (got.background, got.mad, got.peak_index, got.second, got.clipped_run, got.around),
                want,
                strict=True,
            ):
                assert a.dtype == b.dtype or a.dtype.kind == b.dtype.kind == "i", name
                assert np.array_equal(a, b, equal_nan=True), (name, samples, sep, step)
