"""RANSAC [23] for the relative motion of two omni-directional views, on rays.

Minimal samples of eight ray pairs feed the eight-point algorithm (Eq. 10-14),
each new best hypothesis is refitted on its inliers (LO-RANSAC);
inliers are pairs whose angular epipolar error is below a threshold; the number of
iterations adapts to the inlier ratio. A near-stationary or purely rotating rig
(the earthworm robot often stands still) has no defined translation: when a pure
rotation explains the inliers about as well as the essential matrix, the result is
flagged ``translation_reliable = False`` and carries a zero translation.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from omnipipe.config import bounded
from omnipipe.errors import ReconstructionError
from omnipipe.geometry import make_transform
from omnipipe.sfm._kernels import sample_hypothesis
from omnipipe.sfm.geometry import (
    _check_pairs,
    decompose_essential,
    eight_point,
    rotation_from_rays,
)


@dataclass(frozen=True)
class RansacConfig:
    """Settings.

    Attributes:
        threshold_rad: inlier threshold on the angular epipolar error (rad).
        max_iterations: upper bound of iterations.
        confidence: stop when an all-inlier sample has been drawn with this probability.
        min_inliers: fewest inliers for a result.
        rotation_only_ratio: translation unreliable when the rotation-only model has at
            least this fraction of the essential matrix's inliers.
        seed: random seed.
    """

    threshold_rad: float = bounded(math.radians(0.2), gt=0, lt=math.pi)
    max_iterations: int = bounded(2000, ge=1)
    confidence: float = bounded(0.999, gt=0, lt=1)
    min_inliers: int = bounded(15, ge=1)
    rotation_only_ratio: float = bounded(0.9, gt=0, le=1)
    seed: int = bounded(0, ge=0)


@dataclass
class RelativeMotion:
    """Result of :func:`estimate_relative_motion`.

    Attributes:
        rig2_from_rig1: (4, 4), unit translation (zero when not reliable).
        essential: (3, 3) essential matrix (refitted on the inliers).
        inliers: (N,) bool mask.
        translation_reliable: False for (near) pure rotations and standstill.
        iterations: RANSAC iterations run.
    """

    rig2_from_rig1: np.ndarray
    essential: np.ndarray
    inliers: np.ndarray
    translation_reliable: bool
    iterations: int


def estimate_relative_motion(
    rays1: np.ndarray, rays2: np.ndarray, config: RansacConfig | None = None
) -> RelativeMotion:
    """Relative motion of view 2 from view 1 with RANSAC over eight-point samples.

    Raises:
        ReconstructionError: fewer than ``min_inliers`` consistent pairs.
    """
    cfg = config or RansacConfig()
    r1, r2 = _check_pairs(rays1, rays2)
    n = len(r1)
    if n < max(8, cfg.min_inliers):
        raise ReconstructionError(
            f"relative motion: only {n} correspondences (need {max(8, cfg.min_inliers)})"
        )
    rng = np.random.default_rng(cfg.seed)
    # Inliers: angular epipolar error below the threshold (compiled, one pass).
    sin_thr = math.sin(min(cfg.threshold_rad, 0.5 * math.pi))
    best_inl = np.zeros(n, bool)
    best_count = 0
    it, needed = 0, cfg.max_iterations
    while it < min(needed, cfg.max_iterations):
        it += 1
        sample = rng.choice(n, 8, replace=False)
        # eight_point on the sample and the inlier test, compiled (the same values).
        _, inl = sample_hypothesis(r1, r2, sample, sin_thr)
        count = int(inl.sum())
        if count > best_count and count >= 8:
            # Local optimisation (LO-RANSAC): refit on the inliers while they grow.
            for _ in range(5):
                _, inl_lo = sample_hypothesis(r1, r2, np.flatnonzero(inl), sin_thr)
                if inl_lo.sum() <= count:
                    break
                inl, count = inl_lo, int(inl_lo.sum())
        if count > best_count:
            best_inl, best_count = inl, count
            ratio = count / n
            denom = math.log(max(1e-12, 1.0 - ratio**8))
            needed = (
                int(math.ceil(math.log(1.0 - cfg.confidence) / denom))
                if denom < 0
                else cfg.max_iterations
            )
    if best_count < cfg.min_inliers:
        raise ReconstructionError(
            f"relative motion: only {best_count} of {n} correspondences agree on one motion"
        )
    # Refit on the inliers, twice (the inlier set may grow).
    inl = best_inl
    for _ in range(2):
        E, inl = sample_hypothesis(r1, r2, np.flatnonzero(inl), sin_thr)
        if inl.sum() < cfg.min_inliers:
            inl = best_inl
            E = eight_point(r1[inl], r2[inl])
            break
    T, _ = decompose_essential(E, r1[inl], r2[inl])
    # Rotation-only model: rays agree after a rotation alone.
    R0 = rotation_from_rays(r1[inl], r2[inl])
    rot_err = np.arccos(np.clip(np.einsum("ij,ij->i", r1 @ R0.T, r2), -1.0, 1.0))
    rot_inl = int(np.sum(rot_err[inl] < cfg.threshold_rad))
    reliable = rot_inl < cfg.rotation_only_ratio * int(inl.sum())
    if not reliable:
        T = make_transform(R0, np.zeros(3))
    return RelativeMotion(T, E, inl, reliable, it)
