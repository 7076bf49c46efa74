"""Each station's wall profile (:func:`station_profiles`: a robust Fourier fit of the
radius rho, mm, against the angle theta, rad, about the axis, per ring) and every point's
deviation from it (:class:`StationProfiles`), the rings' point indices
(:func:`ring_groups`) and the stations as :class:`.stations.Station` records
(:func:`station_list`).
"""

from __future__ import annotations

from collections.abc import Sequence
from concurrent.futures import Executor
from dataclasses import dataclass, field

import numpy as np

from omnipipe.analysis.defect_search import FeatureZone
from omnipipe.analysis.records import AnalysisConfig, section_config
from omnipipe.analysis.ring_spans import RingGroups
from omnipipe.analysis.stations import (
    Section,
    SectionConfig,
    Station,
    ring_cut,
    section_order,
    station_from_section,
)
from omnipipe.analysis.wall_profile import fit_wall_profile, fourier_design
from omnipipe.executor import InlineExecutor, chunks, ordered_map
from omnipipe.spill import zeros_on_disk


def station_list(stations: StationProfiles) -> list[Station]:
    """The stations of ``stations`` as :class:`.stations.Station` records (bias-corrected
    ovality; no shared terms, no water)."""
    return [
        station_from_section(a, sec, 0.0, 0.0)
        for a, sec in zip(stations.axial, stations.sections, strict=True)
    ]


@dataclass(frozen=True)
class StationProfiles:
    """Each station's wall profile (:func:`station_profiles`).

    Attributes:
        axial, diameter, diameter_sigma, ovality, ovality_sigma: (K,) per station with
            enough points (mm; ovality a fraction, NaN below the profile order 2).
        deviation: (N,) every point's deviation from its station's profile (mm; NaN on
            stations without enough points).
        rings: (K,) each station's ring (index into the analysis' rings).
    """

    axial: np.ndarray
    diameter: np.ndarray
    diameter_sigma: np.ndarray
    ovality: np.ndarray
    ovality_sigma: np.ndarray
    deviation: np.ndarray
    sections: tuple[Section, ...] = ()
    rings: np.ndarray = field(default_factory=lambda: np.zeros(0, int))


def _with_openings(theta: np.ndarray, axial: float, zones: Sequence[FeatureZone], radius: float) -> np.ndarray:
    """A ring's angles (rad) with the lateral openings it crosses filled in (at 0.5 deg
    steps): where the ring lost its light in a branch it is not cut by water."""
    fill = [theta]
    for z in zones:
        if z.arc_mm is not None and z.axial_from_mm <= axial <= z.axial_to_mm:
            c, h = z.arc_mm / radius, z.half_arc_mm / radius
            fill.append(np.linspace(c - h, c + h, max(int(np.degrees(2 * h) / 0.5), 2)))
    return np.concatenate(fill) if len(fill) > 1 else theta


def ring_groups(frame: np.ndarray, n_rings: int) -> Sequence[np.ndarray]:
    """(n_rings,) the indices of each ring's points, ascending (``frame == k`` for every k,
    each made when indexed: :class:`.ring_spans.RingGroups`, a binary search of the
    integrated run's ring-ordered ``frame`` or one stable sort of any other; no index of
    every point held)."""
    return RingGroups(frame, np.arange(n_rings))


@dataclass(frozen=True)
class _RingSamples:
    """One station's ring for its profile fit (:func:`_fit_ring`): its points' arrays
    (M,), in the ring's point order.

    Attributes:
        theta, rho, sigma: angle (rad), radius (mm) and axial coordinate (mm).
        exclude: True where the point is left out of the fit.
        lit: True where the point closes a cut (not stray), or None: every point.
    """

    theta: np.ndarray
    rho: np.ndarray
    sigma: np.ndarray
    exclude: np.ndarray
    lit: np.ndarray | None


@dataclass(frozen=True)
class _ProfileTask:
    """What every station's profile fit shares (:func:`_fit_task`): the settings, the
    lateral openings' ``zones`` and the wall's ``radius`` (mm)."""

    config: AnalysisConfig
    zones: tuple[FeatureZone, ...]
    radius: float


def _fit_task(sent: tuple[_ProfileTask, list[_RingSamples]]) -> list[tuple[float, Section, np.ndarray]]:
    """:func:`_fit_ring` of each ring of ``sent`` (one task on the executor)."""
    task, rings = sent
    sec_config = section_config(task.config)
    return [_fit_ring(task, sec_config, r) for r in rings]


