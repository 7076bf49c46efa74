"""Cross-section measurements of real pipes (issue 30): each station's section, the
run's headline diameter and the section features (taper, bend, ovality, water).

Each station is one laser ring in the local pipe frame of the centreline (angle theta
around the axis from the transported reference x axis, distance rho from the axis).
Its wall profile is the robust Fourier fit rho(theta) = c0 + a1 cos + b1 sin + a2 cos 2
theta + b2 sin 2 theta (:func:`.wall_profile.fit_wall_profile`): c0 is half the mean diameter
(Dmax + Dmin) / 2, |(a2, b2)| half the difference Dmax - Dmin, so the ovality is
(Dmax - Dmin) / D = 2 |(a2, b2)| / c0 and the major axis lies at atan2(b2, a2) / 2.

Standing water returns no laser: the ring is cut off at the water line, one gap in the
ring. A ring with one such cut is still fitted to order 2 while the wall above the water
covers ``cut_min_coverage_deg``; the water depth is the depth of the fitted section
below the chord joining the cut's edges (each edge taken half a sample step into the
gap: the water line lies between the last lit sample and the next, unlit, one). Cuts
at the same angle on several consecutive stations are water; the station's diameter
and ovality then rest on the wall above it only.

The defect finder measures deviations from these per-station sections (an ellipse per
ring that follows a taper and the oblique rings of a bend), never from one cylinder.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass, replace
from typing import Any

import numpy as np

from omnipipe.config import bounded


@dataclass(frozen=True)
class SectionConfig:
    """Settings of the section measurements.

    Attributes:
        min_coverage_deg: a ring covering less of the circumference with several gaps
            fits order 0 only (no ovality).
        cut_min_coverage_deg: a ring with one cut (water) still fits order 2 while the
            wall above it covers this much.
        cut_min_deg: a gap in the ring at least this wide (and 4 sample steps) is a cut.
        water_angle_tol_deg: cuts centred within this of the run's median cut angle are
            the same water surface.
        water_min_pct: a cut is water only when the wall below its chord is at least
            this deep (percent of the diameter) and 3 sigma: shallower cuts are laser
            dropouts, not a water level an inspector codes (PACP codes it in 5 % steps).
        min_stations: stations a stretch (ovality, water, bend) needs.
        ovality_feature_pct: ovality stretches reported from this (percent).
        taper_min_mm: smallest diameter change reported as a taper.
        bend_min_curvature: curvature (1/mm) x diameter above which a stretch is a bend
            (0.2: a bend radius under 5 diameters, an elbow).
        bend_min_turn_deg: smallest turn reported as a bend.
    """

    min_coverage_deg: float = bounded(270.0, gt=0, le=360)
    cut_min_coverage_deg: float = bounded(200.0, gt=0, le=360)
    cut_min_deg: float = bounded(8.0, ge=0, le=360)
    water_angle_tol_deg: float = bounded(35.0, ge=0, le=180)
    water_min_pct: float = bounded(1.0, ge=0, le=100)
    min_stations: int = bounded(2, ge=1)
    ovality_feature_pct: float = bounded(2.0, ge=0, le=100)
    taper_min_mm: float = bounded(2.0, ge=0)
    bend_min_curvature: float = bounded(0.2, ge=0)
    bend_min_turn_deg: float = bounded(10.0, ge=0, le=180)


@dataclass(frozen=True)
class Cut:
    """The widest gap of a ring (radians, [0, 2 pi)): from ``start`` to ``end``
    anticlockwise, ``step`` the ring's median sample step."""

    start: float
    end: float
    step: float

    @property
    def width(self) -> float:
        return (self.end - self.start) % (2 * np.pi)

    @property
    def centre(self) -> float:
        return (self.start + 0.5 * self.width) % (2 * np.pi)


