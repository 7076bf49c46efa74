"""Section features of the measured pipe from its stations and centreline (issue 30):
taper (a diameter change), bend (the centreline turning), ovality and water stretches.

Each is a :class:`~omnipipe.analysis.feature_types.Stretch` (:class:`.Taper`, :class:`.Bend`,
:class:`.Ovality`, :class:`.Water`). A
stretch touching the first or last station is ``truncated`` (it may run on beyond the
measured stations). Extents along the pipe are uncertain by half the local station
spacing (the feature's edge lies somewhere between two stations).
"""

from __future__ import annotations

import math
from collections.abc import Sequence

import numpy as np

from omnipipe.analysis.centreline import BendFit, Centreline, fit_bend, local_tangents
from omnipipe.analysis.feature_types import Bend, Ovality, Stretch, Taper, Water
from omnipipe.analysis.footprint import independent_count
from omnipipe.analysis.stations import Headline, SectionConfig, Station
from omnipipe.errors import ShapeError


def section_features(
    stations: list[Station],
    line: Centreline,
    head: Headline,
    config: SectionConfig,
    mixing_mm: np.ndarray | None = None,
    footprint_mm: np.ndarray | None = None,
) -> list[Stretch]:
    """Taper, bend, ovality and water features of the run, in axial order (a centreline
    turn lying mostly on a taper is not a bend: the cylinder fits tilt in a cone);
    ``mixing_mm`` (S,): the diameter term of the sections each station's ring mixes
    (:func:`taper_weights`); ``footprint_mm`` (S,): half each station's ring's axial
    extent (:func:`.footprint.footprint_mm`; None: rings taken as square)."""
    if len(stations) < 3:
        return []
    tapers = _tapers(stations, config, mixing_mm)
    # The piecewise cylinder fits tilt their axes in a cone: no bend mostly inside a taper.
    bends = [b for b in _bends(line, head.diameter_mm, config) if not any(_within(b, t) for t in tapers)]
    out = tapers + bends
    out += _ovality_stretches(stations, config, footprint_mm) + _water_stretches(stations, config, tapers)
    return sorted(out, key=lambda f: f.axial_from_mm)


def _within(a: Stretch, b: Stretch) -> bool:
    """Half of stretch ``a`` or more lies inside ``b``."""
    lo = max(a.axial_from_mm, b.axial_from_mm)
    hi = min(a.axial_to_mm, b.axial_to_mm)
    return hi - lo >= 0.5 * max(a.axial_to_mm - a.axial_from_mm, 0.0)


def _runs(mask: np.ndarray, min_len: int) -> list[tuple[int, int]]:
    """(first, last) index of each run of True at least ``min_len`` long."""
    out, start = [], None
    for i, m in enumerate([*list(mask), False]):
        if m and start is None:
            start = i
        elif not m and start is not None:
            if i - start >= min_len:
                out.append((start, i - 1))
            start = None
    return out


def _edge_sigma(axial: np.ndarray) -> float:
    return 0.5 * float(np.median(np.diff(axial))) if len(axial) > 1 else math.nan


def _ovality_stretches(
    stations: list[Station], config: SectionConfig, footprint_mm: np.ndarray | None = None
) -> list[Stretch]:
    """Stretches whose ovality is at least ``config.ovality_feature_pct``; their size
    from the stations inside the first and last (those lie where the ovality blends in
    and out: random-features-small's stretches, 2-4 stations, read 0.8-0.9 pp low with
    them), its sigma over the stations whose rings read walls of their own
    (:func:`.footprint.independent_count` with ``footprint_mm`` (S,), half each ring's
    axial extent; one per station, else ShapeError)."""
    ov = np.array([s.ovality for s in stations])
    axial = np.array([s.axial_mm for s in stations])
    if footprint_mm is not None and len(footprint_mm) != len(stations):
        # Zeros would count every station's ring as independent: a sigma too small, silently.
        raise ShapeError(f"footprint_mm: {len(footprint_mm)} values for {len(stations)} stations")
    half = np.zeros(len(stations)) if footprint_mm is None else footprint_mm
    mask = np.nan_to_num(ov, nan=0.0) * 100.0 >= config.ovality_feature_pct
    edge = _edge_sigma(axial)
    out = []
    for i0, i1 in _runs(mask, config.min_stations):
        sel = slice(i0 + 1, i1) if i1 - i0 >= 2 else slice(i0, i1 + 1)
        n = sel.stop - sel.start
        z = np.exp(2j * np.radians([s.ovality_angle_deg for s in stations[sel]]))
        angle = (0.5 * math.degrees(float(np.angle(np.mean(z))))) % 180.0
        osig = np.array([s.ovality_sigma for s in stations[sel]])
        asig = np.array([s.ovality_angle_sigma_deg for s in stations[sel]])
        spread = float(np.std(ov[sel])) if n > 2 else float(np.median(osig))
        n = independent_count(axial[sel], half[sel])
        out.append(
            Ovality(
                axial_from_mm=float(axial[i0]),
                axial_from_sigma_mm=edge,
                axial_to_mm=float(axial[i1]),
                axial_to_sigma_mm=edge,
                percent=100.0 * float(np.median(ov[sel])),
                percent_sigma=100.0 * max(spread, float(np.median(osig))) / math.sqrt(n),
                angle_deg=angle,
                angle_sigma_deg=float(np.median(asig)) / math.sqrt(n),
                truncated=i0 == 0 or i1 == len(stations) - 1,
            )
        )
    return out


