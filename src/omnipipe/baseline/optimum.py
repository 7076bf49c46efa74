"""Baseline optimisation (paper Sec. IV, Eq. 6-9, Fig. 9).

A wall at radial distance d from the mirror axis is measured on the laser plane
z = -l (l: the baseline between the mirror focus and the laser). Its image radius is
r(l, d) = |project((d, 0, -l))| (Eq. 1-3 inverted). The light section inverts that
relation at fixed l, so an image error delta_r becomes a depth error

    delta_d = |dd/dr| delta_r = delta_r / |dr/dd|          (the role of Eq. (6))

with r(l, d) the image radius of Eq. (7) and Eq. (8), and delta_r the quantisation
error of Eq. (9): half a pixel in each direction, sqrt((s_H/2)^2 + (s_V/2)^2), i.e.
sqrt(0.5) px for square pixels. The typeset
Eq. 6-8 are garbled in the paper text; this module derives dr/dd in closed form
from the camera model (docs/baseline.md) and tests it against finite differences.
Since r is proportional to f, the error rate delta_d / d at the optimum depends on
the mirror alone: the optimal l is proportional to d.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from scipy.optimize import minimize_scalar

from omnipipe.config import bounded
from omnipipe.errors import ConfigError
from omnipipe.rig import Mirror


def image_radius(l_mm: np.ndarray, d_mm: np.ndarray, mirror: Mirror, f_px: float) -> np.ndarray:
    """Image radius r (px) of a wall point at radial distance d on the plane z = -l.

    Closed form of the camera model: with the unit direction (sin a, -cos a) of the
    point (tan a = d / l), the mirror point is t (sin a, -cos a), t = a^2/(b + c cos a),
    and r = f t sin a / (2c - t cos a).
    """
    a, b, c = mirror.a, mirror.b, mirror.c
    l_mm = np.asarray(l_mm, float)
    d_mm = np.asarray(d_mm, float)
    norm = np.hypot(l_mm, d_mm)
    sin_a, cos_a = d_mm / norm, l_mm / norm
    t = a * a / (b + c * cos_a)
    return f_px * t * sin_a / (2 * c - t * cos_a)


def dr_dd(l_mm: np.ndarray, d_mm: np.ndarray, mirror: Mirror, f_px: float) -> np.ndarray:
    """Analytic derivative of :func:`image_radius` with respect to d (px per mm).

    With u = cos a: r(u) = f a^2 sqrt(1-u^2) / (2c(b + c u) - a^2 u), du/dd = -u (1-u^2) / d
    ... differentiated by the chain rule below.
    """
    a, b, c = mirror.a, mirror.b, mirror.c
    l_mm = np.asarray(l_mm, float)
    d_mm = np.asarray(d_mm, float)
    norm = np.hypot(l_mm, d_mm)
    u = l_mm / norm  # cos a
    s = d_mm / norm  # sin a
    den = 2 * c * b + (2 * c * c - a * a) * u
    # r = f a^2 s / den;  ds/dd = u^2 / norm;  du/dd = -u s / norm
    ds = u * u / norm
    du = -u * s / norm
    return f_px * a * a * (ds * den - s * (2 * c * c - a * a) * du) / den**2


def quantisation_error_px(pixel_pitch_h: float = 1.0, pixel_pitch_v: float = 1.0) -> float:
    """Eq. (9): sqrt((s_H/2)^2 + (s_V/2)^2) in units of the pixel pitch (sqrt(0.5) px for square pixels)."""
    return math.sqrt((0.5 * pixel_pitch_h) ** 2 + (0.5 * pixel_pitch_v) ** 2) / math.sqrt(
        pixel_pitch_h * pixel_pitch_v
    )


def error_rate(
    l_mm: np.ndarray, d_mm: np.ndarray, mirror: Mirror, f_px: float, delta_r_px: float | None = None
) -> np.ndarray:
    """Depth error rate delta_d / d of the light section at baseline l and wall distance d."""
    dr = quantisation_error_px() if delta_r_px is None else delta_r_px
    return dr / np.abs(dr_dd(l_mm, d_mm, mirror, f_px)) / np.asarray(d_mm, float)


def optimal_baseline(d_mm: float, mirror: Mirror, f_px: float = 1000.0) -> float:
    """Baseline l (mm) that minimises the error rate for a wall at d (mm)."""
    if not d_mm > 0:
        raise ConfigError("distance", f"must be > 0, got {d_mm}")
    res = minimize_scalar(
        lambda l: float(error_rate(l, d_mm, mirror, f_px)),
        bounds=(1e-3 * d_mm, 20.0 * d_mm),
        method="bounded",
        options={"xatol": 1e-6 * d_mm},
    )
    return float(res.x)


@dataclass(frozen=True)
class BaselineConfig:
    """Inputs of the baseline study.

    Attributes:
        mirror: the hyperboloid.
        f_px: image distance f (px); scales the error, not the optimum.
        distances_mm: wall distances d to optimise for.
        delta_r_px: image quantisation error (Eq. 9), sqrt(0.5) px by default.
    """

    mirror: Mirror
    f_px: float = bounded(gt=0)
    distances_mm: tuple[float, ...] = bounded((100.0, 200.0, 300.0), gt=0)
    delta_r_px: float = bounded(default_factory=quantisation_error_px, gt=0)


@dataclass
class BaselineResult:
    """Optimal baselines and the Fig. 9 curves.

    Attributes:
        optimal_mm: {d: l_opt} (mm).
        l_mm: (M,) baselines of the curves.
        rates: {d: (M,) error rate delta_d / d}.
    """

    optimal_mm: dict[float, float]
    l_mm: np.ndarray
    rates: dict[float, np.ndarray]


def run(config: BaselineConfig) -> BaselineResult:
    """Optimal baseline per wall distance, and Fig. 9's error-rate curves."""
    opt = {d: optimal_baseline(d, config.mirror, config.f_px) for d in config.distances_mm}
    l = np.linspace(5.0, 2.0 * max(config.distances_mm), 400)
    rates = {
        d: error_rate(l, d, config.mirror, config.f_px, config.delta_r_px)
        for d in config.distances_mm
    }
    return BaselineResult(opt, l, rates)


def plot_fig9(result: BaselineResult, path: str) -> None:
    """Fig. 9: error rate against baseline for each wall distance (PNG)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(6.4, 4.2))
    for d, rate in result.rates.items():
        line = ax.plot(result.l_mm, 100 * rate, label=f"d = {d:g} mm")[0]
        lo = result.optimal_mm[d]
        ax.axvline(lo, color=line.get_color(), ls=":", lw=1)
    ax.set_xlabel("baseline l (mm)")
    ax.set_ylabel("error rate Δd/d (%)")
    ax.set_ylim(0, min(ax.get_ylim()[1], 4 * max(100 * r.min() for r in result.rates.values())))
    ax.grid(alpha=0.3)
    ax.legend()
    ax.set_title("Depth error against baseline (paper Fig. 9)")
    fig.savefig(path, dpi=120, bbox_inches="tight")
    plt.close(fig)
