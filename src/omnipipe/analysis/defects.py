"""Bulges and dents from the radial deviation map (the paper's future work, Sec. VIII).

The deviation of a wall point is its distance from the axis minus the fitted wall
radius at its station and angle: negative for a bulge (into the pipe), positive
for a dent. The fitted wall is each station's own section (:mod:`.stations`: an ellipse
per ring, on the wall above any standing water, about the ring's own centre), so an
oval, tapering or bending pipe is the reference, never a defect; :class:`WallSamples`
carries those deviations. Candidates are connected groups of points whose deviation exceeds a
threshold (``min_height_mm`` and a multiple of the measured noise) with a neighbour on
their ring at least half as far out (lone samples are extraction outliers), linked
across neighbouring rings and around the pipe's seam.

Each candidate is first measured roughly from its samples beyond the threshold
(largest deviation, extent, weighted centre); that is only the starting point of the
model fit of :mod:`.sizing` (a raised-cosine plateau bump in arc length and axial
position, least squares over the defect and the wall around it), which gives the
reported height, width, length, axial start and angle and their standard
uncertainties. A fitted defect lower than the run's detection limit
(:func:`.sizing.detection_limit`) is not reported. Each is a
:class:`~omnipipe.contract.Defect`.
"""

from __future__ import annotations

import math
from collections.abc import Iterable, Iterator, Sequence
from concurrent.futures import Executor
from dataclasses import dataclass, replace

import numpy as np
from scipy.sparse import coo_matrix
from scipy.sparse.csgraph import connected_components
from scipy.spatial import cKDTree

from omnipipe.analysis.ring_spans import RingSpans
from omnipipe.analysis.sizing import BumpFit, detection_limit, fit_bump, plateau
from omnipipe.contract import Defect
from omnipipe.executor import InlineExecutor, ordered_map, shared_fields
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
            :func:`find_defects` sorts them once (:func:`with_axial_order`), and each
            candidate's window is then a slice of that order (:func:`_axial_range`).
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


def _axial_range(s: WallSamples, lo: float, hi: float) -> np.ndarray:
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


@dataclass(frozen=True)
class FeatureZone:
    """Where a found feature (a joint's gap, a lateral's opening) may reach, with its
    uncertainty: a detection there seen by one ring cannot be told from the feature's rim.

    Attributes:
        axial_from_mm, axial_to_mm: the axial band (contract convention, mm).
        arc_mm: centre of the zone around the pipe (mm, as :attr:`WallSamples.arc_mm`), or
            None: all around (a joint).
        half_arc_mm: half its extent around the pipe (mm; ignored without ``arc_mm``).
        label: what it is, for the warning (e.g. "the joint at -69.3 mm").
    """

    axial_from_mm: float
    axial_to_mm: float
    label: str
    arc_mm: float | None = None
    half_arc_mm: float = 0.0

    def inside(self, sigma_mm: np.ndarray, arc_mm: np.ndarray, circumference_mm: float) -> np.ndarray:
        """(M,) True for the points (sigma_mm, arc_mm) inside the zone."""
        inside = (sigma_mm >= self.axial_from_mm) & (sigma_mm <= self.axial_to_mm)
        if self.arc_mm is not None:
            c = circumference_mm
            du = np.abs((arc_mm - self.arc_mm + 0.5 * c) % c - 0.5 * c)
            inside &= du <= self.half_arc_mm
        return inside

    def holds(self, sigma_mm: np.ndarray, arc_mm: np.ndarray, circumference_mm: float) -> bool:
        """Whether every point (sigma_mm, arc_mm) lies inside the zone."""
        return bool(self.inside(sigma_mm, arc_mm, circumference_mm).all())


@dataclass
class DefectSearch:
    """What :func:`find_defects` found.

    Attributes:
        defects: largest first, each with its 1-sigma uncertainties, ``points`` (samples
            beyond the threshold) and ``travel_mm`` (the robot's travel from the first
            frame to the rings at the defect's start). The axial sigmas hold the fit and
            the ring sampling only (not the camera motion's scale).
        warnings: one line per rejected candidate.
        noise_mm: robust sigma of the deviation map.
        threshold_mm: sample threshold of the detector.
        detection_limit_mm: smallest height of the reference defect detected with >= 95 %
            probability (:func:`.sizing.detection_limit`); no reported defect is lower.
        ring_spacing_mm: median axial distance between consecutive rings.
        sample_spacing_mm: median arc length between samples along a ring.
        masks: per reported defect, the ascending indices of the samples its fitted bump
            covers (model above 1 % of its height), for refitting the wall without it.
    """

    defects: list[Defect]
    warnings: list[str]
    noise_mm: float = float("nan")
    threshold_mm: float = float("nan")
    detection_limit_mm: float = float("nan")
    ring_spacing_mm: float = float("nan")
    sample_spacing_mm: float = float("nan")
    masks: list[np.ndarray] | None = None

    def __iter__(self) -> Iterator[list[Defect] | list[str]]:
        """(defects, warnings) = find_defects(...) keeps working."""
        return iter((self.defects, self.warnings))


@dataclass(frozen=True)
class _Scales:
    """The sampling of a deviation map, the detector's threshold and its link distances.

    Attributes:
        noise: robust sigma of the deviations (mm).
        threshold: sample threshold (mm).
        ring_ids, ring_sigma: the rings present and their median axial positions (mm).
        spacing: 90th percentile of the ring gaps (mm): the wide gaps of a slow gait.
        typical_spacing: median ring gap (mm).
        sample_spacing: median arc length between samples along a ring (mm).
        ds, du: link distances across rings and along a ring (mm).
    """

    noise: float
    threshold: float
    ring_ids: np.ndarray
    ring_sigma: np.ndarray
    spacing: float
    typical_spacing: float
    sample_spacing: float
    ds: float
    du: float


