"""The wall as the defect search reads it, and each ring's wall profile.

:class:`WallSamples` holds the wall points in unrolled pipe coordinates (axial position
and arc length around the pipe, mm; radial deviation from the fitted wall, mm, + out of
the pipe; ring index), optionally with the order sorting them along the pipe
(:func:`with_axial_order`) so that an axial window is a slice (:func:`axial_range`).
:func:`fit_wall_profile` is the robust Fourier fit of one ring's radius over its angle
(radians), :func:`fourier_design` its design matrix.
"""

from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np

from omnipipe.spill import is_on_disk, on_disk


@dataclass(frozen=True)
class WallSamples:
    """Wall points in unrolled pipe coordinates.

    Attributes:
        sigma_mm: (N,) axial position (contract convention).
        arc_mm: (N,) arc length around the pipe, angle x reference radius, in [0, circumference).
        deviation_mm: (N,) radial deviation from the fitted wall (+ out of the pipe).
        ring: (N,) ring (station) index of each point.
        circumference_mm: 2 pi x reference radius.
        ring_travel_mm: (R,) distance the robot travelled from the first frame to the
            frame of ring r (indexed by ring), or None: the axial position's distance from
            the origin stands in. Position errors of the camera motion grow with it.
        axial_order: (N,) the sample indices sorting ``sigma_mm`` (stable), or None:
            :func:`.defects.find_defects` sorts them once (:func:`with_axial_order`), and each
            candidate's window is then a slice of that order (:func:`axial_range`).
    """

    sigma_mm: np.ndarray
    arc_mm: np.ndarray
    deviation_mm: np.ndarray
    ring: np.ndarray
    circumference_mm: float
    ring_travel_mm: np.ndarray | None = None
    axial_order: np.ndarray | None = None


def with_axial_order(samples: WallSamples) -> WallSamples:
    """``samples`` with :attr:`WallSamples.axial_order` (intp: ``np.searchsorted`` copies
    any other index type whole at each call; in the run's scratch when the axial
    positions are, :mod:`omnipipe.spill`)."""
    if samples.axial_order is not None:
        return samples
    order = np.argsort(samples.sigma_mm, kind="stable")
    return replace(samples, axial_order=on_disk(order) if is_on_disk(samples.sigma_mm) else order)


def axial_range(s: WallSamples, lo: float, hi: float) -> np.ndarray:
    """Ascending indices of the samples whose axial position lies in [lo, hi] (mm),
    widened by a margin far above rounding (a superset: each caller applies its own exact
    test to these samples only); every sample's without :attr:`WallSamples.axial_order`."""
    order = s.axial_order
    if order is None:
        return np.arange(len(s.sigma_mm))
    pad = 1e-9 * (1.0 + abs(lo) + abs(hi))
    a = int(np.searchsorted(s.sigma_mm, lo - pad, side="left", sorter=order))
    b = int(np.searchsorted(s.sigma_mm, hi + pad, side="right", sorter=order))
    return np.sort(order[a:b])


def fit_wall_profile(
    theta: np.ndarray, rho: np.ndarray, order: int, loss_scale_mm: float
) -> np.ndarray:
    """Robust Fourier fit rho(theta) = c0 + sum_k (a_k cos k theta + b_k sin k theta).

    Order 1 absorbs a ring's offset from the fitted axis, order 2 an oval section. The
    loss is soft-L1 at ``loss_scale_mm`` (SciPy's ``least_squares(loss="soft_l1")``);
    the residuals are linear in the coefficients, so that loss is convex and its one
    minimum is found by iteratively reweighted least squares (weights
    1 / sqrt(1 + (r / scale)^2), until the coefficients move less than 1e-9 mm).

    Returns:
        (1 + 2 order,) coefficients [c0, a1, b1, a2, b2, ...].
    """
    A = fourier_design(theta, order)
    coef, *_ = np.linalg.lstsq(A, rho, rcond=None)
    if len(rho) <= A.shape[1] + 3:
        return coef
    for _ in range(200):
        r = (A @ coef - rho) / loss_scale_mm
        weighted = A * (1.0 / np.sqrt(1.0 + r * r))[:, None]
        try:
            new = np.linalg.solve(weighted.T @ A, weighted.T @ rho)
        except np.linalg.LinAlgError:  # a degenerate ring: keep the plain fit
            return coef
        done = float(np.max(np.abs(new - coef))) < 1e-9
        coef = new
        if done:
            break
    return coef


def fourier_design(theta: np.ndarray, order: int) -> np.ndarray:
    """(N, 1 + 2 order) design matrix of :func:`fit_wall_profile`."""
    cols = [np.ones_like(theta)]
    for k in range(1, order + 1):
        cols += [np.cos(k * theta), np.sin(k * theta)]
    return np.stack(cols, axis=1)
