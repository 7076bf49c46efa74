"""What the feature finders (:mod:`.features`, :mod:`.joints`) share: their settings, and
the rings in pipe coordinates with each point's deviation from its ring's wall profile.

Per ring, a robust Fourier profile (order 2: the ring's offset and ovality) is fitted; a
ring whose mean radius stands out from its neighbours' running median (the ring lies in
a joint's gap) takes the neighbours' mean radius instead.
"""

from __future__ import annotations

import math
from concurrent.futures import Executor
from dataclasses import dataclass

import numpy as np

from omnipipe.analysis.ring_spans import RingGroups
from omnipipe.analysis.wall_profile import fit_wall_profile, fourier_design
from omnipipe.config import bounded
from omnipipe.executor import InlineExecutor, chunks, ordered_map


@dataclass(frozen=True)
class FeatureConfig:
    """Feature finder settings.

    Attributes:
        min_depth_mm: smallest outward step counted as a gap or an opening.
        noise_factor: the threshold is at least this many noise sigmas.
        joint_noise_factor: the same for a joint's gap (which must also cover most of
            the circumference: noise does not).
        joint_coverage: a group deep over this fraction of the angles at which rings
            sample its axial band is a joint.
        joint_min_rings: a gap seen on part of the circumference only (every ring
            crossing it along a slant) needs its candidates on this many rings.
        joint_link_mm: candidates further apart along the axis (and than 1.5 ring
            spacings) belong to different joints.
        joint_max_gap_mm: a wider deep band is not a joint's gap.
        joint_offset_min_mm: a joint no ring's samples fell in is found by its offset
            alone: the centreline's sideways step between two rings of at least this
            and ``joint_offset_factor`` x the run's median step (on the bench's 34
            true-motion captures: offset joints stepped 5.8-8.1 mm, other steps up to
            2.4 mm).
        joint_offset_factor: see ``joint_offset_min_mm``.
        lateral_reach_rel: a narrower cluster reaching this fraction of the diameter
            beyond the wall is a lateral (the branch wall seen through the hole).
        lateral_reach_thr: a cluster reaching this many thresholds beyond the wall, and
            ``lateral_reach_width`` x its widest chord, is a lateral too (a small branch
            is seen only a little way in; on the bench's 34 true-motion captures at
            400x300, small openings reached 2.2-5.4 thresholds and 0.7-0.9 chords, the
            other clusters at most 1.5 thresholds).
        lateral_reach_width: see ``lateral_reach_thr`` (a dent is far wider than deep).
        lateral_gap_mm: a ring's stretch without returns (the light lost in a branch)
            at least this long around the wall (and 4 sample steps) is an opening's
            where the other rings of the run sample those angles (:mod:`.openings`).
        lateral_gap_rings: rings such stretches of one opening need.
        lateral_max_length_rel: the rings without returns there span at most this
            fraction of the diameter along the axis (a branch at 45 deg, 0.7 D wide).
        min_points: points a cluster needs.
        margin_mm: wall points this close to a gap or an opening are excluded too
            (the edges' ramps and the ring's blur).
        window_mm: running-median window of the rings' mean radius; offset window.
    """

    min_depth_mm: float = bounded(1.5, ge=0)
    noise_factor: float = bounded(6.0, gt=0)
    joint_noise_factor: float = bounded(3.5, gt=0)
    joint_coverage: float = bounded(0.6, gt=0, le=1)
    joint_min_rings: int = bounded(5, ge=2)
    joint_link_mm: float = bounded(3.0, gt=0)
    joint_max_gap_mm: float = bounded(30.0, gt=0)
    joint_offset_min_mm: float = bounded(3.0, gt=0)
    joint_offset_factor: float = bounded(4.0, gt=0)
    lateral_reach_rel: float = bounded(0.08, gt=0, le=1)
    lateral_reach_thr: float = bounded(2.0, gt=0)
    lateral_reach_width: float = bounded(0.5, gt=0)
    lateral_gap_mm: float = bounded(6.0, gt=0)
    lateral_gap_rings: int = bounded(2, ge=1)
    lateral_max_length_rel: float = bounded(1.0, gt=0)
    min_points: int = bounded(8, ge=1)
    margin_mm: float = bounded(3.0, ge=0)
    window_mm: float = bounded(60.0, gt=0)


@dataclass(frozen=True)
class Rings:
    """The points in pipe coordinates, grouped by ring, and their deviation from it."""

    sigma: np.ndarray
    rho: np.ndarray
    theta: np.ndarray
    frame: np.ndarray
    ring_of: np.ndarray
    ring_sigma: np.ndarray
    dev: np.ndarray
    noise: float
    axial_blur_mm: float = 0.0  # the light section's Gaussian sigma along the axis (mm; 0: none)