def _scales(samples: WallSamples, min_height_mm: float, noise_factor: float) -> _Scales:
    """Noise, threshold and link scales of ``samples``: along the ring a few sample
    spacings, across rings 1.5 (wide) ring spacings."""
    dev, sigma = samples.deviation_mm, samples.sigma_mm
    spread = dev - np.median(dev)  # one whole-run temporary, then in place
    noise = 1.4826 * float(np.median(np.abs(spread, out=spread), overwrite_input=True))
    del spread
    threshold = max(min_height_mm, noise_factor * noise)
    # Each ring's samples on their own (no index of every sample held).
    spans = RingSpans(samples.ring)
    ring_ids = spans.rings
    ring_sigma = np.array([np.median(spans.values(i, sigma)) for i in range(len(spans))])
    # Ring spacing varies with the gait (slow start and stop): link across the wide gaps too.
    gaps = np.diff(np.sort(ring_sigma))
    spacing = float(np.percentile(gaps, 90)) if len(ring_ids) > 1 else 10.0
    typical_spacing = float(np.median(gaps)) if len(ring_ids) > 1 else 10.0
    counts = np.bincount(samples.ring)
    sample_spacing = samples.circumference_mm / max(float(np.median(counts[counts > 0])), 1.0)
    return _Scales(
        noise=noise,
        threshold=threshold,
        ring_ids=ring_ids,
        ring_sigma=ring_sigma,
        spacing=spacing,
        typical_spacing=typical_spacing,
        sample_spacing=sample_spacing,
        ds=max(1.5 * spacing, 2.0),
        du=max(3.0 * sample_spacing, 1.0),
    )


def find_defects(
    samples: WallSamples,
    *,
    min_height_mm: float,
    noise_factor: float,
    min_points: int,
    grid_mm: float,
    max_width_fraction: float = 0.5,
    limit_width_mm: float = 10.0,
    limit_length_mm: float = 20.0,
    ring_blur_mm: float = 0.0,
    axial_blur_mm: float = 0.0,
    zones: Sequence[FeatureZone] = (),
    executor: Executor | None = None,
) -> DefectSearch:
    """Detect and measure bulges and dents (the candidates' model fits on ``executor``,
    :mod:`omnipipe.executor`; None: here; the result is the same).

    Args:
        samples: the wall points.
        min_height_mm: smallest deviation reported as a defect.
        noise_factor: the threshold is also at least this many robust noise sigmas.
        min_points: a candidate needs this many points beyond the threshold.
        grid_mm: kept for the configuration's sake (the rough measurement that the model
            fit starts from no longer uses a grid).
        max_width_fraction: candidates wider than this fraction of the circumference are
            a shape change (ovality, a fit problem), not a local defect: reported as warnings.
        limit_width_mm, limit_length_mm: the reference defect of the detection limit.
        ring_blur_mm: the light section's Gaussian smoothing along the ring (mm), fitted
            with each defect (:func:`omnipipe.analysis.sizing.seen_bump_model`).
        axial_blur_mm: the same along the pipe axis (mm).
        zones: the found features' reach (:class:`FeatureZone`): a candidate seen by one
            ring inside one is a warning, not a defect (:func:`_one_sided`), as is one seen
            by one ring at the edge of the measured wall.
    """
    warnings: list[str] = []
    if len(samples.deviation_mm) < 10:
        return DefectSearch([], warnings, masks=[])
    samples = with_axial_order(samples)
    sc = _scales(samples, min_height_mm, noise_factor)
    limit = detection_limit(
        noise_mm=sc.noise,
        threshold_mm=sc.threshold,
        sample_spacing_mm=sc.sample_spacing,
        ring_spacing_mm=sc.typical_spacing,
        min_points=min_points,
        width_mm=limit_width_mm,
        length_mm=limit_length_mm,
    )
    candidates = [
        (sign, kind, members, _rough(samples, members, sign, kind, sc.sample_spacing, sc.typical_spacing))
        for sign, kind in ((-1.0, "bulge"), (1.0, "dent"))
        for members in _clusters(samples, sc, sign, min_points)
        if not _one_sided(samples, sc, members, kind, zones, warnings)
    ]
    # The light section resolves nothing narrower than its blur's full width at half height.
    limits = (max_width_fraction * samples.circumference_mm, limit, 2.355 * ring_blur_mm)
    defects, masks = _reported(samples, sc, candidates, limits, (ring_blur_mm, axial_blur_mm), executor, warnings)
    defects, masks = _merge_overlapping(defects, masks, samples.circumference_mm)
    warnings.extend(_unfitted_warnings(defects))
    order_h = np.argsort([-d.height_mm for d in defects], kind="stable")
    return DefectSearch(
        [defects[i] for i in order_h],
        warnings,
        noise_mm=sc.noise,
        threshold_mm=sc.threshold,
        detection_limit_mm=limit,
        ring_spacing_mm=sc.typical_spacing,
        sample_spacing_mm=sc.sample_spacing,
        masks=[masks[i] for i in order_h],
    )


def _reported(
    samples: WallSamples,
    sc: _Scales,
    candidates: list[tuple[float, str, np.ndarray, Defect]],
    limits: tuple[float, float, float],
    blur: tuple[float, float],
    executor: Executor | None,
    warnings: list[str],
) -> tuple[list[Defect], list[np.ndarray]]:
    """The candidates' model fits that are reported and their masks (:func:`_accepted_unstreaked`;
    ``limits`` as there, ``blur``: the ring's and the axial blur, mm).

    A streak beside a wider candidate's flank (:func:`streak_candidates`) is told before
    its fit, which cannot converge (nothing pins its width), and keeps its rough
    measurement for its warning. Should the fitted neighbours not confirm it (it is not
    flagged after the fits), it is fitted after all and the fits are accepted again: the
    result is the one of fitting every candidate, up to the streaks' warnings' numbers."""
    streaks = set(streak_candidates(samples, [(members, d0) for _, _, members, d0 in candidates], limits[2]))
    fits = _fits(samples, sc, candidates, streaks, blur, executor)
    told = len(warnings)
    defects, masks, flagged = _accepted_unstreaked(samples, sc, candidates, fits, limits, warnings)
    if streaks - flagged:
        del warnings[told:]
        for i in sorted(streaks - flagged):
            sign, _, _, d0 = candidates[i]
            fits[i] = _fit(samples, d0, sign, sc.sample_spacing, sc.typical_spacing, *blur)
        defects, masks, _ = _accepted_unstreaked(samples, sc, candidates, fits, limits, warnings)
    return defects, masks


