"""A step's length judged with its neighbours: the robot's gait over a window of steps.

The earthworm robot advances in strokes of similar length at a similar pace, so the
length per moving frame of neighbouring keyframe steps is alike (within the stroke's
velocity profile and the gait's jitter). A step measured by one source only (the
feature depths on the light-section wall while the laser's consensus peaks are
ambiguous, :data:`omnipipe.sfm.scale_check.FEATURE_ONLY`) is confirmed when its pace
agrees with the trusted steps around it, and stays unreliable otherwise: a wrong
course (one brick, tile or corrugation period off) changes the pace by the period over
the step, far more than the gait does.

Conventions: lengths in mm; a step's pace is its length over the moving frames it
spans (frames the stationary test took for standstills do not count).
"""

from __future__ import annotations

import itertools
import math

import numpy as np

# Steps on either side whose pace the window compares.
WINDOW_STEPS = 4
# Fewest trusted steps in the window for a judgement.
MIN_NEIGHBOURS = 2
# Largest |log(pace / the window's median pace)| of a confirmed step: 0.3 (35 %). The
# random family's strokes vary by up to +-20 % and a keyframe step may cover the slow
# start or end of a stroke; a brick or tile course off changes a step by its period.
GAIT_AGREE_LOG = 0.3


def moving_counts(moved: np.ndarray, frames: list[int]) -> np.ndarray:
    """(K-1,) moving frames each keyframe step spans: frames a+1..b of step a -> b with
    ``moved`` (N,) True (at least 1)."""
    m = np.asarray(moved, bool)
    return np.array(
        [max(int(m[a + 1 : b + 1].sum()), 1) for a, b in itertools.pairwise(frames)],
        int,
    )


def window_pace(
    k: int, lengths: np.ndarray, trusted: np.ndarray, counts: np.ndarray
) -> tuple[float, int]:
    """The median pace (mm per moving frame) of the trusted steps within
    :data:`WINDOW_STEPS` of step k (k excluded), and how many there were (NaN, n with
    fewer than :data:`MIN_NEIGHBOURS`)."""
    lo, hi = max(k - WINDOW_STEPS, 0), min(k + WINDOW_STEPS + 1, len(lengths))
    idx = [j for j in range(lo, hi) if j != k and trusted[j] and np.isfinite(lengths[j]) and lengths[j] > 0]
    if len(idx) < MIN_NEIGHBOURS:
        return math.nan, len(idx)
    return float(np.median(lengths[idx] / counts[idx])), len(idx)


def gait_agrees(k: int, length: float, lengths: np.ndarray, trusted: np.ndarray, counts: np.ndarray) -> str:
    """Why step k's ``length`` (mm) agrees with the window's pace ("" when it does not,
    or when the window cannot tell)."""
    pace, n = window_pace(k, lengths, trusted, counts)
    if not math.isfinite(pace) or not (length > 0):
        return ""
    mine = length / counts[k]
    if abs(math.log(mine / pace)) > GAIT_AGREE_LOG:
        return ""
    return (
        f"its pace {mine:.2f} mm/frame agrees with the {n} steps around it "
        f"({pace:.2f} mm/frame)"
    )