def ring_deviations(
    config: FeatureConfig,
    sigma: np.ndarray,
    rho: np.ndarray,
    theta: np.ndarray,
    frame: np.ndarray,
    rings: np.ndarray,
    executor: Executor | None = None,
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(N,) each point's outward deviation from its ring's wall profile (a ring lying in
    a gap takes its neighbours' mean radius), (R,) the rings' axial positions and (R,)
    True for rings raised above their neighbours (lying in a gap). The rings' profile
    fits on ``executor`` (:mod:`omnipipe.executor`, a few rings a task; None: here; the
    result is the same)."""
    # Each ring's points (ascending, as frame == k selects them), made when needed: no
    # index of every point held (omnipipe.analysis.ring_spans).
    groups = RingGroups(frame, rings)
    ex = executor or InlineExecutor()
    # Each task's rings gathered only when it is sent (ordered_map keeps a few in flight).
    sent = ([(theta[on], rho[on], sigma[on]) for on in (groups[i] for i in part)] for part in chunks(len(rings), ex))
    fits = [fit for task in ordered_map(ex, _ring_fits, sent) for fit in task]
    coef = np.array([c for c, _ in fits]).reshape(len(fits), 5)
    rs = np.array([s for _, s in fits])
    c0 = coef[:, 0].copy()
    for i in range(len(rings)):
        nb = np.abs(rs - rs[i]) <= config.window_mm
        c0[i] = float(np.median(coef[nb, 0]))
    dev = np.zeros(len(sigma))
    raised = np.zeros(len(rings), bool)
    noise0 = 1.4826 * float(np.median(np.abs(coef[:, 0] - c0))) + 1e-9
    peak = _local_peaks(coef[:, 0], rs, config.min_depth_mm, config.joint_max_gap_mm)
    peak = [p if p is not None else q for p, q in zip(peak, _ramp_peaks(coef[:, 0], rs, config.min_depth_mm), strict=True)]
    # A running median lags a taper by up to a ring spacing's drop: a ring counts as
    # raised only above the lines both sides' rings give it too.
    _, hi = _wall_level(coef[:, 0], rs, config.window_mm)
    for i, on in enumerate(groups):
        c = coef[i].copy()
        off = abs(c[0] - c0[i]) > max(config.min_depth_mm, config.noise_factor * noise0)
        if peak[i] is not None:
            raised[i] = True
            c[0] = peak[i]
        elif off and (c[0] < c0[i] or c[0] - hi[i] > config.min_depth_mm):
            raised[i] = c[0] > c0[i]
            c[0] = c0[i]
        dev[on] = rho[on] - fourier_design(theta[on], 2) @ c
    return dev, rs, raised


def _ring_fits(rings: list[tuple[np.ndarray, np.ndarray, np.ndarray]]) -> list[tuple[np.ndarray, float]]:
    """Each ring's (theta rad, rho mm, sigma mm of its points) robust Fourier profile
    (order 2 from 20 points, else 0; soft-L1 at 0.5 mm), as (5,) coefficients zero-padded,
    and its axial position (the median sigma, mm): one task of :func:`ring_deviations`."""
    out = []
    for theta, rho, sigma in rings:
        c = fit_wall_profile(theta, rho, 2 if len(theta) >= 20 else 0, 0.5)
        out.append((np.pad(c, (0, 5 - len(c))), float(np.median(sigma))))
    return out


def robust_sine_fit(
    sigma: np.ndarray, phi: np.ndarray, passes: int, k_sigmas: float, floor_mm: float
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The plane sigma = p0 + p1 cos phi + p2 sin phi (a ring's or a gap's: an axial
    position, mm, that varies once round the pipe, angle phi rad) fitted to (M,)
    samples by least squares ``passes`` times, each time without the samples beyond
    max(``k_sigmas`` robust sigmas (1.4826 x the median absolute residual of the samples
    kept), ``floor_mm``) of the last fit. ((3,) p of the last fit, (M,) every sample's
    residual to it, (M,) the samples within the bound of those residuals)."""
    A = np.column_stack([np.ones(len(phi)), np.cos(phi), np.sin(phi)])
    keep = np.ones(len(phi), bool)
    for _ in range(passes):
        p, *_ = np.linalg.lstsq(A[keep], sigma[keep], rcond=None)
        res = sigma - A @ p
        keep = np.abs(res) <= max(k_sigmas * 1.4826 * float(np.median(np.abs(res[keep]))), floor_mm)
    return p, res, keep


def _side_level(c0: np.ndarray, rs: np.ndarray, nb: np.ndarray, at: float) -> float:
    """The mean radius the rings ``nb`` (on one side) give at ``at``: their Theil-Sen
    line (median of the pairwise slopes) there; one ring: its radius."""
    if len(nb) == 1:
        return float(c0[nb[0]])
    a, b = np.triu_indices(len(nb), 1)
    dz = rs[nb][b] - rs[nb][a]
    ok = np.abs(dz) > 1e-6
    slope = float(np.median((c0[nb][b] - c0[nb][a])[ok] / dz[ok])) if ok.any() else 0.0
    return float(np.median(c0[nb] + slope * (at - rs[nb])))


def _wall_level(c0: np.ndarray, rs: np.ndarray, window_mm: float) -> tuple[np.ndarray, np.ndarray]:
    """(R,) low and (R,) high bounds of each ring's mean radius as the rings either side
    within ``window_mm`` give it: the lower and higher of the two sides' lines carried
    to the ring (:func:`_side_level`; one side only at the run's ends; none: the ring's
    own). A ring in a joint's gap stands above both; one on a taper (whose rings a
    running median lags by up to a ring spacing's drop) or at a taper's kink (above a
    line through both sides) does not."""
    lo, hi = c0.copy(), c0.copy()
    for i in range(len(c0)):
        near = (np.abs(rs - rs[i]) <= window_mm) & (np.arange(len(c0)) != i)
        sides = [np.flatnonzero(near & (rs < rs[i])), np.flatnonzero(near & (rs >= rs[i]))]
        got = [_side_level(c0, rs, nb, float(rs[i])) for nb in sides if len(nb)]
        if got:
            lo[i], hi[i] = min(got), max(got)
    return lo, hi


def _local_peaks(
    c0: np.ndarray, rs: np.ndarray, min_depth_mm: float, max_width_mm: float = math.inf, max_rings: int = 6
) -> list[float | None]:
    """Per ring (ordered along the axis by ``rs``), the mean radius its block's two
    neighbours give at its position (linear between them) if the ring stands more than
    ``min_depth_mm`` above both of them, else None. A block is up to ``max_rings``
    consecutive rings within ``max_width_mm`` along the axis, each standing so (the rings
    lying in a joint's gap: one in a narrow gap, several in a wide one crossed by tilted
    rings, whose running median lags a taper or whose raised rings inflate the median's
    scatter; bench seed 13: four rings 16 mm apart partly in a 10 mm gap); the widest
    block first (a ring of it may stand above its block neighbours alone too). Only
    blocks with a neighbour on both sides; a taper or a bend raises no ring above both
    ends of its block."""
    out: list[float | None] = [None] * len(c0)
    order = np.argsort(rs)
    for m in range(max_rings, 0, -1):  # the widest block first: its rings stand together
        for j in range(1, len(order) - m):
            a, b = order[j - 1], order[j + m]
            block = order[j : j + m]
            if any(out[i] is not None for i in block) or rs[block[-1]] - rs[block[0]] > max_width_mm:
                continue
            if float(np.min(c0[block])) - max(c0[a], c0[b]) > min_depth_mm:
                for i in block:
                    f = (rs[i] - rs[a]) / max(rs[b] - rs[a], 1e-9)
                    out[i] = float(c0[a] + f * (c0[b] - c0[a]))
    return out


def raised_blocks(raised: np.ndarray, ring_sigma: np.ndarray) -> np.ndarray:
    """(R,) True for the raised rings whose neighbour along the axis is raised too."""
    order = np.argsort(ring_sigma)
    r = raised[order]
    nb = np.zeros(len(r), bool)
    nb[1:] |= r[:-1]
    nb[:-1] |= r[1:]
    out = np.zeros(len(raised), bool)
    out[order] = r & nb
    return out


def _ramp_peaks(c0: np.ndarray, rs: np.ndarray, min_depth_mm: float) -> list[float | None]:
    """Per ring (ordered along the axis by ``rs``), its two neighbours' chord at its
    position if the ring stands more than ``min_depth_mm`` above that chord and above
    the line its two nearer rings on one side give it (a ring in a joint's gap on a
    reducer's ramp: bench seed 30, whose upstream rings lie before the ramp), else None.
    A taper's kink raises its ring above the chord but onto both sides' lines."""
    out: list[float | None] = [None] * len(c0)
    o = np.argsort(rs)
    for j in range(2, len(o) - 2):
        i, a, b = o[j], o[j - 1], o[j + 1]
        chord = float(c0[a] + (rs[i] - rs[a]) / max(rs[b] - rs[a], 1e-9) * (c0[b] - c0[a]))
        sides = []
        for p, q in ((o[j - 2], a), (b, o[j + 2])):
            slope = (c0[q] - c0[p]) / max(abs(rs[q] - rs[p]), 1e-9) * np.sign(rs[q] - rs[p])
            sides.append(float(c0[q] + slope * (rs[i] - rs[q])))
        if c0[i] - chord > min_depth_mm and c0[i] - min(sides) > min_depth_mm:
            out[i] = chord
    return out