def _fits(
    samples: WallSamples,
    sc: _Scales,
    candidates: list[tuple[float, str, np.ndarray, Defect]],
    streaks: set[int],
    blur: tuple[float, float],
    executor: Executor | None,
) -> list[tuple[Defect, np.ndarray]]:
    """Each candidate's model fit and mask (:func:`_fit`, on ``executor``'s workers, in
    order; a local pool's read the samples from the run's scratch: not pickled per
    candidate); the ``streaks`` (candidate indices) keep their rough measurement
    (:func:`_unfitted`), unfitted."""
    ex = executor or InlineExecutor()
    todo = [i for i in range(len(candidates)) if i not in streaks]
    sent = shared_fields(samples, ex) if todo else samples
    jobs = ((sent, candidates[i][3], candidates[i][0], sc.sample_spacing, sc.typical_spacing, *blur) for i in todo)
    out: list[tuple[Defect, np.ndarray]] = [
        _unfitted(samples, d0, sign, sc.sample_spacing, sc.typical_spacing) if i in streaks else (d0, np.zeros(0, np.intp))
        for i, (sign, _, _, d0) in enumerate(candidates)
    ]
    for i, fit in zip(todo, ordered_map(ex, _fit_job, jobs), strict=True):
        out[i] = fit
    return out


def _accepted_unstreaked(
    samples: WallSamples,
    sc: _Scales,
    candidates: list[tuple[float, str, np.ndarray, Defect]],
    fits: list[tuple[Defect, np.ndarray]],
    limits: tuple[float, float, float],
    warnings: list[str],
) -> tuple[list[Defect], list[np.ndarray], set[int]]:
    """The reported defects (:func:`_accepted`) without the streaks beside a wider one's
    flank (:func:`_flank_streaks`), their masks and the indices in ``candidates`` of the
    streaks flagged; ``limits``: the widest defect (mm around the pipe), the detection
    limit (mm) and the light section's resolution (mm)."""
    max_width, limit, resolution = limits
    defects, masks, widths, source = _accepted(samples, sc, candidates, fits, max_width, limit, warnings)
    keep = _flank_streaks(defects, widths, resolution, samples.circumference_mm, warnings)
    pick = np.flatnonzero(keep)
    return [defects[i] for i in pick], [masks[i] for i in pick], {source[i] for i in np.flatnonzero(~keep)}


def streak_candidates(
    samples: WallSamples, candidates: Sequence[tuple[np.ndarray, Defect]], resolution_mm: float
) -> list[int]:
    """Indices of the candidates (sample indices, rough measurement :func:`_rough`) that
    are streaks beside a wider one's flank, told before any fit: the arc their samples
    span around the pipe (:func:`_extent_around`) is below ``resolution_mm`` (the light
    section's), and their rough centre lies beside a same-kind candidate spanning at
    least that (:func:`_beside`, on the rough measurements), as :func:`_flank_streaks`
    tells them after the fits. Nothing pins such a streak's width, height and flanks:
    its fit does not converge."""
    if resolution_mm <= 0 or len(candidates) < 2:
        return []
    circ = samples.circumference_mm
    spans = [_extent_around(samples, m) for m, _ in candidates]
    wide = [j for j, span in enumerate(spans) if span >= resolution_mm]
    return [
        i
        for i, (_, d) in enumerate(candidates)
        if spans[i] < resolution_mm and any(candidates[j][1].kind == d.kind and _beside(d, candidates[j][1], circ) for j in wide)
    ]


def _beside(d: Defect, e: Defect, circ: float) -> bool:
    """Whether ``d``'s centre lies beside ``e`` (on a ``circ`` mm circumference): within
    1.5 x e's width around the pipe and along its length (from half its length before its
    start to half after its end)."""
    zc, uc = d.axial_start_mm + 0.5 * d.length_mm, d.angle_deg / 360.0 * circ
    du = abs((e.angle_deg / 360.0 * circ - uc + 0.5 * circ) % circ - 0.5 * circ)
    return du <= 1.5 * e.width_mm and e.axial_start_mm - 0.5 * e.length_mm <= zc <= e.axial_start_mm + 1.5 * e.length_mm


def _unfitted_warnings(defects: Sequence[Defect]) -> list[str]:
    """A warning per defect whose model fit failed (its size is the rough measurement)."""
    return [
        f"{d.kind} at {d.axial_start_mm:.0f} mm, {d.angle_deg:.0f} deg: the model fit "
        "failed (a crest extrapolated far above the samples, or too few samples); its size is "
        "the rough grid measurement, without uncertainty"
        for d in defects
        if not d.fitted
    ]


