"""Joints and laterals: found in the rings, measured, and taken out of the wall.

A joint's gap and a lateral's opening are parts of a sound pipe: their points are not
wall (they would read as dents, and pull the rings' wall profiles). Each point's
deviation from its ring's wall profile (:mod:`.feature_rings`); points further out than
the threshold (``max(min_depth_mm, noise_factor x noise)``; for joints
``joint_noise_factor``) are candidates. Joints: :mod:`.joints`.

* lateral: the candidates not in a joint are linked into clusters across rings; a narrow
  cluster reaching far out (the branch wall behind the hole) is a lateral. Each ring
  crossing the hole gives a chord (centre, half-width) at its axial position; the hole's
  outline, an ellipse in (axial, arc), is fitted through the half-widths (h^2 quadratic
  in the axial position); the opening's diameter is the chord 2 R sin(b / R) of its
  circumferential semi-axis b. Sigmas by jackknife over the rings, with the rings'
  spacing along the hole and a sample's reach at its rim.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from concurrent.futures import Executor
from dataclasses import dataclass, field

import numpy as np
from scipy.sparse import coo_matrix
from scipy.sparse.csgraph import connected_components
from scipy.spatial import cKDTree

from omnipipe.analysis.centreline import Centreline
from omnipipe.analysis.defect_search import FeatureZone
from omnipipe.analysis.feature_rings import (
    FeatureConfig,
    Rings,
    raised_blocks,
    ring_deviations,
    robust_sine_fit,
)
from omnipipe.analysis.feature_types import Joint, Lateral, PointFeature
from omnipipe.analysis.joints import gap_joints, offset_joints, offset_joints_kept
from omnipipe.analysis.openings import (
    HoleExtent,
    ReturnGap,
    closes_both_sides,
    gap_clusters,
    hole_extent,
    local_gaps,
    return_gaps,
    ring_angles,
    ring_axial,
    ring_points,
)
from omnipipe.analysis.ring_spans import BLOCK as POINT_BLOCK
from omnipipe.analysis.ring_spans import RingSpans, ring_ids
from omnipipe.analysis.sample_arcs import SampleArcs, within_ellipses
from omnipipe.spill import ScratchWriter, on_disk, zeros_on_disk


@dataclass(frozen=True)
class FeatureSearch:
    """What :func:`find_features` found.

    Attributes:
        features: joints and laterals, ordered along the pipe.
        not_wall: (N,) True for the points inside a gap or an opening (and their margin).
        threshold_mm: outward deviation beyond which a point counted.
        unseen_gap_mm: the widest axial stretch between the measured rings' first and
            last samples that no sample fell in (mm): a joint gap narrower than this
            may lie there unseen.
        opening_zones: each lateral's opening (its outline's semi-axes along the axis
            and around the pipe, plus the margin and 3 sigma of its centre) for the
            defect search (:func:`feature_zones`).
        stray: (N,) True for the samples far off the wall in a cut no ring is seen to
            close (standing water's texture peaks, :func:`_closed_openings`); also in
            ``not_wall``, and no wall for the stations' water cut either.
    """

    features: list[PointFeature]
    not_wall: np.ndarray
    threshold_mm: float
    unseen_gap_mm: float = 0.0
    opening_zones: tuple[FeatureZone, ...] = ()
    stray: np.ndarray = field(default_factory=lambda: np.zeros(0, bool))


def find_features(
    config: FeatureConfig,
    line: Centreline,
    sigma: np.ndarray,
    rho: np.ndarray,
    theta: np.ndarray,
    frame: np.ndarray,
    radius: float,
    executor: Executor | None = None,
    axial_blur_mm: float = 0.0,
) -> FeatureSearch:
    """Joints and laterals among (N,) points in pipe coordinates (sigma, rho mm; theta
    rad from the centreline's normal towards its binormal; frame: ring index), ``radius``
    the nominal wall radius (mm); the rings' profile fits on ``executor``
    (:func:`.feature_rings.ring_deviations`; None: here; the result is the same);
    ``axial_blur_mm``: the light section's Gaussian sigma along the axis (mm; a hole's
    ends read from the rings' disturbance lie up to about that far out: the laterals'
    axial sigma, :func:`_lateral`)."""
    rings = ring_ids(frame)  # np.unique's, without a sorted copy of a ring-ordered frame
    dev, ring_sigma, raised = ring_deviations(config, sigma, rho, theta, frame, rings, executor)
    # Each point's deviation and ring in the run's scratch (read when needed, :mod:`omnipipe.spill`).
    dev = on_disk(dev)
    writer = ScratchWriter(len(frame), np.intp)
    for a in range(0, len(frame), POINT_BLOCK):
        writer.write(np.searchsorted(rings, frame[a : a + POINT_BLOCK]))
    ring_of = writer.array()
    # The wall's noise without the rings raised together in a block (a wide gap crossed
    # by tilted rings: each ring's wall samples stand off its neighbours' level by the
    # gap's share of its circumference, a large share of the run's samples).
    wall = ~raised_blocks(raised, ring_sigma)[ring_of]
    spread = dev[wall] if wall.any() else dev.copy()  # one copy, its deviations in place
    del wall
    spread -= np.median(spread)
    noise = 1.4826 * float(np.median(np.abs(spread, out=spread)))
    del spread
    thr = max(config.min_depth_mm, config.noise_factor * noise)
    r = Rings(sigma, rho, theta, frame, ring_of, ring_sigma, dev, noise, axial_blur_mm)
    # Joint candidates: beyond a lower threshold (a gap must also cover most of the
    # circumference), or half of it on a ring lying in a gap.
    thr_joint = max(config.min_depth_mm, config.joint_noise_factor * noise)
    cand = (dev > thr_joint) | (raised[ring_of] & (dev > 0.5 * thr_joint))
    not_wall = np.zeros(len(sigma), bool)
    unseen = _unseen_gap(sigma)
    gaps = np.diff(np.sort(ring_sigma))
    spacing = float(np.percentile(gaps, 90)) if len(gaps) else 5.0
    feats: list[PointFeature] = []
    if cand.sum() >= config.min_points:
        for f, mask in gap_joints(config, line, r, cand, max(config.joint_link_mm, 1.5 * spacing), raised):
            feats.append(f)
            not_wall |= mask
    # Laterals: the rest, linked across rings, narrow and reaching far out, and the
    # rings' stretches without returns (the light lost in the branch).
    zones = []
    lats, stray = _laterals(config, r, radius, spacing, thr, not_wall, feats)
    for f, mask, zone in lats:
        feats.append(f)
        not_wall |= mask
        zones.append(zone)
    not_wall |= stray
    # Then the joints seen by their offset alone, away from the openings (whose hole
    # pulls its rings' section centres sideways).
    feats += offset_joints(config, line, r, feats)
    feats.sort(key=lambda f: f.axial_mm)
    return FeatureSearch(feats, not_wall, thr, unseen, tuple(zones), stray)


def _deep_clusters(
    config: FeatureConfig, r: Rings, radius: float, spacing: float, thr: float, not_wall: np.ndarray
) -> tuple[list[np.ndarray], list[np.ndarray]]:
    """The samples beyond ``thr`` either way (not yet taken) linked into clusters of at
    least ``min_points``: (the outward ones on two rings or more reaching as far as an
    opening's, :func:`_opening`; all the others, one ring's too: a lost-return opening
    takes those it meets, the branch wall lit near its rim or the rim's stray samples)."""
    deep, others = [], []
    for sign in (1.0, -1.0):
        idx = np.flatnonzero((sign * r.dev > thr) & ~not_wall)
        if len(idx) < config.min_points:
            continue
        xyz = np.stack([r.sigma[idx], radius * np.cos(r.theta[idx]), radius * np.sin(r.theta[idx])], axis=1)
        pairs = cKDTree(xyz).query_pairs(max(1.5 * spacing, 3.0), output_type="ndarray")
        m = len(idx)
        graph = coo_matrix((np.ones(len(pairs)), (pairs[:, 0], pairs[:, 1])), shape=(m, m))
        _, label = connected_components(graph, directed=False)
        for lab in np.unique(label):
            members = idx[label == lab]
            if len(members) < config.min_points:
                continue
            # One ring's outliers (a reflection) are no opening by themselves.
            opening = (sign > 0 and len(np.unique(r.frame[members])) >= 2
                       and _opening(config, members, r.dev, r.theta, r.frame, radius, thr))
            (deep if opening else others).append(members)
    return deep, others


def _laterals(
    config: FeatureConfig,
    r: Rings,
    radius: float,
    spacing: float,
    thr: float,
    not_wall: np.ndarray,
    joints: Sequence[PointFeature],
) -> tuple[list[tuple[Lateral, np.ndarray, FeatureZone]], np.ndarray]:
    """The laterals: the deep clusters reaching as far as an opening's and closing on
    both sides along the axis, and the openings seen as lost returns (:mod:`.openings`)
    away from the joints, each with the other clusters it meets along the axis (the
    branch wall lit near the rim); (lateral, its not-wall mask, its opening's zone)
    each, and the (N,) mask of the stray samples (:func:`_closed_openings`)."""
    deep, others = _deep_clusters(config, r, radius, spacing, thr, not_wall)
    for i, m in enumerate(others):
        seen = _one_ring_opening(config, r, m, radius, spacing, thr, not_wall)
        if seen is not None:
            deep.append(seen)
            others[i] = np.zeros(0, int)
    deep, stray, open_cuts = _closed_openings(config, r, deep, radius, thr, not_wall)
    others = [m[~stray[m]] for m in others]
    holes = [(m, []) for m in deep]
    for cluster in _lost_openings(config, r, radius, spacing, joints, stray):
        if any(_meets(r, m, cluster, radius, spacing) for m in open_cuts):
            continue  # the cut's own end (water shallowing: ragged, narrower), no hole
        hit = [h for h in holes if _meets(r, h[0], cluster, radius, spacing)]
        if hit:
            hit[0][1].extend(cluster)
            continue
        members = np.zeros(0, int)
        grown = True
        while grown:  # the clusters it meets, and those the grown opening meets
            grown = False
            for i, m in enumerate(others):
                if len(m) and _meets(r, m, cluster, radius, spacing, members):
                    members = np.concatenate([members, m])
                    others[i] = np.zeros(0, int)
                    grown = True
        holes.append((members, list(cluster)))
    stops = [(f.axial_mm - 0.5 * f.gap_mm - config.margin_mm, f.axial_mm + 0.5 * f.gap_mm + config.margin_mm)
             for f in joints if isinstance(f, Joint)]
    planes = _ring_planes(r, thr)  # once for every hole (each ring's fit): linear in the run
    out = [_lateral(config, r, m, radius, spacing, thr, g, stops, planes) for m, g in holes]
    # Pieces of one hole (the branch wall lit in parts, the light lost between them)
    # whose openings overlap: one lateral from them all.
    merged = True
    while merged:
        merged = False
        for i in range(len(out)):
            j = next((j for j in range(i + 1, len(out)) if _one_hole(r, out[i][1], out[j][1], 0.5 * thr)), None)
            if j is not None:
                holes[i] = (np.union1d(holes[i][0], holes[j][0]), [*holes[i][1], *holes[j][1]])
                del holes[j], out[j]
                out[i] = _lateral(config, r, holes[i][0], radius, spacing, thr, holes[i][1], stops, planes)
                merged = True
                break
    return [o[:3] for o in out if o[3]], stray


def _closed_openings(
    config: FeatureConfig, r: Rings, deep: list[np.ndarray], radius: float, thr: float, not_wall: np.ndarray
) -> tuple[list[np.ndarray], np.ndarray, list[np.ndarray]]:
    """The deep clusters that rise from the wall (:func:`_rises_from_the_wall`) or close
    on both sides along the axis (:func:`.openings.closes_both_sides` about the
    cluster's middle half around the pipe); the (N,) mask of the others' samples and their rings' samples beyond ``thr``
    outwards over each ring's share of their angles: stray laser peaks in a cut the run
    never sees closing (standing water returns nothing, and the strongest peak on those
    scan lines is texture, triangulated far off the wall: random-features-small seed 25,
    45-270 mm out), not wall, and no wall missing there either (the stations' water
    cut); and those other clusters."""
    stray = np.zeros(len(r.dev), bool)
    rings = ring_ids(r.frame)
    axial = {int(k): float(s) for k, s in zip(rings, r.ring_sigma, strict=True)}
    wall = (np.abs(r.dev) <= thr) & ~not_wall
    on_ring = ring_points(r.frame, rings)  # each ring's indices when asked (no whole-run index)
    wall_theta = ring_angles(r.frame, rings, r.theta, wall)  # each ring's when asked
    kept, cuts = [], []
    for m in deep:
        c = math.atan2(float(np.mean(np.sin(r.theta[m]))), float(np.mean(np.cos(r.theta[m]))))
        d = (r.theta - c + np.pi) % (2 * np.pi) - np.pi
        lo, hi = float(d[m].min()), float(d[m].max())
        inside = {int(k) for k in np.unique(r.frame[m])}
        half = max(0.25 * (hi - lo), 0.5 * config.lateral_gap_mm / radius)
        if _rises_from_the_wall(r, m, thr) or closes_both_sides(
            axial, wall_theta, inside, 0.5 * (lo + hi) + c, half, config.lateral_max_length_rel * 2.0 * radius
        ):
            kept.append(m)
            continue
        cuts.append(m)
        stray[m] = True
        for k in inside:
            dk = d[m[r.frame[m] == k]]
            on = on_ring[k]
            stray[on] |= (d[on] >= dk.min()) & (d[on] <= dk.max()) & (r.dev[on] > thr)
    return kept, stray, cuts


def _one_hole(r: Rings, a: np.ndarray, b: np.ndarray, low: float) -> bool:
    """Whether two openings' not-wall masks are pieces of one hole: they share samples,
    or they lie side by side around the pipe (their axial spans overlapping over half
    the shorter one) with no wall between them on most of the rings both cross (no
    sample within ``low`` of the wall: the branch wall lit on both sides of a hole whose
    middle returns nothing, or strays inwards)."""
    if (a & b).any():
        return True
    za, zb = r.sigma[a], r.sigma[b]
    over = min(za.max(), zb.max()) - max(za.min(), zb.min())
    if over < 0.5 * min(np.ptp(za), np.ptp(zb)):
        return False
    ca = math.atan2(float(np.mean(np.sin(r.theta[a]))), float(np.mean(np.cos(r.theta[a]))))
    shared = np.intersect1d(r.frame[a], r.frame[b])
    if not len(shared):
        return False
    walled = 0
    spans = RingSpans(r.frame, shared)  # each shared ring's own points: no whole-run arc
    for i in range(len(shared)):
        on = spans.indices(i)
        u = (r.theta[on] - ca + np.pi) % (2 * np.pi) - np.pi
        in_a, in_b = a[on], b[on]
        ua, ub = u[in_a], u[in_b]
        lo, hi = (ua.max(), ub.min()) if np.median(ua) < np.median(ub) else (ub.max(), ua.min())
        between = (u > lo) & (u < hi) & ~in_a & ~in_b
        walled += bool(np.any(between & (np.abs(r.dev[on]) <= low)))
    return 2 * walled < len(shared)


def _one_ring_opening(
    config: FeatureConfig,
    r: Rings,
    members: np.ndarray,
    radius: float,
    spacing: float,
    thr: float,
    not_wall: np.ndarray,
) -> np.ndarray | None:
    """A lateral seen deep by one ring only (rings far apart: seed 5's 43 mm branch in a
    579 mm pipe, rings 15 mm apart, lit 5-20 mm beyond the wall on one ring): the
    cluster ``members`` reaches as an opening's does (:func:`_opening`) and a ring next
    to it along the axis (within 1.5 ring spacings) is disturbed at the same angles (two
    samples or more beyond ``thr`` either way: the branch's far wall, the rim's stray
    light). Returns the cluster with those samples, or None."""
    rings = np.unique(r.frame[members])
    if len(rings) != 1 or float(np.mean(r.dev[members])) <= 0:
        return None
    if not _opening(config, members, r.dev, r.theta, r.frame, radius, thr):
        return None
    th0 = math.atan2(float(np.mean(np.sin(r.theta[members]))), float(np.mean(np.cos(r.theta[members]))))
    d = (r.theta - th0 + np.pi) % (2 * np.pi) - np.pi
    step = float(np.median(np.diff(np.sort(r.theta[r.frame == rings[0]]))))
    lo, hi = float(d[members].min()) - 3.0 * step, float(d[members].max()) + 3.0 * step
    z = float(np.median(r.sigma[members]))
    near = (r.frame != rings[0]) & (np.abs(r.ring_sigma[r.ring_of] - z) <= 1.5 * spacing)
    extra = np.flatnonzero(near & (np.abs(r.dev) > thr) & (d >= lo) & (d <= hi) & ~not_wall)
    if len(extra) < 2:
        return None
    return np.concatenate([members, extra])


def _rises_from_the_wall(r: Rings, members: np.ndarray, thr: float, max_steps: float = 3.0) -> bool:
    """Whether the deep samples ``members`` rise from the wall as a lit branch wall does
    on most of their rings: on half of them or more, an end of the ring's run of them
    (in angle) lies within ``max_steps`` sample steps of a wall sample (within ``thr``)
    and no further out than 4 ``thr`` or a quarter of the ring's deepest (the laser
    plane cuts the branch wall from the rim outwards: sewer-small's 100 mm tee, 6-13 mm
    out at its rim, 25-90 mm at its middle). Texture peaks in a water cut stand alone:
    7-37 steps of the cut from the wall, or next to it as far out as the deepest
    (random-features-small seed 25: 45-93 mm, 0.3-1.0 of the deepest)."""
    rings = np.unique(r.frame[members])
    c = math.atan2(float(np.mean(np.sin(r.theta[members]))), float(np.mean(np.cos(r.theta[members]))))
    rising = 0
    for k in rings:
        on = np.flatnonzero(r.frame == k)
        u = (r.theta[on] - c + np.pi) % (2 * np.pi) - np.pi  # about the cluster: no seam inside it
        o = on[np.argsort(u)]
        t = np.sort(u)
        step = float(np.median(np.diff(t))) if len(t) > 2 else 0.0
        pos = np.flatnonzero(np.isin(o, members))
        low = max(4.0 * thr, 0.25 * float(np.max(r.dev[o[pos]])))
        for i, j in ((pos.min(), pos.min() - 1), (pos.max(), pos.max() + 1)):
            j %= len(o)
            gap = abs((t[j] - t[i] + np.pi) % (2 * np.pi) - np.pi)
            if abs(r.dev[o[j]]) <= thr and gap <= max_steps * step and r.dev[o[i]] <= low:
                rising += 1
                break
    return 2 * rising >= len(rings)


def _lost_openings(
    config: FeatureConfig,
    r: Rings,
    radius: float,
    spacing: float,
    joints: Sequence[PointFeature],
    stray: np.ndarray | None = None,
) -> list[list[ReturnGap]]:
    """The rings' local stretches without returns (:func:`.openings.local_gaps`) outside
    the joints' gaps (a groove's edge hides a tilted ring's samples), linked into
    openings over ``lateral_gap_rings`` rings or more; the ``stray`` samples
    (:func:`_closed_openings`) are no returns."""
    lit = ~stray if stray is not None and stray.any() else None  # (the run's arrays not copied)
    gaps = return_gaps(r.sigma, r.theta, r.frame, radius, config.lateral_gap_mm, lit=lit)
    if not gaps:
        return []
    rings = ring_ids(r.frame)
    axial = {int(k): float(s) for k, s in zip(rings, r.ring_sigma, strict=True)}
    gaps = local_gaps(gaps, r.theta, r.frame, axial, config.lateral_max_length_rel * 2.0 * radius, lit=lit)
    clear = [(f.axial_mm - 0.5 * f.gap_mm - config.margin_mm, f.axial_mm + 0.5 * f.gap_mm + config.margin_mm)
             for f in joints if isinstance(f, Joint)]
    gaps = [g for g in gaps if not any(a <= g.axial_mm <= b for a, b in clear)]
    return gap_clusters(gaps, max(1.5 * spacing, 3.0), config.lateral_gap_rings)


def _meets(
    r: Rings,
    members: np.ndarray,
    cluster: Sequence[ReturnGap],
    radius: float,
    spacing: float,
    taken: np.ndarray | None = None,
) -> bool:
    """Whether the samples ``members`` lie at a lost-return opening ``cluster`` (with
    the samples ``taken`` into it already): within 1.5 ring spacings of it along the
    axis and within its widest gap (plus 3 sample steps) of its centre around the pipe."""
    if not len(members):
        return False
    z = r.sigma[members]
    zs = np.array([g.axial_mm for g in cluster] + ([] if taken is None else list(r.sigma[taken])))
    if z.max() < zs.min() - 1.5 * spacing or z.min() > zs.max() + 1.5 * spacing:
        return False
    c = math.atan2(float(np.mean([math.sin(g.centre) for g in cluster])),
                   float(np.mean([math.cos(g.centre) for g in cluster])))
    half = max(0.5 * g.width + 3.0 * g.step for g in cluster)
    d = np.abs((r.theta[members] - c + np.pi) % (2 * np.pi) - np.pi)
    return bool(np.any(d <= half))


def feature_zones(
    features: list[PointFeature], radius: float, margin_mm: float, openings: Sequence[FeatureZone] = ()
) -> list[FeatureZone]:
    """Each joint's and lateral's reach with its uncertainty, for the defect search
    (:class:`~omnipipe.analysis.defect_search.FeatureZone`): a joint all around the pipe, over
    its gap plus ``margin_mm`` plus 3 sigma of its edges (centre and half-gap sigmas in
    quadrature) each side; a lateral over its opening's semi-axes (the circumferential
    one the arc of its chord on the ``radius`` mm wall) plus the margin plus 3 sigma of
    centre and radius, along the axis and around the pipe; with ``openings`` (the
    laterals' own zones, :attr:`FeatureSearch.opening_zones`: along the axis the
    outline's axial semi-axis, longer than the circumferential one where the branch
    leans) those instead."""
    out: list[FeatureZone] = list(openings)
    for f in features:
        if isinstance(f, Joint):
            half = 0.5 * f.gap_mm + margin_mm + 3.0 * math.hypot(_sd(f.axial_sigma_mm), 0.5 * _sd(f.gap_sigma_mm))
            out.append(FeatureZone(f.axial_mm - half, f.axial_mm + half, f"the joint at {f.axial_mm:.1f} mm"))
        elif isinstance(f, Lateral) and not openings:
            b = radius * math.asin(min(0.5 * f.diameter_mm / radius, 1.0))
            s_r = 0.5 * _sd(f.diameter_sigma_mm)
            along = b + margin_mm + 3.0 * math.hypot(_sd(f.axial_sigma_mm), s_r)
            around = b + margin_mm + 3.0 * math.hypot(radius * math.radians(_sd(f.angle_sigma_deg)), s_r)
            out.append(FeatureZone(
                f.axial_mm - along, f.axial_mm + along, f"the lateral at {f.axial_mm:.1f} mm",
                arc_mm=math.radians(f.angle_deg % 360.0) * radius, half_arc_mm=around,
            ))
    return out


def _sd(value: float | None) -> float:
    """A sigma, 0 when unknown (None or not finite)."""
    return float(value) if value is not None and math.isfinite(value) else 0.0


def with_offset_joints_kept(first: FeatureSearch, second: FeatureSearch) -> FeatureSearch:
    """``second`` (the search after the sections either side of the offset joints were
    fitted apart) with the joints ``first`` found by their offset alone that it lost
    (:func:`.joints.offset_joints_kept`)."""
    kept = offset_joints_kept(first.features, second.features)
    if not kept:
        return second
    feats = sorted([*second.features, *kept], key=lambda f: f.axial_mm)
    return FeatureSearch(
        feats, second.not_wall, second.threshold_mm, second.unseen_gap_mm, second.opening_zones, second.stray
    )


def _opening(
    config: FeatureConfig,
    members: np.ndarray,
    dev: np.ndarray,
    theta: np.ndarray,
    frame: np.ndarray,
    radius: float,
    thr: float,
) -> bool:
    """True if the cluster ``members`` reaches as far beyond the wall as a lateral's
    opening does: ``lateral_reach_rel`` of the diameter, or (a small branch, whose wall
    is seen only a little way in) ``lateral_reach_thr`` x the threshold ``thr`` and
    ``lateral_reach_width`` x its widest chord (a dent is far wider than deep)."""
    reach = float(np.max(dev[members]))
    if reach >= config.lateral_reach_rel * 2.0 * radius:
        return True
    th0 = math.atan2(float(np.mean(np.sin(theta[members]))), float(np.mean(np.cos(theta[members]))))
    u = ((theta[members] - th0 + np.pi) % (2 * np.pi) - np.pi) * radius
    width = max(float(np.ptp(u[frame[members] == k])) for k in np.unique(frame[members]))
    return reach >= config.lateral_reach_thr * thr and reach >= config.lateral_reach_width * width


def _unseen_gap(sigma: np.ndarray) -> float:
    """The widest axial stretch (mm) between consecutive samples (sorted along the axis).

    Without a sorted copy of the run's samples in memory: they are placed range of values
    after range (about :data:`_GAP_BLOCK` samples each, from a histogram of them) in the
    run's scratch in one pass, each range then sorted on its own; the sorted run is those ranges one after the other, so its
    consecutive differences are each range's and the steps from one range's last sample
    to the next one's first (the same subtractions, the same maximum). Samples that are
    not all finite: the whole sort."""
    n = len(sigma)
    if n < 2:
        return 0.0
    lo, hi, finite = math.inf, -math.inf, True
    for a in range(0, n, _GAP_BLOCK):
        blk = sigma[a : a + _GAP_BLOCK]
        finite = finite and bool(np.isfinite(blk).all())
        lo, hi = min(lo, float(blk.min())), max(hi, float(blk.max()))
    if not finite or n <= _GAP_BLOCK or hi <= lo:
        s = np.sort(sigma)
        return float(np.max([np.max(np.diff(s[a : a + _GAP_BLOCK + 1])) for a in range(0, n - 1, _GAP_BLOCK)]))
    edges = np.linspace(lo, hi, 4 * (n // _GAP_BLOCK) + 2)
    counts = np.zeros(len(edges) - 1, np.int64)
    for a in range(0, n, _GAP_BLOCK):
        counts += np.bincount(_value_bin(sigma[a : a + _GAP_BLOCK], edges), minlength=len(counts))
    cuts = [0]  # ranges of consecutive bins holding about _GAP_BLOCK samples each
    while cuts[-1] < len(counts):
        b0 = cuts[-1]
        cuts.append(max(int(np.searchsorted(np.cumsum(counts[b0:]), _GAP_BLOCK, side="right")) + b0, b0 + 1))
    range_of = np.repeat(np.arange(len(cuts) - 1), np.diff(cuts))
    sizes = np.add.reduceat(counts, cuts[:-1])
    starts = np.concatenate([[0], np.cumsum(sizes)[:-1]])
    # The samples placed range after range in the run's scratch (one pass), each range's
    # then sorted on its own.
    placed, fill = zeros_on_disk((n,), sigma.dtype), starts.copy()
    for a in range(0, n, _GAP_BLOCK):
        blk = sigma[a : a + _GAP_BLOCK]
        rg = range_of[_value_bin(blk, edges)]
        order = np.argsort(rg, kind="stable")
        per = np.bincount(rg, minlength=len(sizes))
        at = 0
        for g in np.flatnonzero(per):
            placed[fill[g] : fill[g] + per[g]] = blk[order[at : at + per[g]]]
            fill[g] += per[g]
            at += per[g]
    widest, last = -math.inf, None
    for g in range(len(sizes)):
        part = np.sort(placed[starts[g] : starts[g] + sizes[g]])
        if len(part):
            if last is not None:
                widest = max(widest, float(part[0] - last))
            if len(part) > 1:
                widest = max(widest, float(np.max(np.diff(part))))
            last = part[-1]
    return widest


def _value_bin(values: np.ndarray, edges: np.ndarray) -> np.ndarray:
    """(n,) the bin of ``edges`` (ascending, B + 1) each value lies in (the last bin
    holding the highest edge too)."""
    return np.minimum(np.searchsorted(edges, values, side="right") - 1, len(edges) - 2)


_GAP_BLOCK = 1 << 16
"""Samples per block of :func:`_unseen_gap`'s differences."""


def _chords(
    sigma: np.ndarray, u: SampleArcs, spans: RingSpans, members: np.ndarray, sample: float, radius: float
) -> np.ndarray:
    """(M, 4) per ring crossing the hole: axial position, chord centre and half-width
    (arc mm; half a sample added: the edges lie between samples), ring index. The axial
    position is the ring's own at the chord's centre (:func:`.openings.ring_axial`), not its deep
    samples': those lie out in the branch, where the pipe coordinates of a ring tilted
    to the axis, or of a centreline through a bend, stray along the axis by their depth
    (random-features-small seed 1, a 132 mm branch in an elbow: 20-80 mm). ``u``: the
    samples' arcs about the hole; ``spans``: where the members' rings lie (each ring's
    samples read on their own)."""
    rows = []
    ring = spans.frame[members]
    for k in np.unique(ring):
        m = members[ring == k]
        if len(m) < 2:
            continue
        um = u[m]
        c = 0.5 * (um.max() + um.min())
        on = spans.indices(int(np.searchsorted(spans.rings, k)))
        wall = on[~np.isin(on, m)]
        z = ring_axial(sigma[wall], u[wall] / radius, c / radius) if len(wall) >= 8 else float(np.median(sigma[m]))
        rows.append((z, c, 0.5 * (um.max() - um.min()) + 0.5 * sample, float(k)))
    return np.array(rows).reshape(-1, 4)


def _ellipse(ch: np.ndarray) -> tuple[float, float, float, float]:
    """(axial centre, arc centre, circumferential semi-axis, axial semi-axis) through the
    chords: h^2 = A + B z + C z^2; fewer than 3 chords or no maximum: the widest chord."""
    z, c, h = ch[:, 0], ch[:, 1], ch[:, 2]
    if len(ch) >= 3:
        zc0 = float(np.mean(z))
        A = np.stack([np.ones_like(z), z - zc0, (z - zc0) ** 2], axis=1)
        p, *_ = np.linalg.lstsq(A, h**2, rcond=None)
        if p[2] < 0:
            zc = zc0 - p[1] / (2 * p[2])
            b2 = p[0] - p[1] ** 2 / (4 * p[2])
            if b2 > 0 and z.min() - h.max() <= zc <= z.max() + h.max():
                return float(zc), float(np.average(c, weights=h)), math.sqrt(b2), math.sqrt(-b2 / p[2])
    i = int(np.argmax(h))
    return float(z[i]), float(c[i]), float(h[i]), float(np.ptp(z)) / 2


def _lateral(
    config: FeatureConfig,
    r: Rings,
    members: np.ndarray,
    radius: float,
    spacing: float,
    thr: float,
    gaps: Sequence[ReturnGap] = (),
    stops: Sequence[tuple[float, float]] = (),
    planes: dict[int, np.ndarray] | None = None,
) -> tuple[Lateral, np.ndarray, FeatureZone, bool]:
    """A lateral's opening from its cluster of deep samples ``members`` and the rings'
    stretches without returns across it (``gaps``; either may be empty, not both):
    centre, angle and diameter (jackknife sigmas). Where the rings disturbed at its
    angles show it closing on both sides along the axis (:func:`.openings.hole_extent`;
    ``stops``: the joints' bands, which end that growth), the centre is the middle of
    that reach, 1-sigma from the rings' spacing at its ends and the light's axial blur
    (``r.axial_blur_mm``: a ring partly lit in the hole reads disturbed, each end 0..1 blur
    sigma out, uniform), plus the rings' footprint (:func:`_footprint_sigma`; the zone keeps
    the spacing's: the reach as read); where it runs to the run's end (or a joint), the
    fitted centre stays and the reach is not wall. Returns the lateral, its not-wall mask,
    its zone for the defect search, and whether it can be a round branch's hole."""
    sigma, theta, frame = r.sigma, r.theta, r.frame
    th = np.concatenate([theta[members], [g.centre for g in gaps]])
    th0 = math.atan2(float(np.mean(np.sin(th))), float(np.mean(np.cos(th))))
    u = SampleArcs(theta, th0, radius)  # each sample's arc about th0, made where read
    rings = np.unique(np.concatenate([frame[members], [g.ring for g in gaps]]).astype(int))
    spans = RingSpans(frame, rings)  # the hole's rings' samples, a ring at a time
    steps = []
    for i in range(len(spans)):
        d_u = np.diff(np.sort(u[spans.indices(i)]))
        steps.append(float(np.median(d_u[d_u > 0])) if (d_u > 0).any() else 1.0)
    sample = float(np.median(steps))
    ch = _merged_chords(_chords(sigma, u, spans, members, sample, radius), _gap_chords(gaps, th0, radius))
    ch = _main_block(ch, max(3.0 * spacing, 10.0))
    zc, uc, b, a = _ellipse(ch[:, :3])
    est = [(zc, uc, b)]
    if len(ch) >= 4:
        est += [_ellipse(np.delete(ch[:, :3], i, axis=0))[:3] for i in range(len(ch))]
    arr = np.array(est)
    n = len(arr) - 1
    jk = np.sqrt((n - 1) / n * np.sum((arr[1:] - arr[1:].mean(axis=0)) ** 2, axis=0)) if n >= 3 else np.zeros(3)
    # Beside the jackknife: where the rings fall along the hole (their spacing), and the
    # edge samples' reach (a ring's light is lost or half-lit at the rim: up to a sample).
    s_z = math.hypot(float(jk[0]), spacing / math.sqrt(12.0))
    s_u = math.hypot(float(jk[1]), sample / math.sqrt(12.0))
    s_b = math.hypot(float(jk[2]), sample)
    planes = _ring_planes(r, thr) if planes is None else planes
    s_rep = s_z  # the reported axial sigma; the zone's along the axis stays s_z (the reach as read)
    ext = _extent(r, u.minus(uc), ch, (float(th0 + uc / radius), radius, uc), float(np.max(ch[:, 2])) + sample,
                  thr, stops, planes)
    reach = (zc - a, zc + a)
    if ext is not None and all(ext.closed):
        zc, a = 0.5 * (ext.lo_mm + ext.hi_mm), 0.5 * (ext.hi_mm - ext.lo_mm)
        s_z = 0.5 * math.hypot(ext.lo_sigma_mm, ext.hi_sigma_mm)
        s_rep = math.hypot(s_z, 0.5 * math.sqrt(2.0 / 12.0) * r.axial_blur_mm)  # each end 0..1 blur out
        reach = (zc - a, zc + a)
    elif ext is not None:  # seen to the run's end (or a joint): the grown rings not wall
        reach = (min(zc - a, ext.lo_mm), max(zc + a, ext.hi_mm))
    diameter = 2.0 * radius * math.sin(min(b / radius, 0.5 * math.pi))
    round_hole = len(members) > 0 or not _no_round_hole(ext, diameter, config.lateral_gap_rings * spacing)
    f = Lateral(
        axial_mm=zc,
        axial_sigma_mm=math.hypot(s_rep, _footprint_sigma(planes, ch, ext, float(th0 + uc / radius))),
        angle_deg=math.degrees(th0 + uc / radius) % 360.0,
        angle_sigma_deg=math.degrees(s_u / radius),
        diameter_mm=diameter,
        diameter_sigma_mm=2.0 * s_b * abs(math.cos(min(b / radius, 0.5 * math.pi))),
        points=len(members),
    )
    m = config.margin_mm
    zr, ar = 0.5 * (reach[0] + reach[1]), 0.5 * (reach[1] - reach[0])
    inside = within_ellipses(sigma, u, [(zc, a + m, uc, b + m), (zr, ar + m, uc, b + m)])
    inside[members] = True
    along, around = ar + m + 3.0 * math.hypot(s_z, s_b), b + m + 3.0 * math.hypot(s_u, s_b)
    zone = FeatureZone(
        zr - along, zr + along, f"the lateral at {zc:.1f} mm",
        arc_mm=(math.radians(f.angle_deg) * radius), half_arc_mm=around,
    )
    return f, inside, zone, round_hole


def _footprint_sigma(
    planes: dict[int, np.ndarray], ch: np.ndarray, ext: HoleExtent | None, angle: float
) -> float:
    """1-sigma (mm) of a hole's axial position in the pipe from its rings' footprint
    along the axis: each ring (``planes``: :func:`_ring_planes`) of the hole (its chords
    ``ch``, (M, 4) ring in column 3, and the rings ``ext`` grew it over) lies
    ``p1 cos a + p2 sin a`` mm off its mean axial position at the hole's angle ``a``
    (rad), the median of them the hole's offset. The hole is read
    there, right where that tilt is the rig's in the pipe (the laser plane leaning),
    off by all of it where it is the coordinate's (the centreline's tangent off the
    pipe's axis: a ring square to the pipe then looks tilted by as much); the run
    cannot tell the two apart, so the hole lies anywhere between the reading and the
    offset back from it (uniform): about the reading, |offset| / sqrt(3) RMS. Rings
    square to the coordinate, or a hole at the angle their tilt is about (offset 0),
    add nothing."""
    rings = ch[:, 3] if ext is None else np.concatenate([ch[:, 3], ext.chords[:, 3]])
    off = [float(planes[k][1] * math.cos(angle) + planes[k][2] * math.sin(angle))
           for k in {int(k) for k in rings} if k in planes]
    return abs(float(np.median(off))) / math.sqrt(3.0) if off else 0.0


def _no_round_hole(ext: HoleExtent | None, diameter: float, min_mm: float) -> bool:
    """Whether an opening of lost returns alone (no deep sample), ``diameter`` mm wide,
    cannot be a round branch's hole: it closes shorter than it is wide
    (:func:`_shorter_than_wide`), or it is narrower than ``min_mm`` (``lateral_gap_rings``
    wide ring spacings): the rings such an opening needs then straddle more than the
    hole, and returns lost that briefly are a dropout's (a pit, a stain; random-features-
    small seed 15: 7 and 13 mm lost on two rings 9 mm apart in a 188 mm pipe, an
    "opening" 11.7 mm wide)."""
    return _shorter_than_wide(ext, diameter) or diameter < min_mm


def _shorter_than_wide(ext: HoleExtent | None, diameter: float) -> bool:
    """Whether a hole seen closing on both sides is shorter along the axis, even between
    the clean rings either side (each end at most ``sqrt(12)`` x its sigma / 2 further
    out), than it is wide (``diameter`` mm): no round branch's (its hole is D / sin of
    its angle long, at least D), but the returns lost on a ring or two across a seam or
    a shadow (bench seeds 4 and 15: 43 mm wide, 36 mm between the clean rings)."""
    if ext is None or not all(ext.closed):
        return False
    half = 0.5 * math.sqrt(12.0)
    return (ext.hi_mm + half * ext.hi_sigma_mm) - (ext.lo_mm - half * ext.lo_sigma_mm) < diameter


def _extent(
    r: Rings, u: SampleArcs, ch: np.ndarray, centre: tuple[float, float, float], half: float, thr: float,
    stops: Sequence[tuple[float, float]], planes: dict[int, np.ndarray],
) -> HoleExtent | None:
    """The hole's reach along the axis (:func:`.openings.hole_extent`) from its chords
    ``ch`` (M, 4: axial, centre arc mm about the angle the arcs of ``_lateral`` start
    from, half-width, ring): each ring's axial position from its wall samples
    (``planes``: :func:`_ring_planes`) at the hole's angle, or where it meets the hole
    (a chord's centre), disturbance beyond half the feature threshold ``thr`` within
    ``half`` arc mm of the centre (``u``: the samples' arc about it). ``centre``: the
    hole's angle (rad), the wall radius (mm) and the hole's centre arc in ``ch``'s
    terms (mm)."""
    at, radius, uc = centre

    def z_at(k: int, c: float) -> float:
        p, a = planes[k], at + c / radius
        return float(p[0] + p[1] * math.cos(a) + p[2] * math.sin(a))

    ring_z = {k: z_at(k, 0.0) for k in planes}
    inside = {int(k) for k in ch[:, 3]} & set(ring_z)
    chords = {int(k): (float(c) - uc, float(h)) for c, h, k in ch[:, 1:4] if int(k) in inside}
    return hole_extent(ring_z, u, r.dev, r.frame, inside, half, 0.5 * thr, list(stops), z_at, chords)


def _ring_planes(r: Rings, thr: float) -> dict[int, np.ndarray]:
    """Each ring's plane sigma = p0 + p1 cos theta + p2 sin theta (mm; (3,) p) through its
    wall samples (deviation within ``thr``; rings with at least 8 of them): the fit of
    :func:`.openings.ring_axial`, whose value at an angle is p's there. Made once for all
    the holes (a ring at a time over its own samples: linear in the run)."""
    spans = RingSpans(r.frame)  # each ring's samples on their own (no index of every wall sample)
    out = {}
    for i, k in enumerate(spans.rings):
        on = spans.indices(i)
        on = on[np.abs(r.dev[on]) <= thr]
        if len(on) >= 8:
            out[int(k)] = robust_sine_fit(r.sigma[on], r.theta[on], 2, 3.0, 0.5)[0]
    return out


def _main_block(ch: np.ndarray, link_mm: float) -> np.ndarray:
    """The chords (M, 4: axial, centre, half-width, ring) along the axis around the
    widest one, up to a step wider than ``link_mm`` between consecutive ones (a joint's
    lost stretch on a ring far from the hole joined by its angles)."""
    if len(ch) < 2:
        return ch
    ch = ch[np.argsort(ch[:, 0])]
    part = np.concatenate([[0], np.cumsum(np.diff(ch[:, 0]) > link_mm)])
    return ch[part == part[int(np.argmax(ch[:, 2]))]]


def _gap_chords(gaps: Sequence[ReturnGap], th0: float, radius: float) -> np.ndarray:
    """(M, 4) per gap: axial position, chord centre and half-width (arc mm about
    ``th0``), ring index. The hole's rim lies between the last lit sample and where the
    next one would fall: the chord is the gap less one sample step (half at each end)."""
    rows = []
    for g in gaps:
        c = ((g.centre - th0 + np.pi) % (2 * np.pi) - np.pi) * radius
        rows.append((g.axial_mm, c, max(0.5 * (g.width - g.step), 0.5 * g.step) * radius, float(g.ring)))
    return np.array(rows).reshape(-1, 4)


def _merged_chords(deep: np.ndarray, lost: np.ndarray) -> np.ndarray:
    """(M, 4) chords (axial, centre, half-width, ring) of a hole from its deep samples'
    and its lost returns' chords: where both lie on one ring and meet around it, one
    chord spanning both (the branch wall lit near the rim, the light lost beyond)."""
    rows = [list(r) for r in deep]
    for z, c, h, k in lost:
        for r in rows:
            if r[3] == k and abs(r[1] - c) <= r[2] + h + 1e-6:
                lo, hi = min(r[1] - r[2], c - h), max(r[1] + r[2], c + h)
                r[1], r[2] = 0.5 * (lo + hi), 0.5 * (hi - lo)
                break
        else:
            rows.append([z, c, h, k])
    return np.array(sorted(rows)).reshape(-1, 4)