OVALITY_MIN_SIGMAS = 1.0
"""An ovality stretch is reported when its percent is at least this many of its own
sigma (:func:`significant_ovality`)."""


def significant_ovality(features: list[Stretch]) -> tuple[list[Stretch], list[str]]:
    """``features`` without the ovality stretches within :data:`OVALITY_MIN_SIGMAS` of
    their own sigma of none (their stations' rings, overlapping along the axis, read one
    wall whose shape they share), and a warning for each."""
    kept, warnings = [], []
    for f in features:
        if isinstance(f, Ovality) and f.percent_sigma is not None and f.percent < OVALITY_MIN_SIGMAS * f.percent_sigma:
            warnings.append(
                f"an ovality of {f.percent:.1f} % at {f.axial_from_mm:.0f}..{f.axial_to_mm:.0f} mm is within "
                f"{OVALITY_MIN_SIGMAS:g} sigma ({f.percent_sigma:.1f} %) of none: its stations' rings overlap "
                "along the axis and read one wall, so it is not reported"
            )
            continue
        kept.append(f)
    return kept, warnings


def _depth_steps(
    depth: np.ndarray,
    sigma: np.ndarray,
    runs: list[tuple[int, int]],
    min_len: int,
    moved: np.ndarray,
    on_joint: np.ndarray | None = None,
) -> list[tuple[int, int]]:
    """``runs`` (first, last) of wet stations split where the depth steps between
    neighbours whose invert may have moved (``moved`` (S - 1,) bool, between station i
    and i + 1: both inside a reported taper, or the section's diameter stepping between
    them, :func:`_section_moved`) by more than 4 sigma (their independent ``sigma`` in
    quadrature) and 5 % of the shallower: level water over a reducer, a different depth
    on each side (random-features seed 0: 65 mm above a 543 -> 477 mm reducer, 33 mm
    below it). Each piece keeps ``min_len`` stations off a found joint's band
    (``on_joint`` (S,) bool: a ring there may span both sections, its depth no evidence
    of a level of its own). Elsewhere the invert does not move and a step is the
    stations' own error (sewer-small: 42 and 39 mm either side of a lateral over 40 mm
    of water)."""
    off = np.cumsum(np.r_[0, ~np.asarray(on_joint if on_joint is not None else np.zeros(len(depth), bool))])
    out = []
    for i0, i1 in runs:
        start = i0
        for i in range(i0, i1):
            jump = abs(depth[i + 1] - depth[i])
            big = jump > max(4.0 * math.hypot(sigma[i], sigma[i + 1]), 0.05 * min(depth[i], depth[i + 1]))
            big = big and bool(moved[i])
            if big and off[i + 1] - off[start] >= min_len and off[i1 + 1] - off[i + 1] >= min_len:
                out.append((start, i))
                start = i + 1
        out.append((start, i1))
    return out