def _accepted(
    samples: WallSamples,
    sc: _Scales,
    candidates: list[tuple[float, str, np.ndarray, Defect]],
    fits: Iterable[tuple[Defect, np.ndarray]],
    max_width_mm: float,
    limit: float,
    warnings: list[str],
) -> tuple[list[Defect], list[np.ndarray], list[float], list[int]]:
    """The fitted candidates that are reported (truncation flagged, travel added), their
    masks, how wide each is around the pipe (mm: the fitted width, or the arc its
    samples span without a fit) and its index in ``candidates``; a line is appended to
    ``warnings`` for each rejected or truncated one."""
    defects: list[Defect] = []
    masks: list[np.ndarray] = []
    widths: list[float] = []
    source: list[int] = []
    for i, ((_, kind, members, d0), (d, mask)) in enumerate(zip(candidates, fits, strict=True)):
        d, cut_by = _truncation(samples, d, d0.height_mm, members, sc)
        rejected = _rejection(d, kind, max_width_mm, limit)
        if rejected:
            warnings.append(rejected)
            continue
        travel = round(_travel(samples, d.axial_start_mm, sc.ring_ids, sc.ring_sigma), 2)
        defects.append(replace(d, points=len(members), travel_mm=travel))
        masks.append(mask)
        widths.append(d.width_mm if d.fitted else _extent_around(samples, members))
        source.append(i)
        if cut_by:
            warnings.append(
                f"{kind} at {d.axial_start_mm:.0f} mm, {d.angle_deg:.0f} deg runs past "
                f"{cut_by}: truncated, its sizes are those of the measured part (lower bounds)"
            )
    return defects, masks, widths, source


def measured_only(defects: Sequence[Defect]) -> tuple[list[Defect], list[str]]:
    """The defects whose height stands clear of its 1-sigma (the fit's with the terms it
    cannot see: a candidate shorter or narrower than the light section's blur has a
    height the blur's uncertainty leaves open), and a warning line per other one: its
    height is not measured, nothing tells it from the wall (random-features-small seed
    30: a dent 7.4 +- 10.4 mm, 3.4 mm long, on a ring straddling a reducer's start;
    seed 1: 12.6 +- 56 mm on the first ring of a 15 mm long reducer). A defect without a
    sigma (its fit failed, a warning of its own) is kept."""
    kept, warnings = [], []
    for d in defects:
        if d.height_sigma_mm is not None and d.height_sigma_mm >= d.height_mm:
            warnings.append(
                f"{d.kind} candidate at {d.axial_start_mm:.0f} mm, {d.angle_deg:.0f} deg: height "
                f"{d.height_mm:.1f} +- {d.height_sigma_mm:.1f} mm, not measured (within its "
                f"1-sigma of the wall; {d.width_mm:.1f} x {d.length_mm:.1f} mm across): not "
                "reported as a defect"
            )
        else:
            kept.append(d)
    return kept, warnings


def _extent_around(s: WallSamples, members: np.ndarray) -> float:
    """Arc length (mm) the samples ``members`` span around the pipe (across the seam)."""
    circ = s.circumference_mm
    u = s.arc_mm[members]
    u = (u - u[0] + 0.5 * circ) % circ - 0.5 * circ
    return float(np.ptp(u)) if len(u) else 0.0


def _flank_streaks(
    defects: list[Defect], widths: list[float], resolution_mm: float,
    circ: float, warnings: list[str],
) -> np.ndarray:
    """(D,) False for the streaks beside another defect's flank: a detection narrower
    around the pipe (``widths``, mm) than the light section resolves (``resolution_mm``:
    the ring blur's full width at half height) whose centre lies within 1.5 widths of a
    wider defect of the same kind, beside it, and along its length. Such streaks (one or
    two samples per ring, the wider defect's depth, at the same angle over several
    rings) are extraction artefacts of the steep flank (the continuous run's two false
    dents); they cannot be sized: each is a warning, not a defect."""
    keep = np.ones(len(defects), bool)
    for i, d in enumerate(defects):
        if widths[i] >= resolution_mm:
            continue
        for j, e in enumerate(defects):
            if j == i or e.kind != d.kind or widths[j] < resolution_mm:
                continue
            if _beside(d, e, circ):
                keep[i] = False
                warnings.append(
                    f"{d.kind} candidate at {d.axial_start_mm:.0f} mm, {d.angle_deg:.0f} deg ({d.points} samples "
                    f"up to {d.height_mm:.2f} mm, {widths[i]:.2f} mm wide): narrower than the light section "
                    f"resolves ({resolution_mm:.2f} mm) beside the flank of the {e.kind} at "
                    f"{e.axial_start_mm:.0f} mm, {e.angle_deg:.0f} deg: an extraction artefact that cannot be "
                    "sized, flagged here, not reported as a defect"
                )
                break
    return keep


def _fit_job(
    job: tuple[WallSamples, Defect, float, float, float, float, float],
) -> tuple[Defect, np.ndarray]:
    """:func:`_fit` of one candidate, its arguments as one tuple (for the executor)."""
    return _fit(*job)