@dataclass(frozen=True)
class Section:
    """One ring's fitted wall profile.

    Attributes:
        coef: [c0, a1, b1, a2, b2, ...] of :func:`.wall_profile.fit_wall_profile` (mm).
        cov: its covariance (mm^2).
        order: the Fourier order fitted (0 or 2).
        cut: the ring's widest gap when it is a cut (water candidate), else None.
        coverage_deg: the circumference the ring covers.
    """

    coef: np.ndarray
    cov: np.ndarray
    order: int
    cut: Cut | None
    coverage_deg: float


@dataclass(frozen=True)
class Station:
    """One measured cross-section (mm; ovality a fraction; angles degrees).

    Attributes:
        axial_mm: position along the centreline (the defects' convention).
        diameter_mm, diameter_sigma_mm: mean diameter (Dmax + Dmin) / 2 and its 1-sigma.
        diameter_min_mm, diameter_max_mm: Dmin and Dmax of the fitted section.
        ovality, ovality_sigma: (Dmax - Dmin) / D (bias-corrected) and its 1-sigma; NaN
            when the ring's coverage allowed order 0 only.
        ovality_angle_deg, ovality_angle_sigma_deg: direction of the major axis, [0, 180),
            from the first rig frame's x axis towards y.
        water_depth_mm, water_depth_sigma_mm: standing water above the invert (0: none
            seen; its sigma then the shallowest depth a cut would show).
        water_depth_shared_sigma_mm: the part of that sigma every station of the run
            shares (:attr:`WaterDepth.shared_mm`): a stretch's average keeps it whole.
        water_depth_joint_sigma_mm: the part of that sigma from a found joint's step
            (:func:`with_water`'s ``joints``): no evidence of a depth step between
            stations (``sections._depth_steps``).
        water_depth_footprint_sigma_mm: the part of that sigma from the sections the
            station's ring mixes (:func:`.footprint.water_footprint_terms`): shared by
            the stations whose footprints overlap, no evidence of a depth step either.
        wall_coverage_deg: circumference covered by the ring's wall points.
        deformation_mm, deformation_sigma_mm: mean diameter minus the run's (headline).
    """

    axial_mm: float
    diameter_mm: float
    diameter_sigma_mm: float
    diameter_min_mm: float
    diameter_max_mm: float
    ovality: float
    ovality_sigma: float
    ovality_angle_deg: float
    ovality_angle_sigma_deg: float
    water_depth_mm: float = 0.0
    water_depth_sigma_mm: float = 0.0
    wall_coverage_deg: float = 360.0
    deformation_mm: float = 0.0
    deformation_sigma_mm: float = 0.0
    cut_centre_deg: float | None = None
    water_depth_shared_sigma_mm: float = 0.0
    water_depth_joint_sigma_mm: float = 0.0
    water_depth_footprint_sigma_mm: float = 0.0

    def to_contract(self) -> dict[str, Any]:
        """The report.json ``stations`` entry: the contract's keys with their sigma
        partners, then omnipipe's (``wall_coverage_deg``, ``deformation_mm``)."""
        return {
            "axial_mm": _r(self.axial_mm, 2),
            "inner_diameter_mm": _r(self.diameter_mm, 3),
            "inner_diameter_sigma_mm": _r(self.diameter_sigma_mm, 4),
            "inner_diameter_min_mm": _r(self.diameter_min_mm, 3),
            "inner_diameter_max_mm": _r(self.diameter_max_mm, 3),
            "ovality_pct": _r(100 * self.ovality, 3),
            "ovality_sigma_pct": _r(100 * self.ovality_sigma, 3),
            "ovality_angle_deg": _r(self.ovality_angle_deg, 2),
            "ovality_angle_sigma_deg": _r(self.ovality_angle_sigma_deg, 2),
            "water_depth_mm": _r(self.water_depth_mm, 2),
            "water_depth_sigma_mm": _r(self.water_depth_sigma_mm, 3),
            "wall_coverage_deg": _r(self.wall_coverage_deg, 1),
            "deformation_mm": _r(self.deformation_mm, 3),
            "deformation_sigma_mm": _r(self.deformation_sigma_mm, 4),
        }


