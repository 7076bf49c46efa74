"""Descriptor matching: the exact two-nearest search equals OpenCV's brute force."""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from omnipipe.sfm._kernels import two_smallest_columns
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


@pytest.mark.parametrize("seed", range(4))
def test_two_smallest_columns_equals_numpy(seed: int) -> None:
    """The backward search read off the forward product: each column's nearest row and
    two smallest squared distances, as NumPy finds them (the first of equal minima)."""
    rng = np.random.default_rng(seed)
    top = 256 if seed % 2 else 6  # small ranges: many equal distances
    n, m = (int(v) for v in rng.integers(2, 200, 2))
    a = rng.integers(0, top, (n, 128)).astype(np.float32)
    b = rng.integers(0, top, (m, 128)).astype(np.float32)
    a[: n // 3] = a[n - n // 3 :]  # duplicated rows: ties
    dot = a @ b.T
    qq, tt = np.einsum("ij,ij->i", a, a), np.einsum("ij,ij->i", b, b)
    cols = np.unique(rng.integers(0, len(b), 40))
    best, d0, d1 = two_smallest_columns(qq, tt, dot, cols)
    d = tt[cols][None, :] + qq[:, None] - np.float32(2.0) * dot[:, cols]  # (rows, C)
    ranked = np.sort(d, axis=0)
    assert np.array_equal(best, np.argmin(d, axis=0))
    assert np.array_equal(d0, np.maximum(ranked[0], 0)) and np.array_equal(d1, np.maximum(ranked[1], 0))


def _match_reference(f1: FrameFeatures, f2: FrameFeatures, ratio: float) -> np.ndarray:
    """match_features as two searches of their own (the former code)."""
    def one_way(a: np.ndarray, b: np.ndarray) -> dict[int, int]:
        best, d0, d1 = two_nearest(a, b)
        keep = np.flatnonzero(d0.astype(np.float64) < ratio * d1.astype(np.float64))
        return dict(zip(keep.tolist(), best[keep].tolist(), strict=True))

    fwd = one_way(f1.descriptors, f2.descriptors)
    targets = np.unique(np.fromiter(fwd.values(), int, len(fwd)))
    bwd = {int(targets[q]): i for q, i in one_way(f2.descriptors[targets], f1.descriptors).items()}
    return np.array([(i, j) for i, j in fwd.items() if bwd.get(j) == i], int).reshape(-1, 2)


@pytest.mark.parametrize("seed", range(4))
def test_match_features_equals_two_searches(seed: int) -> None:
    rng = np.random.default_rng(seed)
    base = rng.integers(0, 120, (300, 128)).astype(np.float32)
    other = np.clip(base[rng.permutation(300)[:250]] + rng.integers(-9, 10, (250, 128)), 0, 255)
    other = np.concatenate([other, rng.integers(0, 120, (80, 128))]).astype(np.float32)
    other[:10] = other[10:20]  # equal descriptors: no ratio test passes between them

    def feats(d: np.ndarray) -> FrameFeatures:
        return FrameFeatures(np.zeros((len(d), 3)), np.zeros((len(d), 2)), d, np.zeros(len(d), int))

    got = match_features(feats(base), feats(other), 0.8)
    assert len(got) > 100
    assert np.array_equal(got, _match_reference(feats(base), feats(other), 0.8))