def _truncation(
    s: WallSamples, d: Defect, top_mm: float, members: np.ndarray, sc: _Scales
) -> tuple[Defect, str | None]:
    """The defect flagged ``truncated`` when it runs past the measured stretch: its
    samples beyond the threshold lie on the first or last ring, its extent reaches beyond
    them, it overlaps an unmeasured gap (rings further apart than 3 wide ring spacings
    and 5 mm), or the wall beside it around the ring was not measured (:func:`_cut_around`). Its extent is then clipped to the measured rings (the length a lower bound,
    1-sigma one ring spacing) and its height is the larger of the fit's and the largest
    measured deviation ``top_mm`` (a bump cut off mid-flank is fitted too low). Returns
    (defect, what cut it or None)."""
    z = np.asarray(sc.ring_sigma, float)
    if len(z) < 2:
        return d, None
    lo, hi = float(z.min()), float(z.max())
    on = set(np.unique(s.ring[members]).tolist())
    start, end = d.axial_start_mm, d.axial_end_mm
    cuts = []
    if start < lo or int(sc.ring_ids[np.argmin(z)]) in on:
        cuts.append(f"the start of the measured stretch (first ring at {lo:.1f} mm)")
    if end > hi or int(sc.ring_ids[np.argmax(z)]) in on:
        cuts.append(f"the end of the measured stretch (last ring at {hi:.1f} mm)")
    zs = np.sort(z)
    wide = np.diff(zs) > max(3.0 * sc.spacing, 5.0)
    cuts += [
        f"an unmeasured gap ({a:.1f} to {b:.1f} mm)"
        for a, b in zip(zs[:-1][wide], zs[1:][wide], strict=True)
        if start < b and end > a
    ]
    if _cut_around(s, d, members, sc):
        cuts.append("an unmeasured part of the wall around the ring (e.g. below the water line)")
    if not cuts:
        return d, None
    new_start, new_end = max(start, lo), min(end, hi)
    if new_end <= new_start:
        zm = s.sigma_mm[members]
        new_start, new_end = float(zm.min()), float(zm.max())
    spacing = round(max(sc.typical_spacing, 0.1), 4)
    return replace(
        d,
        axial_start_mm=round(new_start, 3),
        length_mm=round(new_end - new_start, 3),
        length_sigma_mm=spacing,
        axial_start_sigma_mm=spacing if new_start != start else d.axial_start_sigma_mm,
        height_mm=round(max(d.height_mm, top_mm), 3),
        truncated=True,
    ), " and ".join(cuts)


def _cut_around(s: WallSamples, d: Defect, members: np.ndarray, sc: _Scales) -> bool:
    """Whether the wall beside the defect went unmeasured on at least half of its rings:
    within its width plus 5 mm each side, a stretch of the ring without samples longer
    than 5 sample spacings and 5 mm (standing water, a shadow)."""
    circ = s.circumference_mm
    centre = d.angle_deg / 360.0 * circ
    half = 0.5 * d.width_mm + 5.0
    min_gap = max(5.0 * sc.sample_spacing, 5.0)
    rings = np.unique(s.ring[members])
    cut = 0
    for r in rings:
        on = s.ring == r
        u = (s.arc_mm[on] - centre + 0.5 * circ) % circ - 0.5 * circ
        u = np.sort(u[np.abs(u) <= half])
        edges = np.concatenate([[-half], u, [half]])
        if np.max(np.diff(edges)) > min_gap:
            cut += 1
    return cut * 2 >= len(rings) > 0


SPIKE_RATIO = 3.0
"""A candidate deeper than this many times its width and its length is no wall
deformation (random-features-small seed 0: 217 mm deep over 11 x 8 mm, three samples
of one ring past a reducer under water; the simulated defects are at most 0.8 as deep
as they are long)."""


def _rejection(d: Defect, kind: str, max_width_mm: float, limit: float) -> str | None:
    """Why a fitted candidate is not reported (a warning line), or None."""
    if d.width_mm > max_width_mm:
        return (
            f"{kind} candidate at {d.axial_start_mm:.0f} mm spans {d.width_mm:.0f} mm of the "
            "circumference: a shape change, not reported as a defect"
        )
    if d.height_mm > SPIKE_RATIO * max(d.width_mm, d.length_mm):
        return (
            f"{kind} candidate at {d.axial_start_mm:.0f} mm, {d.angle_deg:.0f} deg: {d.height_mm:.1f} mm "
            f"deep but only {d.width_mm:.1f} x {d.length_mm:.1f} mm across: a spike (stray light, e.g. "
            "a reflection off standing water or a mortar joint, or a hole's rim), not a wall "
            "deformation; not reported as a defect"
        )
    if not d.height_mm >= limit:
        return (
            f"{kind} candidate at {d.axial_start_mm:.0f} mm, {d.angle_deg:.0f} deg: fitted "
            f"height {d.height_mm:.2f} mm is below the detection limit {limit:.2f} mm, not reported"
        )
    return None


def _clusters(
    samples: WallSamples, sc: _Scales, sign: float, min_points: int
) -> Iterator[np.ndarray]:
    """Sample indices of each candidate of one sign (-1: bulges, +1: dents): connected
    groups of supported samples beyond the threshold, at least ``min_points`` strong."""
    arc, sigma, circ = samples.arc_mm, samples.sigma_mm, samples.circumference_mm
    cand = _supported_beyond(samples, sign, sc)
    if len(cand) < min_points:
        return
    ds, du = sc.ds, sc.du
    box = np.array([circ / du, (np.ptp(sigma) + 4 * ds) / ds])
    xy = np.column_stack([arc[cand] / du % box[0], (sigma[cand] - sigma.min() + ds) / ds])
    pairs = cKDTree(xy, boxsize=box).query_pairs(1.0, output_type="ndarray")
    graph = coo_matrix((np.ones(len(pairs)), (pairs[:, 0], pairs[:, 1])), shape=(len(cand),) * 2)
    n_comp, label = connected_components(graph, directed=False)
    for c in range(n_comp):
        members = cand[label == c]
        if len(members) < min_points:
            continue
        if len(np.unique(samples.ring[members])) == 1 and len(members) < 2 * min_points:
            # A speck on one ring, narrower than a few samples: an extraction outlier
            # cluster (seen beside deep, steep defects), below any size the run resolves.
            continue
        yield members