def _r(x: float | None, nd: int) -> float | None:
    return None if x is None or not math.isfinite(x) else round(float(x), nd)


def ring_cut(theta: np.ndarray, config: SectionConfig) -> tuple[Cut | None, float]:
    """The ring's widest gap if it is a cut (``config.cut_min_deg`` and 4 sample steps
    wide), and the ring's coverage (degrees)."""
    t = np.sort(np.mod(theta, 2 * np.pi))
    gaps = np.diff(np.concatenate([t, [t[0] + 2 * np.pi]]))
    i = int(np.argmax(gaps))
    step = float(np.median(gaps))
    coverage = 360.0 - math.degrees(float(gaps[i]))
    if gaps[i] < max(math.radians(config.cut_min_deg), 4 * step):
        return None, coverage
    return Cut(float(t[i]), float(t[(i + 1) % len(t)]), step), coverage


def section_order(cut: Cut | None, coverage_deg: float, wanted: int, config: SectionConfig) -> int:
    """The Fourier order a ring supports: ``wanted`` when it covers
    ``config.min_coverage_deg``, or ``config.cut_min_coverage_deg`` with a single cut."""
    if coverage_deg >= config.min_coverage_deg:
        return wanted
    if cut is not None and coverage_deg >= config.cut_min_coverage_deg:
        return wanted
    return 0