def _section_moved(stations: list[Station], config: SectionConfig, tapers: Sequence[Stretch]) -> np.ndarray:
    """(S - 1,) True between neighbouring stations where the invert may have moved: both
    inside one of the ``tapers`` (within half a station spacing), or their diameters
    differing by ``config.taper_min_mm`` and 4 sigma (a reducer no taper was reported
    for: random-features-small seed 23's 280 -> 245 mm one, 10 mm long beside a joint,
    its wide side's stations mixing both sections; one water stretch over it read
    26.4 mm, the median of 8 stations below the step, 41.5 mm above it)."""
    axial = np.array([s.axial_mm for s in stations])
    d = np.array([s.diameter_mm for s in stations])
    dsig = np.array([s.diameter_sigma_mm for s in stations])
    edge = _edge_sigma(axial)
    on_taper = np.zeros(len(stations), bool)
    for t in tapers:
        on_taper |= (axial >= t.axial_from_mm - edge) & (axial <= t.axial_to_mm + edge)
    step = np.abs(np.diff(d)) >= np.maximum(config.taper_min_mm, 4.0 * np.hypot(dsig[:-1], dsig[1:]))
    return (on_taper[:-1] & on_taper[1:]) | step


def _water_stretches(
    stations: list[Station], config: SectionConfig, tapers: Sequence[Stretch] = ()
) -> list[Stretch]:
    """Stretches of standing water (stations with a water depth; a step in the depth on
    one of the ``tapers`` starts another, :func:`_depth_steps`): the median depth; its
    sigma the stations' independent part (their spread or stated sigma) / sqrt(n), the
    part they share (``water_depth_shared_sigma_mm``) and the sections their rings mix
    (``water_depth_footprint_sigma_mm``, the median: overlapping footprints read the
    same wall) whole. A joint's step or a footprint's mix in a station's sigma is no
    reason against a depth step."""
    depth = np.array([s.water_depth_mm for s in stations])
    axial = np.array([s.axial_mm for s in stations])
    foot = np.array([s.water_depth_footprint_sigma_mm for s in stations])
    own = np.array([
        math.sqrt(max(s.water_depth_sigma_mm**2 - s.water_depth_shared_sigma_mm**2 - s.water_depth_joint_sigma_mm**2 - f**2, 0.0))
        for s, f in zip(stations, foot, strict=True)
    ])
    edge = _edge_sigma(axial)
    runs = _runs(depth > 0, config.min_stations)
    on_joint = np.array([s.water_depth_joint_sigma_mm > 0 for s in stations], bool)
    runs = _depth_steps(depth, own, runs, config.min_stations, _section_moved(stations, config, tapers), on_joint)
    out = []
    for i0, i1 in runs:
        sel = slice(i0, i1 + 1)
        shared = float(np.median([s.water_depth_shared_sigma_mm for s in stations[sel]]))
        total = np.array([s.water_depth_sigma_mm for s in stations[sel]])
        mix = float(np.median(foot[sel]))
        dsig = np.sqrt(np.maximum(total**2 - shared**2 - foot[sel] ** 2, 0.0))
        n = i1 - i0 + 1
        spread = float(np.std(depth[sel])) if n > 2 else 0.0
        out.append(
            Water(
                axial_from_mm=float(axial[i0]),
                axial_from_sigma_mm=edge,
                axial_to_mm=float(axial[i1]),
                axial_to_sigma_mm=edge,
                depth_mm=float(np.median(depth[sel])),
                depth_sigma_mm=math.hypot(max(spread, float(np.median(dsig))) / math.sqrt(n), shared, mix),
                truncated=i0 == 0 or i1 == len(stations) - 1,
            )
        )
    return out