def _one_sided(
    s: WallSamples, sc: _Scales, members: np.ndarray, kind: str, zones: Sequence[FeatureZone], warnings: list[str]
) -> bool:
    """Whether a candidate seen by one ring only has one-sided support: on one side
    along the axis no other ring measured the wall at its angles within 3 wide ring
    spacings (and 5 mm) - the run's first or last ring, a ring beside a feature's
    excluded band or an unmeasured stretch - or it lies inside a found feature's zone.
    The wall beyond it was not measured (or is the feature's rim): it cannot be told
    from the run's end or the feature and cannot be sized; a warning line is appended
    and it is not a defect. A candidate seen by two rings or more is dropped here only
    where its samples beyond the threshold reach into a found lateral's zone: it is the
    opening's rim (the wall around it lit by the branch, the rim's stray light), not a
    deformation of the wall (random-features-small seeds 6, 9, 14, 20, 31: bulges and
    dents 4-90 mm high at the holes' rims); a dent beside the opening, clear of its
    zone, stays a defect, and so does one seen by several rings in a joint's zone. Other
    candidates seen by one ring mid-run: :func:`_mid_run_reason`."""
    circ = s.circumference_mm
    zs, arc = s.sigma_mm[members], s.arc_mm[members]
    rim = next((q for q in zones if q.arc_mm is not None and q.inside(zs, arc, circ).any()), None)
    if rim is not None:
        dev = np.abs(s.deviation_mm[members])
        warnings.append(
            f"{kind} candidate at {float(np.median(zs)):.0f} mm ({len(members)} samples up to "
            f"{float(dev.max()):.2f} mm) lies partly within the reach of {rim.label}: the "
            "opening's rim, flagged here, not reported as a defect"
        )
        return True
    rings = np.unique(s.ring[members])
    crossed = _crossed_band(s, rings, zones)
    if crossed is not None:
        warnings.append(
            f"{kind} candidate at {float(np.median(zs)):.0f} mm ({len(members)} samples on {len(rings)} rings) "
            f"lies on rings that each run slanted across the band of {crossed.label}: each ring mixes the "
            "sections either side and its one profile cannot follow the step; flagged here, not reported as a defect"
        )
        return True
    if len(rings) != 1:
        return False
    ref = float(arc[0])
    du = (arc - ref + 0.5 * circ) % circ - 0.5 * circ
    wide = max(3.0 * sc.spacing, 5.0)
    lo, hi = zs.min(), zs.max()
    idx = _axial_range(s, lo - wide, hi + wide)  # the other rings' samples within reach only
    u_all = (s.arc_mm[idx] - ref + 0.5 * circ) % circ - 0.5 * circ
    sig = s.sigma_mm[idx]
    near = (s.ring[idx] != rings[0]) & (u_all >= du.min() - sc.du) & (u_all <= du.max() + sc.du)
    before = idx[near & (sig < lo) & (sig >= lo - wide)]
    after = idx[near & (sig > hi) & (sig <= hi + wide)]
    if not len(before) or not len(after):
        why = f"one ring, with no measured wall {'before' if not len(before) else 'after'} it along the pipe"
    else:
        why = _mid_run_reason(s, members, zones, before, after)
        if why is None:
            return False
    dev = np.abs(s.deviation_mm[members])
    angle = (ref + float(np.median(du))) % circ / circ * 360.0
    head = f"{kind} candidate at {float(np.median(zs)):.0f} mm, {angle:.0f} deg ({len(members)} samples up to {float(dev.max()):.2f} mm)"
    if why.startswith("steep:"):
        warnings.append(f"{head} {why[6:]}: a streak of stray peaks along one ring, not reported as a defect")
        return True
    warnings.append(
        f"{head} seen by {why}: one-sided, it cannot be told from the run's end or "
        "a feature's rim and cannot be sized; flagged here, not reported as a defect"
    )
    return True


CROSSING_SHARE = 0.05
"""A ring runs slanted across a joint's band when at least this share of its samples
lies inside the band and at least this share outside it (:func:`_crossed_band`)."""


def _crossed_band(s: WallSamples, rings: np.ndarray, zones: Sequence[FeatureZone]) -> FeatureZone | None:
    """The found joint's band (a zone all around) that every ring of a candidate runs
    slanted across (:data:`CROSSING_SHARE` of its samples inside and outside it), or None. Such rings lie on the sections
    either side of the joint and their one wall profile cannot follow the step between
    them (random-features-small seed 1: rings tilted 14-18 deg spanning 170 mm each across
    a joint and a 585 -> 531 mm reducer, a 23 mm "dent" on five of them 40 mm before the
    band and in it). A defect on rings square to the pipe beside (or inside) a joint's
    band is no such candidate: each of its rings lies wholly inside or outside."""
    circ = s.circumference_mm
    for q in zones:
        if q.arc_mm is not None:
            continue
        crossing = True
        for k in rings:
            on = s.ring == k
            share = float(q.inside(s.sigma_mm[on], s.arc_mm[on], circ).mean())
            if not CROSSING_SHARE <= share <= 1.0 - CROSSING_SHARE:
                crossing = False
                break
        if crossing:
            return q
    return None


STEEP_RATIO = 0.5
"""A defect candidate on one ring whose height exceeds this fraction of the distance
between the clean rings either side (at its angles) rises steeper than any dent:
the simulator's 100 defects (random-features and robustness scenes) have height over
length at most 0.50, a real dent seen by one ring lies between its neighbours, so its
height over that distance is at most about that."""


def _mid_run_reason(
    s: WallSamples, members: np.ndarray, zones: Sequence[FeatureZone], before: np.ndarray, after: np.ndarray
) -> str | None:
    """Why a candidate seen by one ring mid-run (wall measured on both sides, ``before``
    and ``after`` the indices of the other rings' samples at its angles) is no defect, or
    None: it lies wholly inside a feature's zone; it reaches into a joint's band (a ring
    tilted across the joint lies on both sections, and its one profile cannot follow the
    step: random-features-small seed 30, a 12 mm "dent" on the ring crossing a 5 mm
    offset joint at a taper's start, peaking 20 mm from the band on the ring's far
    side); or it is steeper than a dent (:data:`STEEP_RATIO`; seeds 14 and 31: 7-10 mm
    over 12 samples of one ring, the clean rings 10-11 mm apart around it, texture taken
    for the laser peak along the ring)."""
    circ = s.circumference_mm
    zs, arc = s.sigma_mm[members], s.arc_mm[members]
    zone = next((q for q in zones if q.holds(zs, arc, circ)), None)
    if zone is not None:
        return f"one ring inside the reach of {zone.label}"
    band = next((q for q in zones if q.arc_mm is None and q.inside(zs, arc, circ).any()), None)
    if band is not None:
        return f"one ring reaching into the band of {band.label} (the ring mixes the sections either side)"
    height = float(np.max(np.abs(s.deviation_mm[members])))
    between = float(s.sigma_mm[after].min() - s.sigma_mm[before].max())
    if height > STEEP_RATIO * between:
        return f"steep:rises {height:.1f} mm between rings {between:.1f} mm apart that measured the wall there"
    return None