def profile_radius(coef: np.ndarray, theta: np.ndarray) -> np.ndarray:
    """rho(theta) of a Fourier profile (mm)."""
    out = np.full(np.shape(theta), float(coef[0]))
    for k in range(1, (len(coef) - 1) // 2 + 1):
        out = out + coef[2 * k - 1] * np.cos(k * theta) + coef[2 * k] * np.sin(k * theta)
    return out


REACH_MODEL_REL = 0.25
"""Relative 1-sigma of the stripe's blur reach past a water line
(:func:`omnipipe.laser.extract.edge_reach_mm`) as a model: it takes the ring's median
blur and mm per px where the water line meets the ring at its own range, and texture
lifts the faintest peaks up to half a blur further (0.9 of 5.9 mm on the true-motion
captures). On the 34 random-features runs the wet stations of a run err alike: seeds
20 and 28, 1.1 and 1.4 mm (0.3-0.4 mm stated per stretch before), what a reach off by
0.55 x its 2.5 / 4.5 mm gives; with 0.25 every stretch's depth is within 3 sigma (14)."""


@dataclass(frozen=True)
class EdgeReach:
    """How far (mm along the wall) a ring's samples run on past the end of its lit
    stretch, and its 1-sigma: the run's model (the imaged stripe's blur above the
    extractor's threshold, :func:`omnipipe.laser.extract.edge_reach_mm`; ``sigma_mm``
    one ring's spread about it, :data:`REACH_MODEL_REL` added, shared by the run's
    rings) or, ``measured``, the ring's own at its cut's ends (the stripe's half-height
    point there, :func:`omnipipe.laser.extract.station_edge_reach`: measured from the
    last samples themselves, so no half sample step and no model term)."""

    mm: float = 0.0
    sigma_mm: float = 0.0
    measured: bool = False


@dataclass(frozen=True)
class WaterDepth:
    """One station's water depth (mm) and its 1-sigma with the named terms it holds
    (mm, each a depth error; ``sigma_mm`` their quadrature sum).

    Attributes:
        depth_mm: the fitted section's depth below the water line's chord.
        edge_mm: the chord's ends from the ring's sample spacing (each uncertain by
            step / sqrt(12), the two independently; the run's rings alike:
            :attr:`shared_mm`).
        fit_mm: the section fit's covariance carried through the depth (the wall under
            the water is the fit's extrapolation across the cut).
        wall_mm: the wall noise of one sample at that range (the chord's ends sit on it).
        reach_mm: the reach's 1-sigma (``EdgeReach.sigma_mm``) moving both ends back
            alike; shared by every station of the run (the water line meets each ring on
            the same wall, so its stripe fades alike; a reach measured at each ring's cut
            errs alike over a run too), not averaged away.
    """

    depth_mm: float
    edge_mm: float
    fit_mm: float
    wall_mm: float
    reach_mm: float = 0.0

    @property
    def sigma_mm(self) -> float:
        return math.hypot(self.edge_mm, self.fit_mm, self.wall_mm, self.reach_mm)

    @property
    def shared_mm(self) -> float:
        """The part of :attr:`sigma_mm` the run's stations share: the reach's, and the
        chord ends' quantisation (``edge_mm``): every ring is sampled on the
        extractor's same fixed scan-line angles and level water meets each ring at
        nearly the same angle, so each ring's last lit sample falls the same way (24
        synthetic rings on 0.5 deg samples: the stretch's depth errs by up to 0.35 mm
        as the depth moves through a sample step, 9 sigma of the averaged term)."""
        return math.hypot(self.edge_mm, self.reach_mm)


def _depth_below_chord(coef: np.ndarray, e1: float, e2: float) -> float:
    """Largest depth (mm) of the profile ``coef`` between angles e1 < e2 below the chord
    joining its points at e1 and e2 (away from the axis)."""

    def point(a: np.ndarray) -> np.ndarray:
        r = profile_radius(coef, a)
        return np.stack([r * np.cos(a), r * np.sin(a)], axis=-1)

    p1, p2 = point(np.array(e1)), point(np.array(e2))
    chord = p2 - p1
    normal = np.array([chord[1], -chord[0]]) / max(float(np.linalg.norm(chord)), 1e-9)
    if normal @ (0.5 * (p1 + p2)) < 0:
        normal = -normal  # away from the axis, towards the cut's wall
    inside = point(np.linspace(e1, e2, 181))
    return float(np.max((inside - p1) @ normal))


def water_depth(section: Section, radial_sigma_mm: float, reach: EdgeReach | None = None) -> WaterDepth:
    """Depth (mm) of the fitted section below the chord across its cut, and its 1-sigma.

    The lit stretch stops between the last lit sample and the next (half a sample step
    into the gap, uncertain by step / sqrt(12)); the stripe's blur carries the samples
    ``reach.mm`` past the water line itself, so each chord end is taken that far back
    towards the lit wall (``reach.sigma_mm`` its ring-to-ring 1-sigma, with the reach
    model's own ``REACH_MODEL_REL``: both shared by the run's rings). A reach measured
    at this ring's cut (``reach.measured``) is taken from the last samples themselves
    (no half step, no step quantisation) with its stated sigma. An edge's
    error moves the depth by the wall's slope across the chord; the fit's covariance is
    carried through the depth by its Jacobian in the coefficients.
    """
    cut = section.cut
    if cut is None:
        return WaterDepth(0.0, math.nan, math.nan, math.nan)
    reach = reach or EdgeReach()
    coef = np.asarray(section.coef, float)
    ends = (cut.start, cut.start + cut.width)
    rho = [float(profile_radius(coef, np.array(e))) for e in ends]
    back = [reach.mm / max(r, 1e-9) for r in rho]
    half = 0.0 if reach.measured else 0.5 * cut.step
    e1 = ends[0] + half - back[0]
    e2 = ends[1] - half + back[1]
    depth = _depth_below_chord(coef, e1, e2)
    # Each edge's depth error: the depth's change with the edge (mm / rad, signed towards
    # the gap) x its angle error.
    h = 1e-4
    slopes = [
        (_depth_below_chord(coef, e1 + h, e2) - _depth_below_chord(coef, e1 - h, e2)) / (2 * h),
        (_depth_below_chord(coef, e1, e2 - h) - _depth_below_chord(coef, e1, e2 + h)) / (2 * h),
    ]
    quant = 0.0 if reach.measured else cut.step / math.sqrt(12.0)
    edge = math.hypot(slopes[0] * quant, slopes[1] * quant)
    reach_sig = reach.sigma_mm if reach.measured else math.hypot(reach.sigma_mm, REACH_MODEL_REL * reach.mm)
    reach_err = abs(slopes[0] * reach_sig / max(rho[0], 1e-9) + slopes[1] * reach_sig / max(rho[1], 1e-9))
    jac = np.zeros(len(coef))
    for k in range(len(coef)):
        dc = np.zeros(len(coef))
        dc[k] = 1e-3
        jac[k] = (_depth_below_chord(coef + dc, e1, e2) - _depth_below_chord(coef - dc, e1, e2)) / 2e-3
    cov = np.asarray(section.cov, float)[: len(coef), : len(coef)]
    fit = math.sqrt(max(float(jac @ cov @ jac), 0.0))
    return WaterDepth(max(depth, 0.0), edge, fit, radial_sigma_mm, reach_err)


def station_from_section(
    axial_mm: float, section: Section, radial_sys_mm: float, cal_rel: float
) -> Station:
    """A :class:`Station` from a ring's section fit (water not yet decided: depth 0);
    ``radial_sys_mm`` and ``cal_rel`` the radial errors no fit sees (added to diameters)."""
    c, cov = section.coef, section.cov
    c0 = float(c[0])
    d = 2.0 * c0
    dsig = math.hypot(2.0 * math.sqrt(max(cov[0, 0], 0.0)), 2.0 * radial_sys_mm, cal_rel * d)
    if section.order >= 2:
        var2 = 0.5 * (cov[3, 3] + cov[4, 4])
        raw2 = float(c[3] ** 2 + c[4] ** 2)
        amp = math.sqrt(max(raw2 - 2.0 * var2, 0.0))
        ovality, osig = 2.0 * amp / c0, 2.0 * math.sqrt(var2) / c0
        angle = math.degrees(0.5 * math.atan2(float(c[4]), float(c[3]))) % 180.0
        asig = math.degrees(0.5 * math.sqrt(var2) / max(math.sqrt(raw2), 1e-9))
        asig = min(asig, 180.0 / math.sqrt(12.0))
    else:
        amp, ovality, osig, angle, asig = 0.0, math.nan, math.nan, math.nan, math.nan
    return Station(
        axial_mm=float(axial_mm),
        diameter_mm=d,
        diameter_sigma_mm=dsig,
        diameter_min_mm=d - 2.0 * amp,
        diameter_max_mm=d + 2.0 * amp,
        ovality=ovality,
        ovality_sigma=osig,
        ovality_angle_deg=angle,
        ovality_angle_sigma_deg=asig,
        wall_coverage_deg=section.coverage_deg,
        cut_centre_deg=None if section.cut is None else math.degrees(section.cut.centre),
    )


SCATTER_MIN_STATIONS = 5
"""Stations with an ovality :func:`ovality_scatter` needs (three second differences)."""


def ovality_scatter(stations: list[Station]) -> float:
    """The ring-to-ring scatter of the stations' ovality (a fraction, 1-sigma per component
    of the ovality vector ovality x (cos 2 phi, sin 2 phi), phi the major axis) that their
    fit sigmas do not hold: from each station's difference to the mean of its neighbours
    in axial order (a smooth change of the pipe's ovality along the run cancels; robust
    MAD over both components, / sqrt(1.5) for the neighbours' own scatter), less the
    stations' median fit sigma in quadrature; 0 with fewer than
    :data:`SCATTER_MIN_STATIONS` stations with an ovality.

    A ring's shape errs by more than its own fit says (the wall texture's peaks, the
    stripe's blur along a tilted ring, the section a ring's footprint mixes); measured
    in benchmarks/RESULTS.md (ana27)."""
    ok = [s for s in stations if math.isfinite(s.ovality) and math.isfinite(s.ovality_angle_deg)]
    if len(ok) < SCATTER_MIN_STATIONS:
        return 0.0
    ok.sort(key=lambda s: s.axial_mm)
    v = np.array([s.ovality for s in ok]) * np.exp(2j * np.radians([s.ovality_angle_deg for s in ok]))
    d = v[1:-1] - 0.5 * (v[:-2] + v[2:])
    spread = 1.4826 * float(np.median(np.abs(np.concatenate([d.real, d.imag])))) / math.sqrt(1.5)
    fit = float(np.median([s.ovality_sigma for s in ok]))
    return math.sqrt(max(spread**2 - fit**2, 0.0))


JOINT_STEP_MAX_REL = 0.05
"""The largest joint step (offset and gap depth, relative to the diameter) a water
station's sigma takes (:func:`with_water`): a joint's offset read from a degenerate
local axis can be tens of percent of the diameter (random-features seed 13: 127 mm in
a 533 mm pipe, against 2.3 true); real joint offsets are a few percent."""


def with_water(
    stations: list[Station],
    sections: list[Section],
    radial_sigma_mm: float,
    config: SectionConfig,
    reach: EdgeReach | Sequence[EdgeReach] | None = None,
    joints: Sequence[tuple[float, float, float]] = (),
) -> tuple[list[Station], bool]:
    """The stations with their water depths: cuts at the run's common cut angle, deep
    enough (``config.water_min_pct``, 3 sigma), on at least ``config.min_stations``
    stations are water (returns True then); the other stations are dry (depth 0, sigma
    the depth of the narrowest cut). ``reach``: the stripe's blur past a water line
    (:func:`water_depth`), the run's or one per station. ``joints``: found joints'
    bands (axial from, to; mm) and the step (mm) their sections make at the wall (the
    offset and the gap's depth in quadrature): a station there may ring both sections
    and its cut end lie in the gap's recess, so its depth's sigma holds that step (at
    most :data:`JOINT_STEP_MAX_REL` of the diameter; kept apart in
    ``water_depth_joint_sigma_mm``: no reason against a stretch's depth step)."""
    reaches = list(reach) if isinstance(reach, Sequence) else [reach] * len(stations)
    centres = np.array([s.cut_centre_deg for s in stations if s.cut_centre_deg is not None])
    common = None
    if len(centres) >= config.min_stations:
        z = np.exp(1j * np.radians(centres))
        common = math.degrees(float(np.angle(np.mean(z))))
    out, wet = [], 0
    for st, sec, st_reach in zip(stations, sections, reaches, strict=True):
        shallowest = 0.5 * st.diameter_mm * (1.0 - math.cos(0.5 * math.radians(config.cut_min_deg)))
        is_water = (
            common is not None
            and st.cut_centre_deg is not None
            and abs((st.cut_centre_deg - common + 180.0) % 360.0 - 180.0) <= config.water_angle_tol_deg
        )
        if is_water:
            wd = water_depth(sec, radial_sigma_mm, st_reach)
            depth, sig, shared = wd.depth_mm, wd.sigma_mm, wd.shared_mm
            is_water = depth >= max(3.0 * sig, 0.01 * config.water_min_pct * st.diameter_mm)
            step = max((step for lo, hi, step in joints if lo <= st.axial_mm <= hi), default=0.0)
            step = min(step, JOINT_STEP_MAX_REL * st.diameter_mm)
            sig = math.hypot(sig, step)
        if is_water:
            wet += 1
            out.append(
                replace(
                    st, water_depth_mm=depth, water_depth_sigma_mm=sig, water_depth_shared_sigma_mm=shared,
                    water_depth_joint_sigma_mm=step,
                )
            )
        else:
            out.append(replace(st, water_depth_mm=0.0, water_depth_sigma_mm=shallowest))
    if wet < config.min_stations:
        out = [
            replace(s, water_depth_mm=0.0) if s.water_depth_mm > 0 else s for s in out
        ]
        return out, False
    return out, True


@dataclass(frozen=True)
class Headline:
    """The run's inner diameter from its stations (mm).

    Attributes:
        diameter_mm, sigma_mm: median of the stations' mean diameters and its 1-sigma.
        min_mm, max_mm: smallest Dmin and largest Dmax of the stations (each smoothed
            over 5 neighbouring stations).
        stations_used: stations measured.
        move_sigma_mm: the part of ``sigma_mm`` (in quadrature) from the median's move
            (:func:`median_move_mm`; 0 where the stations beside the median agree).
    """

    diameter_mm: float
    sigma_mm: float
    min_mm: float
    max_mm: float
    stations_used: int
    move_sigma_mm: float = 0.0


def _running_median(x: np.ndarray, half: int = 2) -> np.ndarray:
    return np.array([np.median(x[max(0, i - half) : i + half + 1]) for i in range(len(x))])


MEDIAN_MOVE_FROM = 1.0
"""The headline's sigma takes :func:`median_move_mm` in from where that move exceeds this
many of its other terms (in full from one more): below, the stations beside the median
agree within what the sigma states already (every run without a diameter change: at most
0.7 x on the features bench's)."""


def median_move_mm(diameters: np.ndarray) -> float:
    """How far the median of ``diameters`` (mm) moves when one of them lies on its other
    side (a ring the run placed across a section's end, or one more ring of the other
    section): the mean of the move up and the move down, from the order statistics beside
    the median (for n odd (d[k+1] - d[k-1]) / 2 about the middle d[k]; for n even the mean
    of (d[k+2] - d[k]) / 2 and (d[k+1] - d[k-1]) / 2 about the middle pair d[k], d[k+1]);
    0 for fewer than 2 values. Small among like stations (a fraction of their scatter /
    sqrt(n)); on a diameter change whose ramp holds the median, the stations' spacing in
    diameter there."""
    d = np.sort(np.asarray(diameters, float))
    n = len(d)
    if n < 2:
        return 0.0
    k = (n - 1) // 2
    if n % 2:
        return float(d[k + 1] - d[k - 1]) / 2.0
    return float(d[min(k + 2, n - 1)] + d[k + 1] - d[k] - d[max(k - 1, 0)]) / 4.0


def headline(stations: list[Station], shared_sigma_mm: float) -> Headline:
    """Mean diameter of the run: the median of the stations' (Dmax + Dmin) / 2 (robust to
    a ring across a joint; on a taper the diameter at the middle station).

    Its sigma: 1.25 x the stations' scatter / sqrt(n), the scatter from each station's
    difference to the line through its neighbours (a taper's slope cancels; robust MAD,
    / sqrt(1.5) for the neighbours' own noise), and ``shared_sigma_mm`` (errors all
    stations share: the rig calibration, the systematic ring radius); with fewer than 3
    stations their stated sigma stands in for the scatter. Where the stations beside the
    median differ by more than that states (:func:`median_move_mm` beyond
    :data:`MEDIAN_MOVE_FROM` x it: the median lies on a diameter change no taper was
    reported for, random-features seed 23: 12 stations, 5 of the 244.7 mm section, 3 on a
    10 mm ramp and 4 before it, the median 248.5 mm between 247.1 and 250.0), that move
    too, taken in continuously over one more sigma.
    """
    d = np.array([s.diameter_mm for s in stations])
    ds = np.array([s.diameter_sigma_mm for s in stations])
    n = len(d)
    if n >= 3:
        resid = d[1:-1] - 0.5 * (d[:-2] + d[2:])
        scatter = 1.4826 * float(np.median(np.abs(resid))) / math.sqrt(1.5)
    else:
        scatter = float(np.median(ds))
    stat = 1.2533 * scatter / math.sqrt(max(n, 1))
    sigma = math.hypot(stat, shared_sigma_mm)
    move = median_move_mm(d)
    share = min(max(move / sigma - MEDIAN_MOVE_FROM, 0.0), 1.0) if sigma > 0 else float(move > 0)
    dmin = _running_median(np.array([s.diameter_min_mm for s in stations]))
    dmax = _running_median(np.array([s.diameter_max_mm for s in stations]))
    return Headline(
        diameter_mm=float(np.median(d)),
        sigma_mm=math.hypot(sigma, share * move),
        min_mm=float(np.min(dmin)),
        max_mm=float(np.max(dmax)),
        stations_used=n,
        move_sigma_mm=share * move,
    )


def headline_on_a_taper(head: Headline, stations: list[Station]) -> Headline:
    """The headline of a run whose diameter changes along it (a taper reported): the
    median then reads one station of the ramp, not an average of like ones, so its
    sigma holds that station's whole sigma (with the sections its ring mixes:
    :func:`.footprint.footprint_terms`) beside the average's."""
    if not stations:
        return head
    d = np.array([s.diameter_mm for s in stations])
    at = int(np.argmin(np.abs(d - head.diameter_mm)))
    return replace(head, sigma_mm=math.hypot(head.sigma_mm, stations[at].diameter_sigma_mm))


CLEAR_MAJORITY = 2.0
"""A reducing run's headline is one section's when that side of the ramp holds at least
this many times the other side's stations (:func:`headline_of_a_section`)."""


def headline_of_a_section(
    head: Headline,
    stations: list[Station],
    ramp: tuple[float, float],
    diameters: tuple[float, float],
    shared_sigma_mm: float,
) -> Headline:
    """The headline of a reducing run: the diameter of the constant section most of its
    stations measured, not the median station, which on a reducer lies on the ramp
    (random-features seed 0: 11 stations over a 543 -> 477 mm reducer, the median one
    489 mm on the ramp, placed 6 mm off by the camera motion where the ramp falls 3 mm
    per mm: 9 mm from the truth there).

    ``ramp`` (from, to) mm and ``diameters`` (from, to) mm: the reported taper's. The
    stations before and after the ramp are the two sections; when one holds at least
    :data:`CLEAR_MAJORITY` times the other's stations, the headline is :func:`headline`
    over its stations alone (``min_mm``, ``max_mm`` kept from the whole run's ``head``).
    Otherwise the run measured both alike: the median station stands, and its sigma
    holds that station's whole sigma (:func:`headline_on_a_taper`) and the sections'
    difference as a uniform ambiguity (/ sqrt(12)): which section the run "is" is not
    decided by it (seed 25: 4 stations either side of a 339 -> 281 mm reducer placed
    under a 10 % scale, the true rings 2 and 7); that difference stands for the median's
    move (``head.move_sigma_mm``: the same ambiguity, not counted twice)."""
    axial = np.array([s.axial_mm for s in stations])
    before = [s for s, a in zip(stations, axial, strict=True) if a < ramp[0]]
    after = [s for s, a in zip(stations, axial, strict=True) if a > ramp[1]]
    big, small = (before, after) if len(before) >= len(after) else (after, before)
    if big and len(big) >= CLEAR_MAJORITY * len(small):
        own = headline(big, shared_sigma_mm)
        return replace(own, min_mm=head.min_mm, max_mm=head.max_mm, stations_used=len(big))
    own_sigma = math.sqrt(max(head.sigma_mm**2 - head.move_sigma_mm**2, 0.0))
    mid = headline_on_a_taper(replace(head, sigma_mm=own_sigma, move_sigma_mm=0.0), stations)
    return replace(mid, sigma_mm=math.hypot(mid.sigma_mm, abs(diameters[1] - diameters[0]) / math.sqrt(12.0)))


def with_deformation(stations: list[Station], head: Headline) -> list[Station]:
    """Each station's mean diameter minus the run's, with its 1-sigma."""
    return [
        replace(
            s,
            deformation_mm=s.diameter_mm - head.diameter_mm,
            deformation_sigma_mm=math.hypot(s.diameter_sigma_mm, head.sigma_mm),
        )
        for s in stations
    ]