def _taper_fit(
    axial: np.ndarray, d: np.ndarray, weight: np.ndarray | None = None
) -> tuple[float, float, float, float, float]:
    """Best ramp D1 -> D2 between a and b (constant outside) over the station grid:
    (a, b, D1, D2, weighted residual sum of squares); ``weight`` (S,) each station's
    weight (None: all 1).

    Every knot pair's two-parameter weighted least squares from prefix sums over the
    stations in axial order (O(1) a pair: stations before a weigh (1, 0), after b (0, 1),
    between (1 - w, w) with w linear in z), so the search grows with the square of the
    stations, not their cube, in blocks of pairs of bounded memory; the best pair is
    then fitted directly.
    """
    wt = np.ones(len(d)) if weight is None else np.asarray(weight, float)
    order = np.argsort(axial, kind="stable")
    z, y, w = axial[order], d[order], wt[order]
    centre = (float(np.average(z, weights=w)), float(np.average(y, weights=w)))
    zc, yc = z - centre[0], y - centre[1]  # centred: the sums lose nothing to cancellation
    cum = np.stack(
        [np.concatenate([[0.0], np.cumsum(w * v)]) for v in (np.ones_like(zc), zc, zc * zc, yc, zc * yc)]
    )
    knots = np.concatenate([axial, 0.5 * (axial[1:] + axial[:-1])])
    knots.sort()
    total = float(w @ (yc * yc))
    best = (math.inf, 0, 0)
    block = max(1, 100_000 // max(len(knots), 1))  # rows of pairs per block (about 13 MB)
    for i0 in range(0, len(knots) - 1, block):
        ka, kb = _pairs(len(knots), i0, i0 + block)
        rss = total - _explained(z, cum, centre[0], knots[ka], knots[kb])
        j = int(np.argmin(rss))
        if rss[j] < best[0]:
            best = (float(rss[j]), int(ka[j]), int(kb[j]))
    ba, bb = float(knots[best[1]]), float(knots[best[2]])
    ramp = np.clip((axial - ba) / (bb - ba), 0.0, 1.0)
    A = np.stack([1.0 - ramp, ramp], axis=1)
    root = np.sqrt(wt)
    coef, *_ = np.linalg.lstsq(A * root[:, None], d * root, rcond=None)
    return ba, bb, float(coef[0]), float(coef[1]), float(np.sum(wt * (A @ coef - d) ** 2))


def _pairs(n: int, first: int, stop: int) -> tuple[np.ndarray, np.ndarray]:
    """Knot pairs (i, j), i < j < n, for i in [first, stop), in (i, j) order."""
    rows = np.arange(first, min(stop, n - 1))
    counts = n - 1 - rows
    ka = np.repeat(rows, counts)
    kb = np.arange(len(ka)) - np.repeat(np.cumsum(counts) - counts, counts) + ka + 1
    return ka, kb


def _explained(z: np.ndarray, cum: np.ndarray, z0: float, a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Weighted sum of squares the ramp (a, b) explains of the centred diameters, per
    pair, from the weighted prefix sums ``cum`` (w, w z, w z^2, w y, w z y; centred) of
    the stations ``z`` (sorted)."""
    lo = np.searchsorted(z, a, side="right")  # stations [0, lo): ramp 0
    hi = np.searchsorted(z, b, side="left")  # stations [hi, n): ramp 1
    n_mid, s_z, s_zz, s_y, s_zy = cum[:, hi] - cum[:, lo]
    n_all = cum[0, -1]
    n_hi, y_hi = n_all - cum[0, hi], cum[3, -1] - cum[3, hi]
    length, ac = b - a, a - z0
    sum_w = n_hi + (s_z - ac * n_mid) / length
    s22 = n_hi + (s_zz - 2.0 * ac * s_z + ac * ac * n_mid) / length**2
    s12 = sum_w - s22
    s11 = n_all - 2.0 * sum_w + s22
    r2 = y_hi + (s_zy - ac * s_y) / length
    r1 = cum[3, -1] - r2
    det = s11 * s22 - s12 * s12
    ok = det > 1e-9 * np.maximum(s11 * s22, 1e-300)
    # One column (every station on one side): the constant's fit, which explains 0 (centred).
    return np.where(ok, (s22 * r1 * r1 - 2.0 * s12 * r1 * r2 + s11 * r2 * r2) / np.where(ok, det, 1.0), 0.0)


def taper_weights(sigma_mm: np.ndarray, mixing_mm: np.ndarray | None) -> np.ndarray:
    """(S,) each station's weight in the taper fit: 1, or less where its diameter's
    sigma with the sections its ring mixes (``mixing_mm``, :func:`.footprint.footprint_terms`)
    exceeds the run's median, as (median / sigma)^2. A ring tilted far off the centreline
    (random-features seed 9's last station: 180 mm of pipe in one 214 mm ring, read
    156 mm) no longer decides the ramp."""
    sig = np.asarray(sigma_mm, float)
    if mixing_mm is None or len(mixing_mm) != len(sig):
        return np.ones(len(sig))
    var = sig**2 + np.asarray(mixing_mm, float) ** 2
    return np.minimum(float(np.median(var)) / np.maximum(var, 1e-12), 1.0)


def _tapers(stations: list[Station], config: SectionConfig, mixing_mm: np.ndarray | None = None) -> list[Stretch]:
    """A diameter change along the run: a ramp fitted to the stations' mean diameters
    (weighted, :func:`taper_weights`), reported when the change is at least
    ``config.taper_min_mm`` and 6 sigma and the ramp explains the stations much better
    than one diameter (residuals 3 x smaller; 4 x missed random-features seed 9's
    ramp through a bent, oval stretch, 3.2 x; the runs without a taper whose best ramp
    changes by over 2 mm read 1.1-1.6 x, but seed 21's 3.2 mm step 13 x, refused at
    5.8 sigma only)."""
    axial = np.array([s.axial_mm for s in stations])
    d = np.array([s.diameter_mm for s in stations])
    dsig = np.array([s.diameter_sigma_mm for s in stations])
    if len(d) < 4:
        return []
    w = taper_weights(dsig, mixing_mm)
    a, b, d1, d2, rss = _taper_fit(axial, d, w)
    rss0 = float(w @ (d - np.average(d, weights=w)) ** 2)
    noise = max(math.sqrt(rss / max(float(w.sum()) - 4, 1)), float(np.median(dsig)))
    n1 = max(float(np.sum(w[axial <= a])), 1.0)
    n2 = max(float(np.sum(w[axial >= b])), 1.0)
    s1, s2 = noise / math.sqrt(n1), noise / math.sqrt(n2)
    change = abs(d2 - d1)
    if change < max(config.taper_min_mm, 6.0 * math.hypot(s1, s2)) or rss * 9.0 > rss0:
        return []
    edge = _edge_sigma(axial)
    return [
        Taper(
            axial_from_mm=a,
            axial_from_sigma_mm=edge,
            axial_to_mm=b,
            axial_to_sigma_mm=edge,
            diameter_from_mm=d1,
            diameter_from_sigma_mm=s1,
            diameter_to_mm=d2,
            diameter_to_sigma_mm=s2,
            truncated=bool(a <= axial[0] or b >= axial[-1]),
        )
    ]


def _end_tangents(line: Centreline, diameter_mm: float) -> np.ndarray:
    """(K, 3) the stations' tangents for the bend fit: ``line``'s, but within a tangent's
    half span (half the piecewise fits' window: a quarter diameter, at least three
    station spacings) of the run's first or last station the slope at the station of a
    quadratic through the centres within that span (:func:`.centreline.local_tangents`):
    there the centres lie on one side only and their line is a bend's chord, half the
    turn over the span behind its tangent: the turn read as ending before the run's end
    (benchmarks/RESULTS.md, ana22)."""
    arc = np.asarray(line.arc_mm, float)
    steps = np.abs(np.diff(arc))
    moved = steps[steps > 0.1]
    half = 0.5 * max(0.25 * diameter_mm, 3.0 * (float(np.median(moved)) if len(moved) else 0.0))
    t = np.array(line.tangent, float)
    ends = (arc - arc.min() < half) | (arc.max() - arc < half)
    if ends.any():
        t[ends] = local_tangents(np.asarray(line.centre, float), t, half, curved=True)[ends]
    return t


def _bends(line: Centreline, diameter_mm: float, config: SectionConfig) -> list[Stretch]:
    """Stretches where the centreline turns faster than ``config.bend_min_curvature`` /
    diameter: runs of steps whose curvature over a diameter of centreline
    (:func:`smoothed_curvature`) is above it and above the tangents' noise, merged across
    gaps of a station or two, each measured by the straight - bend - straight fit of the
    tangent's turn over the stations from the previous bend to the next
    (:func:`.centreline.fit_bend`): its start, end, turn and radius with their sigmas.

    The per-step turn of neighbouring stations a few mm apart is noise-dominated where
    rings ride a taper's cone or cross a lateral or joint (random-features seed 9: steps of
    up to 2.6 / D for an R = 2 D bend's 0.5 / D), so the curvature is a line fit of the
    tangents over a diameter of arc, its noise from the stations' own scatter."""
    t, arc = np.asarray(line.tangent), np.asarray(line.arc_mm)
    if len(t) < 4:
        return []
    kappa_st, noise_st = smoothed_curvature(t, arc, diameter_mm)
    kappa = 0.5 * (kappa_st[1:] + kappa_st[:-1])  # per step (step i joins stations i, i + 1)
    noise = np.maximum(noise_st[1:], noise_st[:-1])
    thr = np.maximum(config.bend_min_curvature / diameter_mm, 4.0 * noise)
    spacing = float(np.median(np.maximum(np.diff(arc), 1e-6)))
    runs = _merged(_runs(kappa > thr, 1), arc, 2.5 * spacing)
    # Runs of noise in a straight stretch turn little: not a bend, nor a fit's bound.
    half_turn = math.radians(0.5 * config.bend_min_turn_deg)
    runs = [
        (i0, i1) for i0, i1 in runs
        if i1 - i0 + 1 >= config.min_stations
        and math.acos(float(np.clip(t[max(i0 - 1, 0)] @ t[min(i1 + 2, len(t) - 1)], -1.0, 1.0))) >= half_turn
    ]
    out = []
    fit_t = _end_tangents(line, diameter_mm) if runs else t
    for j, (i0, i1) in enumerate(runs):
        # The stretch to fit: from midway to the previous bend to midway to the next.
        k0 = 0 if j == 0 else (runs[j - 1][1] + 1 + i0) // 2
        k1 = len(t) - 1 if j == len(runs) - 1 else (i1 + 1 + runs[j + 1][0]) // 2
        sel = slice(k0, k1 + 1)
        # The tangents are lines through the centres within a quarter diameter either side.
        fit = fit_bend(arc[sel], fit_t[sel], (float(arc[i0]), float(arc[i1 + 1])), 0.5 * diameter_mm / spacing)
        # A turn tighter than the pipe's own radius is a kink (a joint's offset, a
        # lateral's edge tilting the tangents), not a bend a pipe can make.
        if fit is None or not _turns_enough(fit, config.bend_min_turn_deg) or fit.radius_mm < 0.5 * diameter_mm:
            continue
        out.append(
            Bend(
                axial_from_mm=fit.start_mm,
                axial_from_sigma_mm=fit.start_sigma_mm,
                axial_to_mm=fit.end_mm,
                axial_to_sigma_mm=fit.end_sigma_mm,
                radius_mm=fit.radius_mm,
                radius_sigma_mm=fit.radius_sigma_mm,
                turn_deg=math.degrees(fit.turn_rad),
                turn_sigma_deg=math.degrees(fit.turn_sigma_rad),
                truncated=fit.truncated,
            )
        )
    return out


def _turns_enough(fit: BendFit, min_turn_deg: float) -> bool:
    """The fitted bend turns at least ``min_turn_deg``; a truncated one (the turning runs
    on past the run's first or last station) within two of its sigmas of it: its turn is
    the run's part only, a lower bound, and read short by the tangents' lag at the run's
    end (benchmarks/RESULTS.md, ana25/ana27)."""
    turn = math.degrees(fit.turn_rad)
    if fit.truncated:
        turn += 2.0 * math.degrees(fit.turn_sigma_rad)
    return turn >= min_turn_deg


def smoothed_curvature(tangent: np.ndarray, arc_mm: np.ndarray, span_mm: float) -> tuple[np.ndarray, np.ndarray]:
    """(K,) curvature (1/mm) at each station and its noise level (1/mm): the slope of the
    unit tangents (K, 3) against arc length (K,) mm in a line fit over the stations within
    +-``span_mm`` / 2 (at least 3; 0 otherwise), its part normal to their mean direction.
    The noise: the tangents' scatter about their local lines (a robust sigma per
    component, from second differences) over the fit's lever arm, sqrt(sum (s - mean)^2)."""
    t, arc = np.asarray(tangent, float), np.asarray(arc_mm, float)
    n = len(t)
    kappa, noise = np.zeros(n), np.zeros(n)
    if n < 3:
        return kappa, noise
    # Second differences of neighbouring tangents: sqrt(6) sigma per component for white noise.
    d2 = t[2:] - 2.0 * t[1:-1] + t[:-2]
    sigma_t = 1.4826 * float(np.median(np.abs(d2))) / math.sqrt(6.0)
    for i in range(n):
        near = np.abs(arc - arc[i]) <= 0.5 * span_mm
        if near.sum() < 3:
            continue
        s = arc[near] - arc[near].mean()
        ss = float(s @ s)
        if ss <= 1e-9:
            continue
        m = t[near].mean(axis=0)
        m /= max(float(np.linalg.norm(m)), 1e-12)
        k = (s @ (t[near] - m)) / ss
        k = k - (k @ m) * m
        kappa[i] = float(np.linalg.norm(k))
        noise[i] = sigma_t / math.sqrt(ss)
    return kappa, noise


def _merged(runs: list[tuple[int, int]], arc: np.ndarray, gap_mm: float) -> list[tuple[int, int]]:
    """``runs`` of steps (first, last step index; step i joins stations i and i + 1) joined
    where the arc between one's end and the next's start is at most ``gap_mm``."""
    out: list[tuple[int, int]] = []
    for i0, i1 in runs:
        if out and arc[i0] - arc[out[-1][1] + 1] <= gap_mm:
            out[-1] = (out[-1][0], i1)
        else:
            out.append((i0, i1))
    return out