def _supported_beyond(samples: WallSamples, sign: float, sc: _Scales) -> np.ndarray:
    """Ascending indices of the samples beyond the threshold (``sign`` x deviation, -1:
    bulges, +1: dents) with a neighbour on their ring (within about 2.5 sample spacings)
    at least half the threshold out. A lone sample beyond the threshold without one is
    an extraction outlier (a blurred peak where the ring runs steeply), not wall. Taken
    about :data:`SUPPORT_BLOCK` samples (whole rings) at a time: the temporaries a
    block's, not the run's (:meth:`.ring_spans.RingSpans.blocks`)."""
    spans = RingSpans(samples.ring)
    out = []
    for sel in spans.blocks(SUPPORT_BLOCK):
        value = sign * samples.deviation_mm[sel]
        arc, ring = samples.arc_mm[sel], samples.ring[sel]
        whole = len(value) == len(samples.ring)  # one block: the neighbours wrap (a run of one ring)
        hit = np.flatnonzero((value > sc.threshold) & _supported(arc, ring, value, samples.circumference_mm, sc, whole))
        out.append(hit + sel.start if isinstance(sel, slice) else sel[hit])
    cand = np.concatenate(out) if out else np.zeros(0, np.intp)
    return cand if spans.order is None else np.sort(cand)


def _supported(
    arc: np.ndarray, ring: np.ndarray, value: np.ndarray, circ: float, sc: _Scales, wrap: bool
) -> np.ndarray:
    """(M,) bool for M samples of whole rings (``arc`` mm, ``ring``, ``value`` the signed
    deviation): the sample's neighbour before or after it along its ring (sorted by ring,
    then arc) lies within about 2.5 sample spacings and is at least half the threshold
    out. ``wrap``: the first and last samples are neighbours too (the whole run)."""
    order = np.lexsort((arc, ring))
    near_gap = 2.5 * sc.du / 3.0  # about 2.5 sample spacings along the ring
    supported = np.zeros(len(value), bool)
    for shift in (1, -1):  # the one before and after
        nb = np.roll(order, shift)
        close = (ring[nb] == ring[order]) & (
            np.abs((arc[nb] - arc[order] + 0.5 * circ) % circ - 0.5 * circ) <= near_gap
        )
        if not wrap and len(order):
            close[0 if shift == 1 else -1] = False  # its neighbour lies in another block's ring
        supported[order] |= close & (value[nb] > 0.5 * sc.threshold)
    return supported


SUPPORT_BLOCK = 1 << 16
"""Samples (whole rings) per block of :func:`_supported_beyond`."""


def _merge_overlapping(
    defects: list[Defect], masks: list[np.ndarray], circ: float
) -> tuple[list[Defect], list[np.ndarray]]:
    """One defect per bump: a detection whose centre lies inside the half-height extent of
    another of the same kind supported by more samples is a piece of it (a short, wide
    defect between two rings can fall apart into several candidate clusters); it is
    dropped and its samples join the larger one's mask (sample indices, ascending)."""
    keep = np.ones(len(defects), bool)
    masks = [np.asarray(m) for m in masks]
    order = sorted(range(len(defects)), key=lambda i: -defects[i].points)
    for rank, i in enumerate(order):
        if not keep[i]:
            continue
        a = defects[i]
        za = a.axial_start_mm + 0.5 * a.length_mm
        ua = a.angle_deg / 360.0 * circ
        for j in order[rank + 1 :]:
            b = defects[j]
            if not keep[j] or b.kind != a.kind:
                continue
            dz = abs(b.axial_start_mm + 0.5 * b.length_mm - za)
            du = abs((b.angle_deg / 360.0 * circ - ua + 0.5 * circ) % circ - 0.5 * circ)
            if dz <= 0.5 * a.length_mm and du <= 0.5 * a.width_mm:
                keep[j] = False
                masks[i] = np.union1d(masks[i], masks[j])
    return [d for d, k in zip(defects, keep, strict=True) if k], [
        m for m, k in zip(masks, keep, strict=True) if k
    ]


def _travel(s: WallSamples, axial_mm: float, ring_ids: np.ndarray, ring_sigma: np.ndarray) -> float:
    """Distance travelled from the first frame to the frames whose rings measured the
    axial position ``axial_mm`` (interpolated between rings; |axial_mm| without travels)."""
    if s.ring_travel_mm is None or not len(ring_ids):
        return abs(float(axial_mm))
    travel = np.asarray(s.ring_travel_mm, float)[ring_ids]
    order = np.argsort(ring_sigma)
    return float(np.interp(axial_mm, ring_sigma[order], travel[order]))


