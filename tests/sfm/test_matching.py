"""Descriptor matching: the exact two-nearest search equals OpenCV's brute force."""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from omnipipe.sfm.features import FrameFeatures, match_features, two_nearest


def _brute(a: np.ndarray, b: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    found = cv2.BFMatcher(cv2.NORM_L2).knnMatch(a, b, k=2)
    return (
        np.array([m[0].trainIdx for m in found]),
        np.array([m[0].distance for m in found], np.float32),
        np.array([m[1].distance for m in found], np.float32),
    )


@pytest.mark.parametrize("seed", range(6))
def test_two_nearest_equals_brute_force_to_the_bit(seed: int) -> None:
    rng = np.random.default_rng(seed)
    n, m = rng.integers(2, 300, 2)
    top = 256 if seed % 2 else 8  # small ranges: many equal distances
    a = rng.integers(0, top, (n, 128)).astype(np.float32)
    b = rng.integers(0, top, (m, 128)).astype(np.float32)
    b[: m // 2] = b[m - m // 2 :]  # duplicated train descriptors: ties
    best, d0, d1 = two_nearest(a, b)
    ref_best, ref0, ref1 = _brute(a, b)
    assert np.array_equal(d0, ref0) and np.array_equal(d1, ref1)
    untied = ref0 < ref1  # with a tie, either is "nearest" and no ratio test passes
    assert np.array_equal(best[untied], ref_best[untied])


def test_non_integer_descriptors_take_the_brute_force_path() -> None:
    rng = np.random.default_rng(9)
    a, b = rng.random((40, 128), np.float32), rng.random((50, 128), np.float32)
    best, d0, d1 = two_nearest(a, b)
    ref_best, ref0, ref1 = _brute(a, b)
    assert np.array_equal(best, ref_best) and np.array_equal(d0, ref0) and np.array_equal(d1, ref1)


def test_matches_are_mutual_and_pass_the_ratio_test() -> None:
    rng = np.random.default_rng(3)
    base = rng.integers(0, 200, (120, 128)).astype(np.float32)
    noisy = np.clip(base + rng.integers(-3, 4, base.shape), 0, 255).astype(np.float32)
    order = rng.permutation(len(base))

    def feats(d: np.ndarray) -> FrameFeatures:
        return FrameFeatures(np.zeros((len(d), 3)), np.zeros((len(d), 2)), d, np.zeros(len(d), int))

    pairs = match_features(feats(base), feats(noisy[order]))
    assert len(pairs) >= 110  # distinct descriptors, small noise: nearly all found
    assert np.array_equal(order[pairs[:, 1]], pairs[:, 0])  # each to its own copy
