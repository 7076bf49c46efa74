"""The rig's path across the pipe, smoothed over its neighbours along the axis.

A frame between two keyframes is resected on its own against the adjusted wall points
(:func:`omnipipe.sfm.adjust.resect_pending`): on a large pipe's far wall at 640x480 its
position across the axis scatters 0.1-0.2 mm from frame to frame (the robustness
bench's corrugated 963 mm run: 0.096 mm RMS across against 0.013 along), while the
robot crawling inside the pipe moves sideways smoothly over tens of millimetres of
travel. Each station's position is therefore fitted, robustly, with a quadratic in the
travel over the stations within :data:`WINDOW_MM` of it (tricube weights, residuals
beyond :data:`OUTLIER_SIGMAS` sigmas down-weighted), and only the part of its offset
from the fit ACROSS the path is removed, at most :data:`MAX_SHIFT_SIGMAS` sigmas (a
real sideways move larger than the noise, e.g. over an offset joint, is kept). The
sigma is the scatter's own, from the window's second differences across the path
(median size / sqrt(6): the trend's share of a second difference is negligible over
a few millimetres, and a sideways move spoils only two of them). Along the path nothing changes: step lengths, the stationary frames
and the run's scale are the laser's, the wall's and the adjustment's.
"""

from __future__ import annotations

import numpy as np

from omnipipe.sfm.types import SfmResult

# Stations within this travel (mm) of a station shape its fit.
WINDOW_MM = 25.0
# Polynomial degree of the fit in the travel.
DEGREE = 2
# Fewer stations than this in the window: left as it is.
MIN_STATIONS = 5
# Reweighting passes and the residual (robust sigmas) beyond which a station is
# down-weighted (weight OUTLIER_SIGMAS * sigma / residual).
PASSES = 4
OUTLIER_SIGMAS = 2.0
# A station moves across the path at most this many of its window's robust sigmas.
MAX_SHIFT_SIGMAS = 3.0


def smooth_across(positions: np.ndarray) -> np.ndarray:
    """(S, 3) station positions (mm, in path order) with their offsets across the path
    from the local robust quadratic fit removed (see the module docstring); (S, 3)."""
    p = np.asarray(positions, float)
    s = np.r_[0.0, np.cumsum(np.linalg.norm(np.diff(p, axis=0), axis=1))]
    second = _second_differences(p)
    out = p.copy()
    for i in range(len(p)):
        idx = np.flatnonzero(np.abs(s - s[i]) <= WINDOW_MM)
        if len(idx) < MIN_STATIONS:
            continue
        # The scatter's scale from the window's second differences across the path: a
        # real sideways move spoils two of them, not the median.
        inner = idx[(idx > 0) & (idx < len(p) - 1)]
        sigma = float(np.median(second[inner - 1])) / np.sqrt(6.0) + 1e-9 if len(inner) else 0.0
        x = s[idx] - s[i]
        design = np.vander(x, DEGREE + 1)  # columns x^2, x, 1: the fit at s_i is the last
        tricube = (1.0 - (np.abs(x) / (WINDOW_MM * (1 + 1e-9))) ** 3) ** 3
        robust = np.ones(len(idx))
        for _ in range(PASSES):
            w = np.sqrt(tricube * robust)[:, None]
            coef, *_ = np.linalg.lstsq(design * w, p[idx] * w, rcond=None)
            res = np.linalg.norm(p[idx] - design @ coef, axis=1)
            robust = np.minimum(1.0, OUTLIER_SIGMAS * sigma / np.maximum(res, 1e-12))
        direction = coef[-2] / (np.linalg.norm(coef[-2]) + 1e-12)
        shift = coef[-1] - p[i]
        shift -= (shift @ direction) * direction
        norm = float(np.linalg.norm(shift))
        if norm > MAX_SHIFT_SIGMAS * sigma:
            shift *= MAX_SHIFT_SIGMAS * sigma / max(norm, 1e-12)
        out[i] = p[i] + shift
    return out


def _second_differences(p: np.ndarray) -> np.ndarray:
    """(S - 2,) the size (mm) of each inner station's second difference across the
    path, ``p[i-1] - 2 p[i] + p[i+1]`` without its part along the path."""
    if len(p) < 3:
        return np.zeros(0)
    d2 = p[:-2] - 2.0 * p[1:-1] + p[2:]
    along = p[2:] - p[:-2]
    along /= np.maximum(np.linalg.norm(along, axis=1, keepdims=True), 1e-12)
    d2 -= np.sum(d2 * along, axis=1, keepdims=True) * along
    return np.linalg.norm(d2, axis=1)


def smooth_path(result: SfmResult) -> None:
    """``result``'s registered frames moved across the path by :func:`smooth_across`
    (in place); frames sharing one position (a station) move together, as one sample."""
    frames = np.flatnonzero(result.registered)
    if len(frames) < MIN_STATIONS:
        return
    pos = result.world_from_rig[frames, :3, 3]
    new = np.r_[True, np.linalg.norm(np.diff(pos, axis=0), axis=1) > 1e-9]
    sample = np.cumsum(new) - 1
    smoothed = smooth_across(pos[new])
    result.world_from_rig[frames, :3, 3] = pos + (smoothed - pos[new])[sample]
