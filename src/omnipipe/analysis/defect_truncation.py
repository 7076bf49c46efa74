"""Candidates and defects at the edge of the measured wall.

Before the model fit, :func:`one_sided` drops (with a warning line) a candidate that
cannot be told from the run's end or a feature: seen by one ring with wall measured on
one side only, inside a found feature's zone, at a lateral's rim, on rings running
slanted across a joint's band (:func:`_crossed_band`) or steeper than any dent
(:func:`_mid_run_reason`). After it, :func:`truncation` flags a defect that runs past the
measured stretch (the run's ends, an unmeasured gap, the wall unmeasured around the ring:
:func:`_cut_around`) and clips it to the measured part. Positions in mm (contract
convention along the pipe, arc length around it).
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import replace

import numpy as np

from omnipipe.analysis.defect_search import FeatureZone, Scales
from omnipipe.analysis.wall_profile import WallSamples, axial_range
from omnipipe.contract import Defect


def truncation(
    s: WallSamples, d: Defect, top_mm: float, members: np.ndarray, sc: Scales
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


def _cut_around(s: WallSamples, d: Defect, members: np.ndarray, sc: Scales) -> bool:
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


def one_sided(
    s: WallSamples, sc: Scales, members: np.ndarray, kind: str, zones: Sequence[FeatureZone], warnings: list[str]
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
    idx = axial_range(s, lo - wide, hi + wide)  # the other rings' samples within reach only
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