def _rough(
    s: WallSamples,
    members: np.ndarray,
    sign: float,
    kind: str,
    sample_spacing: float,
    ring_spacing: float,
) -> Defect:
    """Rough extent of a candidate from its samples beyond the threshold: the fit's start."""
    circ = s.circumference_mm
    value = sign * s.deviation_mm[members]
    ref = float(s.arc_mm[members[np.argmax(value)]])
    u = (s.arc_mm[members] - ref + 0.5 * circ) % circ - 0.5 * circ
    z = s.sigma_mm[members]
    w = value / value.sum()
    uc, zc = float(w @ u), float(w @ z)
    width = float(np.ptp(u)) + 2.0 * sample_spacing
    length = float(np.ptp(z)) + ring_spacing
    return Defect(
        kind=kind,
        height_mm=round(float(value.max()), 3),
        width_mm=round(width, 3),
        length_mm=round(length, 3),
        axial_start_mm=round(zc - 0.5 * length, 3),
        angle_deg=round(((ref + uc) % circ) / circ * 360.0, 3),
    )


def _window(
    s: WallSamples, d0: Defect, sample_spacing: float, ring_spacing: float
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The samples inside the fit's window about the roughly measured defect ``d0``'s
    centre: (M,) their indices (ascending), their arcs (mm, unwrapped) and axial
    positions (mm) about that centre. Only the window's axial slice of the samples is
    read (:func:`_axial_range`): the temporaries are the window's, not the run's."""
    circ = s.circumference_mm
    w0, l0 = max(d0.width_mm, sample_spacing), max(d0.length_mm, 0.5 * ring_spacing)
    zc = d0.axial_start_mm + 0.5 * l0
    hu = min(max(1.5 * w0, 0.5 * w0 + 10.0 * sample_spacing, 6.0), 0.45 * circ)
    hz = max(1.5 * l0, 0.5 * l0 + 3.0 * ring_spacing, 6.0)
    idx = _axial_range(s, zc - hz, zc + hz)
    u = (s.arc_mm[idx] - d0.angle_deg / 360.0 * circ + 0.5 * circ) % circ - 0.5 * circ
    z = s.sigma_mm[idx] - zc
    win = (np.abs(u) <= hu) & (np.abs(z) <= hz)
    return idx[win], u[win], z[win]


def _unfitted(
    s: WallSamples, d0: Defect, sign: float, sample_spacing: float, ring_spacing: float
) -> tuple[Defect, np.ndarray]:
    """A candidate left unfitted: ``d0`` and its samples in the fit's window above half
    its height (as :func:`_fit` when the fit fails; sample indices, ascending)."""
    idx, _, _ = _window(s, d0, sample_spacing, ring_spacing)
    return d0, idx[sign * s.deviation_mm[idx] > 0.5 * d0.height_mm]


def _covered(s: WallSamples, fit: BumpFit, uc: float, zc: float) -> np.ndarray:
    """Ascending indices of the samples the fitted bump covers (model above 1 % of its
    height; ``uc``, ``zc``: the fit's origin, mm around and along the pipe). A plateau is
    0 beyond half its full width plus half its ramp: only that axial slice is read."""
    circ = s.circumference_mm
    reach = 0.5 * (abs(fit.length) + abs(fit.ramp_z * fit.length)) + 1e-6
    idx = _axial_range(s, zc + fit.z0 - reach, zc + fit.z0 + reach)
    u = (s.arc_mm[idx] - uc + 0.5 * circ) % circ - 0.5 * circ
    z = s.sigma_mm[idx] - zc
    cover = (
        plateau(u - fit.u0, fit.width, fit.ramp_u * fit.width)
        * plateau(z - fit.z0, fit.length, fit.ramp_z * fit.length)
    ) > 0.01
    return idx[cover]


def _fit(
    s: WallSamples, d0: Defect, sign: float, sample_spacing: float, ring_spacing: float,
    blur_u_mm: float = 0.0,
    blur_z_mm: float = 0.0,
) -> tuple[Defect, np.ndarray]:
    """Model fit around a roughly measured defect ``d0``: the reported defect and its mask
    (sample indices, ascending; without a usable fit: ``d0``, without uncertainties, and
    its samples above half its height)."""
    circ = s.circumference_mm
    w0, l0 = max(d0.width_mm, sample_spacing), max(d0.length_mm, 0.5 * ring_spacing)
    uc = d0.angle_deg / 360.0 * circ
    zc = d0.axial_start_mm + 0.5 * l0
    idx, u, z = _window(s, d0, sample_spacing, ring_spacing)
    value = sign * s.deviation_mm[idx]
    fit = fit_bump(
        u,
        z,
        value,
        s.ring[idx],
        (d0.height_mm, 0.0, 0.0, w0, l0),
        bounds_u=(-0.5 * w0 - 2 * sample_spacing, 0.5 * w0 + 2 * sample_spacing),
        bounds_z=(-0.5 * l0 - ring_spacing, 0.5 * l0 + ring_spacing),
        blur_u_mm=blur_u_mm,
        blur_z_mm=blur_z_mm,
    )
    top = float(np.max(value)) if len(value) else 0.0
    if fit is not None and fit.height > top + 3.0 * fit.noise + 0.25 * top:
        # The bump rises far above every sample (a crest extrapolated between rings from a
        # few points): not a measurement. The rough one is reported instead.
        fit = None
    if fit is None:
        return d0, idx[value > 0.5 * d0.height_mm]
    cover = _covered(s, fit, uc, zc)
    angle = ((uc + fit.u0) % circ) / circ * 360.0
    return Defect(
        kind=d0.kind,
        height_mm=round(fit.height, 3),
        width_mm=round(fit.width, 3),
        length_mm=round(fit.length, 3),
        axial_start_mm=round(zc + fit.z0 - 0.5 * fit.length, 3),
        angle_deg=round(angle, 3),
        height_sigma_mm=round(fit.height_sigma, 4),
        width_sigma_mm=round(fit.width_sigma, 4),
        length_sigma_mm=round(fit.length_sigma, 4),
        axial_start_sigma_mm=round(fit.start_sigma, 4),
        angle_sigma_deg=round(math.degrees(fit.u0_sigma / (circ / (2 * math.pi))), 5),
        fit_noise_mm=round(fit.noise, 4),
    ), cover