def _fit_ring(
    task: _ProfileTask, sec_config: SectionConfig, ring: _RingSamples
) -> tuple[float, Section, np.ndarray]:
    """One station's wall profile: its axial position (mm, the median of its points'),
    its :class:`.stations.Section` and (M,) its points' deviations from it (mm)."""
    config = task.config
    use = np.flatnonzero(~ring.exclude)
    if len(use) < 12:
        use = np.arange(len(ring.exclude))
    th = ring.theta[use]
    axial = float(np.median(ring.sigma))
    # The cut (water) is where the ring has no points at all; the coverage for the
    # order is that of the points fitted (a defect's samples left out open a gap).
    lit = ring.theta if ring.lit is None else ring.theta[ring.lit]
    cut, coverage = ring_cut(_with_openings(lit, axial, task.zones, task.radius), sec_config)
    _, fitted_coverage = ring_cut(th, sec_config)
    order = section_order(cut, min(coverage, fitted_coverage), config.profile_order, sec_config)
    coef = fit_wall_profile(th, ring.rho[use], order, config.loss_scale_mm)
    A = fourier_design(th, order)
    res = ring.rho[use] - A @ coef
    spread = 1.4826 * float(np.median(np.abs(res)))
    inlier = np.abs(res) <= 4.0 * max(spread, 1e-6)
    cov = np.linalg.pinv(A[inlier].T @ A[inlier]) * spread**2
    deviation = ring.rho - fourier_design(ring.theta, order) @ coef
    return axial, Section(coef, cov, order, cut, coverage), deviation


def station_profiles(
    config: AnalysisConfig,
    groups: Sequence[np.ndarray],
    theta: np.ndarray,
    rho: np.ndarray,
    sigma: np.ndarray,
    ok_station: np.ndarray,
    exclude: np.ndarray,
    zones: Sequence[FeatureZone] = (),
    radius: float = 1.0,
    stray: np.ndarray | None = None,
    executor: Executor | None = None,
) -> StationProfiles:
    """Each station's wall profile (fitted without the ``exclude`` points) and every
    point's deviation from it; the stations' fits on ``executor``
    (:mod:`omnipipe.executor`, a few stations a task; None: here; the result is the same).

    The diameter's sigma is the fit's (A^T A)^-1 scaled by the ring's robust residual
    spread. A ring cut off by water (one gap) keeps the order while the wall above it
    covers ``cut_min_coverage_deg`` (:func:`.stations.section_order`). Ovality is
    2 |(a2, b2)| / c0, bias-corrected (:func:`.stations.station_from_section`).
    A lateral's opening (``zones`` with an arc, on the ``radius`` mm wall) is no cut:
    the light lost in the branch is not a water line; ``stray`` samples (off the wall
    in a cut: :attr:`.features.FeatureSearch.stray`) do not close a cut.
    """
    deviation = zeros_on_disk((len(exclude),), float)  # in the run's scratch (omnipipe.spill)
    deviation.fill(np.nan)
    ex = executor or InlineExecutor()
    rings = np.flatnonzero(ok_station)
    strays = stray is not None and len(stray) > 0

    def ring(k: int) -> _RingSamples:
        on = groups[k]
        return _RingSamples(theta[on], rho[on], sigma[on], exclude[on], ~stray[on] if strays else None)

    # Each task's rings gathered only when it is sent (ordered_map keeps a few in flight).
    task, parts = _ProfileTask(config, tuple(zones), float(radius)), chunks(len(rings), ex)
    sent = ((task, [ring(int(rings[i])) for i in part]) for part in parts)
    axial, sections = [], []
    for part, fits in zip(parts, ordered_map(ex, _fit_task, sent), strict=True):
        for i, (a, sec, dev) in zip(part, fits, strict=True):
            deviation[groups[int(rings[i])]] = dev
            axial.append(a)
            sections.append(sec)
    stations = [station_from_section(a, sec, 0.0, 0.0) for a, sec in zip(axial, sections, strict=True)]
    return StationProfiles(
        axial=np.array([st.axial_mm for st in stations]),
        diameter=np.array([st.diameter_mm for st in stations]),
        diameter_sigma=np.array([st.diameter_sigma_mm for st in stations]),
        ovality=np.array([st.ovality for st in stations]),
        ovality_sigma=np.array([st.ovality_sigma for st in stations]),
        deviation=deviation,
        sections=tuple(sections),
        rings=np.flatnonzero(ok_station),
    )
