"""Which fitted candidates are reported as defects.

:func:`reported` fits the candidates (on an executor, :func:`_fits`) and accepts them
(:func:`_accepted`): truncation flagged, the robot's travel added, and rejected with a
warning line when wider than a shape change, a spike, or below the detection limit
(:func:`_rejection`). Streaks beside a wider defect's flank, narrower than the light
section resolves, are told before their fit (:func:`streak_candidates`) and after it
(:func:`_flank_streaks`); pieces of one bump are merged (:func:`merge_overlapping`);
:func:`measured_only` keeps the defects whose height stands clear of its 1-sigma. Sizes
mm, angles degrees.
"""

from __future__ import annotations

from collections.abc import Iterable, Sequence
from concurrent.futures import Executor
from dataclasses import replace

import numpy as np

from omnipipe.analysis.defect_fit import fit_candidate, fit_candidate_job, unfitted
from omnipipe.analysis.defect_search import Scales
from omnipipe.analysis.defect_truncation import truncation
from omnipipe.analysis.wall_profile import WallSamples
from omnipipe.contract import Defect
from omnipipe.executor import InlineExecutor, ordered_map, shared_fields


def reported(
    samples: WallSamples,
    sc: Scales,
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
    defects, masks, flagged = _accepted_unstreaked(samples, sc, candidates, fits, limits, warnings, streaks)
    if streaks - flagged:
        del warnings[told:]
        for i in sorted(streaks - flagged):
            sign, _, _, d0 = candidates[i]
            fits[i] = fit_candidate(samples, d0, sign, sc.sample_spacing, sc.typical_spacing, *blur)
        defects, masks, _ = _accepted_unstreaked(samples, sc, candidates, fits, limits, warnings)
    return defects, masks


def _fits(
    samples: WallSamples,
    sc: Scales,
    candidates: list[tuple[float, str, np.ndarray, Defect]],
    streaks: set[int],
    blur: tuple[float, float],
    executor: Executor | None,
) -> list[tuple[Defect, np.ndarray]]:
    """Each candidate's model fit and mask (:func:`.defect_fit.fit_candidate`, on ``executor``'s workers, in
    order; a local pool's read the samples from the run's scratch: not pickled per
    candidate); the ``streaks`` (candidate indices) keep their rough measurement
    (:func:`.defect_fit.unfitted`), unfitted."""
    ex = executor or InlineExecutor()
    todo = [i for i in range(len(candidates)) if i not in streaks]
    sent = shared_fields(samples, ex) if todo else samples
    jobs = ((sent, candidates[i][3], candidates[i][0], sc.sample_spacing, sc.typical_spacing, *blur) for i in todo)
    out: list[tuple[Defect, np.ndarray]] = [
        unfitted(samples, d0, sign, sc.sample_spacing, sc.typical_spacing) if i in streaks else (d0, np.zeros(0, np.intp))
        for i, (sign, _, _, d0) in enumerate(candidates)
    ]
    for i, fit in zip(todo, ordered_map(ex, fit_candidate_job, jobs), strict=True):
        out[i] = fit
    return out


def _accepted_unstreaked(
    samples: WallSamples,
    sc: Scales,
    candidates: list[tuple[float, str, np.ndarray, Defect]],
    fits: list[tuple[Defect, np.ndarray]],
    limits: tuple[float, float, float],
    warnings: list[str],
    unfitted_streaks: set[int] | frozenset[int] = frozenset(),
) -> tuple[list[Defect], list[np.ndarray], set[int]]:
    """The reported defects (:func:`_accepted`) without the streaks beside a wider one's
    flank (:func:`_flank_streaks`), their masks and the indices in ``candidates`` of the
    streaks flagged; ``limits``: the widest defect (mm around the pipe), the detection
    limit (mm) and the light section's resolution (mm); ``unfitted_streaks``: the
    candidates not fitted on purpose (:func:`streak_candidates`)."""
    max_width, limit, resolution = limits
    defects, masks, widths, source = _accepted(
        samples, sc, candidates, fits, (max_width, limit), warnings, unfitted_streaks
    )
    keep = _flank_streaks(defects, widths, resolution, samples.circumference_mm, warnings)
    pick = np.flatnonzero(keep)
    return [defects[i] for i in pick], [masks[i] for i in pick], {source[i] for i in np.flatnonzero(~keep)}


def streak_candidates(
    samples: WallSamples, candidates: Sequence[tuple[np.ndarray, Defect]], resolution_mm: float
) -> list[int]:
    """Indices of the candidates (sample indices, rough measurement :func:`.defect_fit.rough_measure`) that
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


def unfitted_warnings(defects: Sequence[Defect]) -> list[str]:
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
    sc: Scales,
    candidates: list[tuple[float, str, np.ndarray, Defect]],
    fits: Iterable[tuple[Defect, np.ndarray]],
    limits: tuple[float, float],
    warnings: list[str],
    unfitted_streaks: set[int] | frozenset[int] = frozenset(),
) -> tuple[list[Defect], list[np.ndarray], list[float], list[int]]:
    """The fitted candidates that are reported (truncation flagged, travel added), their
    masks, how wide each is around the pipe (mm: the fitted width, or the arc its
    samples span without a fit) and its index in ``candidates``; a line is appended to
    ``warnings`` for each rejected or truncated one. ``limits``: the widest defect (mm
    around the pipe) and the detection limit (mm). A candidate on one ring whose model
    fit failed (not one of ``unfitted_streaks``, left unfitted on purpose) is rejected:
    one ring gives no profile along the pipe, and without the fit nothing sizes it or
    tells it from the ring's own error (random-features-small seed 16: an 11 mm "dent"
    on one ring tilted into an unfound joint's gap)."""
    max_width_mm, limit = limits
    defects: list[Defect] = []
    masks: list[np.ndarray] = []
    widths: list[float] = []
    source: list[int] = []
    for i, ((_, kind, members, d0), (d, mask)) in enumerate(zip(candidates, fits, strict=True)):
        d, cut_by = truncation(samples, d, d0.height_mm, members, sc)
        rejected = _rejection(d, kind, max_width_mm, limit)
        if rejected is None and not d.fitted and i not in unfitted_streaks and len(np.unique(samples.ring[members])) == 1:
            rejected = (
                f"{kind} candidate at {d.axial_start_mm:.0f} mm, {d.angle_deg:.0f} deg ({len(members)} samples "
                f"up to {d.height_mm:.2f} mm) seen by one ring, and its model fit failed: nothing sizes it or "
                "tells it from the ring's own error (a ring tilted into a gap, stray peaks); not reported as a defect"
            )
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


def merge_overlapping(
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
