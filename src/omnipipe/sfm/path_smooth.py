"""The rig's path across the pipe, smoothed over its neighbours along the axis.

A frame between two keyframes is resected on its own against the adjusted wall points
(:func:`omnipipe.sfm.adjust.resect_pending`): on a large pipe's far wall at 640x480 its
position across the axis scatters 0.1-0.2 mm from frame to frame (the robustness
bench's corrugated 963 mm run: 0.096 mm RMS across against 0.013 along). The robot
crawling inside the pipe is assumed to move sideways smoothly over a few tens of
millimetres of travel; a sideways jump larger than the scatter (an offset joint) is
kept. Each station's position is fitted, robustly, with a quadratic in the travel
over the stations within :data:`WINDOW_MM` of it (tricube weights, residuals beyond
:data:`OUTLIER_SIGMAS` sigmas down-weighted), and only the part of its offset from the
fit ACROSS the path is removed, at most :data:`MAX_SHIFT_SIGMAS` sigmas. The sigma is
the scatter's own, the typical size of a station's offset across the path from the
window's second differences (their median / sqrt(6): the trend's share of a second
difference is negligible over a few millimetres, and a sideways jump spoils only two
of them). Along the path nothing changes: step lengths, the stationary frames and the
run's scale stay the laser's, the wall's and the adjustment's; rotations are kept.
"""

from __future__ import annotations

import numpy as np

from omnipipe.sfm.types import SfmResult

# Stations within this travel (mm) of a station shape its fit.
WINDOW_MM = 25.0
# Fewer stations than this in the window: left as it is.
MIN_STATIONS = 5
# Reweighting passes and the residual (robust sigmas) beyond which a station is
# down-weighted (weight OUTLIER_SIGMAS * sigma / residual).
PASSES = 4
OUTLIER_SIGMAS = 2.0
# A station moves across the path at most this many of its window's robust sigmas.
MAX_SHIFT_SIGMAS = 3.0
# Floor of that sigma (mm): a path without scatter is left as it is.
SIGMA_FLOOR_MM = 1e-6
# Stations fitted at once (memory: CHUNK x the widest window x 3 x 3 floats).
CHUNK = 256


def smooth_across(positions: np.ndarray) -> np.ndarray:
    """(S, 3) station positions (mm, in path order) with their offsets across the path
    from the local robust quadratic fit removed (see the module docstring); (S, 3)."""
    p = np.asarray(positions, float)
    out = p.copy()
    if len(p) < MIN_STATIONS:
        return out
    s = np.r_[0.0, np.cumsum(np.linalg.norm(np.diff(p, axis=0), axis=1))]
    lo = np.searchsorted(s, s - WINDOW_MM, "left")
    hi = np.searchsorted(s, s + WINDOW_MM, "right")
    second = np.r_[np.nan, _second_differences(p), np.nan]  # per station; none at the ends
    width = int((hi - lo).max())
    for first in range(0, len(p), CHUNK):
        rows = np.arange(first, min(first + CHUNK, len(p)))
        out[rows] += _shifts(p, s, second, rows, lo[rows], hi[rows], width)
    return out


def _shifts(
    p: np.ndarray,
    s: np.ndarray,
    second: np.ndarray,
    rows: np.ndarray,
    lo: np.ndarray,
    hi: np.ndarray,
    width: int,
) -> np.ndarray:
    """(R, 3) the shifts across the path of the stations ``rows`` (R,), each fitted over
    the stations lo..hi-1 of its window (``width`` the widest window); zero where a
    window holds fewer than :data:`MIN_STATIONS`."""
    j = lo[:, None] + np.arange(width)[None, :]
    valid = j < hi[:, None]
    j = np.minimum(j, len(p) - 1)
    x = np.where(valid, s[j] - s[rows][:, None], 0.0)
    tricube = np.where(valid, (1.0 - (np.abs(x) / (WINDOW_MM * (1 + 1e-9))) ** 3) ** 3, 0.0)
    # The scatter's scale from the window's second differences across the path: a real
    # sideways move spoils two of them, not the median.
    with np.errstate(all="ignore"):
        d2 = np.where(valid, second[j], np.nan)
        counted = np.isfinite(d2).any(axis=1)
        sigma = np.zeros(len(rows))
        sigma[counted] = np.nanmedian(d2[counted], axis=1) / np.sqrt(6.0)
    sigma = np.maximum(sigma, SIGMA_FLOOR_MM)
    design = np.stack([x * x, x, np.ones_like(x)], axis=2)  # (R, M, 3): the fit at s_i is the last
    robust = np.ones_like(x)
    pts = p[j]
    for _ in range(PASSES):
        w = tricube * robust
        weighted = np.swapaxes(design * w[:, :, None], 1, 2)  # (R, 3, M)
        coef = np.linalg.solve(weighted @ design + 1e-12 * np.eye(3), weighted @ pts)  # (R, 3, 3)
        res = np.linalg.norm(pts - design @ coef, axis=2)
        robust = np.minimum(1.0, OUTLIER_SIGMAS * sigma[:, None] / np.maximum(res, 1e-12))
    direction = coef[:, 1] / np.maximum(np.linalg.norm(coef[:, 1], axis=1, keepdims=True), 1e-12)
    shift = coef[:, 2] - p[rows]
    shift -= np.sum(shift * direction, axis=1, keepdims=True) * direction
    norm = np.linalg.norm(shift, axis=1)
    shift *= np.minimum(1.0, MAX_SHIFT_SIGMAS * sigma / np.maximum(norm, 1e-12))[:, None]
    shift[valid.sum(axis=1) < MIN_STATIONS] = 0.0
    return shift


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
