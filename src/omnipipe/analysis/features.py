"""Joints and laterals: found in the rings, measured, and taken out of the wall.

A joint's gap and a lateral's opening are parts of a sound pipe: their points are not
wall (they would read as dents, and pull the rings' wall profiles). Per ring, a robust
Fourier profile (order 2: the ring's offset and ovality) is fitted; a ring whose mean
radius stands out from its neighbours' running median (the ring lies in a joint's gap)
takes the neighbours' mean radius instead. Points further out than the threshold
(``max(min_depth_mm, noise_factor x noise)``; for joints ``joint_noise_factor``) are
candidates.

* joint: candidates are grouped along the axis (a gap between them wider than
  ``joint_link_mm`` splits groups); a group whose axial band is seen deep over most
  (``joint_coverage``) of the angles at which any ring samples that band is a joint. A
  ring tilted to the axis crosses a narrow gap along a slant, so the gap is seen by the
  rings together, not by one ring covering the circumference; a gap lying between two
  rings that no ring crosses cannot be seen (``FeatureSearch.unseen_gap_mm``: the widest
  axial stretch no ring sampled). Each gap edge (at half the gap's depth) is where deep
  samples give way to shallow ones: per ring crossing it, the split that misclassifies
  fewest samples; the edge is their median, 1-sigma their scatter / sqrt(n) (fewer than
  3 rings: the rings' spacing / sqrt(12)). The offset is fitted to the wall
  within ``window_mm`` on both sides (the gap left out) in a straight frame through the
  joint: rho = per-ring radius + centre drift (quadratic along the axis, so a bend does
  not pass for an offset) + ovality + a step of the downstream centre (the offset); its
  sigma by jackknife over the rings.
* lateral: the remaining candidates are linked into clusters across rings; a narrow
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
from dataclasses import dataclass

import numpy as np
from scipy.sparse import coo_matrix
from scipy.sparse.csgraph import connected_components
from scipy.spatial import cKDTree

from omnipipe.analysis.centreline import Centreline
from omnipipe.analysis.defects import FeatureZone, fit_wall_profile, fourier_design
from omnipipe.analysis.feature_types import Joint, Lateral, PointFeature
from omnipipe.analysis.openings import ReturnGap, gap_clusters, local_gaps, return_gaps
from omnipipe.config import bounded


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
class FeatureSearch:
    """What :func:`find_features` found.

    Attributes:
        features: joints and laterals, ordered along the pipe.
        not_wall: (N,) True for the points inside a gap or an opening (and their margin).
        threshold_mm: outward deviation beyond which a point counted.
        unseen_gap_mm: the widest axial stretch between the measured rings' first and
            last samples that no sample fell in (mm): a joint gap narrower than this
            may lie there unseen.
    """

    features: list[PointFeature]
    not_wall: np.ndarray
    threshold_mm: float
    unseen_gap_mm: float = 0.0


@dataclass(frozen=True)
class _Rings:
    """The points in pipe coordinates, grouped by ring, and their deviation from it."""

    sigma: np.ndarray
    rho: np.ndarray
    theta: np.ndarray
    frame: np.ndarray
    ring_of: np.ndarray
    ring_sigma: np.ndarray
    dev: np.ndarray
    noise: float


def find_features(
    config: FeatureConfig,
    line: Centreline,
    sigma: np.ndarray,
    rho: np.ndarray,
    theta: np.ndarray,
    frame: np.ndarray,
    radius: float,
) -> FeatureSearch:
    """Joints and laterals among (N,) points in pipe coordinates (sigma, rho mm; theta
    rad from the centreline's normal towards its binormal; frame: ring index), ``radius``
    the nominal wall radius (mm)."""
    rings = np.unique(frame)
    dev, ring_sigma, raised = _deviations(config, sigma, rho, theta, frame, rings)
    ring_of = np.searchsorted(rings, frame)
    # The wall's noise without the rings raised together in a block (a wide gap crossed
    # by tilted rings: each ring's wall samples stand off its neighbours' level by the
    # gap's share of its circumference, a large share of the run's samples).
    wall = ~_raised_blocks(raised, ring_sigma)[ring_of]
    wall = wall if wall.any() else np.ones(len(dev), bool)
    noise = 1.4826 * float(np.median(np.abs(dev[wall] - np.median(dev[wall]))))
    thr = max(config.min_depth_mm, config.noise_factor * noise)
    r = _Rings(sigma, rho, theta, frame, ring_of, ring_sigma, dev, noise)
    # Joint candidates: beyond a lower threshold (a gap must also cover most of the
    # circumference), or half of it on a ring lying in a gap.
    thr_joint = max(config.min_depth_mm, config.joint_noise_factor * noise)
    cand = (dev > thr_joint) | (raised[ring_of] & (dev > 0.5 * thr_joint))
    not_wall = np.zeros(len(sigma), bool)
    unseen = _unseen_gap(sigma)
    gaps = np.diff(np.sort(ring_sigma))
    spacing = float(np.percentile(gaps, 90)) if len(gaps) else 5.0
    if cand.sum() < config.min_points:
        feats = list(_offset_joints(config, line, r, []))
        for f, mask in _laterals(config, r, radius, spacing, thr, not_wall, feats):
            feats.append(f)
            not_wall |= mask
        return FeatureSearch(sorted(feats, key=lambda f: f.axial_mm), not_wall, thr, unseen)
    feats: list[PointFeature] = []
    for band in _joint_bands(config, r, cand, max(config.joint_link_mm, 1.5 * spacing), raised):
        f, mask = _joint(config, line, r, cand, band)
        if not 0.0 < f.gap_mm <= config.joint_max_gap_mm:
            continue  # a wide outward stretch (a taper's tilted rings), not a gap
        feats.append(f)
        not_wall |= mask
    for f in _offset_joints(config, line, r, feats):
        feats.append(f)
    # Laterals: the rest, linked across rings, narrow and reaching far out, and the
    # rings' stretches without returns (the light lost in the branch).
    for f, mask in _laterals(config, r, radius, spacing, thr, not_wall, feats):
        feats.append(f)
        not_wall |= mask
    feats.sort(key=lambda f: f.axial_mm)
    return FeatureSearch(feats, not_wall, thr, unseen)


def _deep_clusters(
    config: FeatureConfig, r: _Rings, radius: float, spacing: float, thr: float, not_wall: np.ndarray
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
    r: _Rings,
    radius: float,
    spacing: float,
    thr: float,
    not_wall: np.ndarray,
    joints: Sequence[PointFeature],
) -> list[tuple[Lateral, np.ndarray]]:
    """The laterals: the deep clusters reaching as far as an opening's, and the
    openings seen as lost returns (:mod:`.openings`) away from the joints, each with
    the other clusters it meets along the axis (the branch wall lit near the rim);
    (lateral, its not-wall mask) each."""
    deep, others = _deep_clusters(config, r, radius, spacing, thr, not_wall)
    for i, m in enumerate(others):
        seen = _one_ring_opening(config, r, m, radius, spacing, thr, not_wall)
        if seen is not None:
            deep.append(seen)
            others[i] = np.zeros(0, int)
    holes = [(m, []) for m in deep]
    for cluster in _lost_openings(config, r, radius, spacing, joints):
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
    return [_lateral(config, r.sigma, r.theta, r.frame, m, radius, spacing, g) for m, g in holes]


def _one_ring_opening(
    config: FeatureConfig,
    r: _Rings,
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


def _lost_openings(
    config: FeatureConfig, r: _Rings, radius: float, spacing: float, joints: Sequence[PointFeature]
) -> list[list[ReturnGap]]:
    """The rings' local stretches without returns (:func:`.openings.local_gaps`) outside
    the joints' gaps (a groove's edge hides a tilted ring's samples), linked into
    openings over ``lateral_gap_rings`` rings or more."""
    gaps = return_gaps(r.sigma, r.theta, r.frame, radius, config.lateral_gap_mm)
    if not gaps:
        return []
    rings = np.unique(r.frame)
    axial = {int(k): float(s) for k, s in zip(rings, r.ring_sigma, strict=True)}
    gaps = local_gaps(gaps, r.theta, r.frame, axial, config.lateral_max_length_rel * 2.0 * radius)
    clear = [(f.axial_mm - 0.5 * f.gap_mm - config.margin_mm, f.axial_mm + 0.5 * f.gap_mm + config.margin_mm)
             for f in joints if isinstance(f, Joint)]
    gaps = [g for g in gaps if not any(a <= g.axial_mm <= b for a, b in clear)]
    return gap_clusters(gaps, max(1.5 * spacing, 3.0), config.lateral_gap_rings)


def _meets(
    r: _Rings,
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


def feature_zones(features: list[PointFeature], radius: float, margin_mm: float) -> list[FeatureZone]:
    """Each joint's and lateral's reach with its uncertainty, for the defect search
    (:class:`~omnipipe.analysis.defects.FeatureZone`): a joint all around the pipe, over
    its gap plus ``margin_mm`` plus 3 sigma of its edges (centre and half-gap sigmas in
    quadrature) each side; a lateral over its opening's semi-axes (the circumferential
    one the arc of its chord on the ``radius`` mm wall) plus the margin plus 3 sigma of
    centre and radius, along the axis and around the pipe."""
    out: list[FeatureZone] = []
    for f in features:
        if isinstance(f, Joint):
            half = 0.5 * f.gap_mm + margin_mm + 3.0 * math.hypot(_sd(f.axial_sigma_mm), 0.5 * _sd(f.gap_sigma_mm))
            out.append(FeatureZone(f.axial_mm - half, f.axial_mm + half, f"the joint at {f.axial_mm:.1f} mm"))
        elif isinstance(f, Lateral):
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
    fitted apart) with the joints ``first`` found by their offset alone
    (:func:`_offset_joints`) that it lost: the break at such a joint straightens the
    centreline's step the search saw, and the wall either side then fits one cylinder
    each with the joint's step between them."""
    kept = [
        f for f in first.features
        if isinstance(f, Joint) and f.points == 0 and f.offset_mm is not None
        and not any(isinstance(g, Joint) and abs(g.axial_mm - f.axial_mm) <= 3.0 * f.axial_sigma_mm + 0.5 * g.gap_mm
                    for g in second.features)
    ]
    if not kept:
        return second
    feats = sorted([*second.features, *kept], key=lambda f: f.axial_mm)
    return FeatureSearch(feats, second.not_wall, second.threshold_mm, second.unseen_gap_mm)


def _offset_joints(
    config: FeatureConfig, line: Centreline, r: _Rings, found: list[PointFeature]
) -> list[Joint]:
    """Joints seen by their offset alone: a gap that lies between two rings (no ring
    sampled it) but whose downstream section is displaced. The recentred centreline
    steps sideways there (by the offset) between the two rings' stations: a step of at
    least ``joint_offset_min_mm`` and ``joint_offset_factor`` x the median step of the
    run (a bend's or a taper's drift), away from the joints already found, whose offset
    the wall either side then confirms (:func:`_local_axis`: >= 3 sigma, and the same
    as the step within half of it and 3 sigma). The joint
    lies somewhere in the unsampled stretch between the rings (tilted rings overlapping
    along the axis: between their middles): its centre and 1-sigma (stretch /
    sqrt(12)); the gap, unseen, is half the stretch with the same sigma; no depth."""
    ks = np.unique(r.frame)
    if len(ks) < 4:
        return []
    order = np.argsort(line.arc_mm[ks])
    ks = ks[order]
    d = np.diff(line.centre[ks], axis=0)
    t = line.tangent[ks[:-1]]
    step = np.linalg.norm(d - np.sum(d * t, axis=1)[:, None] * t, axis=1)
    out: list[Joint] = []
    for i in np.flatnonzero(step >= config.joint_offset_min_mm):
        others = np.delete(step, i)
        if step[i] < config.joint_offset_factor * float(np.median(others)):
            continue
        a = float(np.max(r.sigma[r.frame == ks[i]]))
        b = float(np.min(r.sigma[r.frame == ks[i + 1]]))
        if b <= a:  # tilted rings overlapping along the axis: between their middles
            a, b = (float(np.median(r.sigma[r.frame == k])) for k in ks[i : i + 2])
        near = [f for f in [*found, *out] if isinstance(f, Joint)
                and f.axial_mm - 0.5 * f.gap_mm <= b + config.joint_link_mm
                and f.axial_mm + 0.5 * f.gap_mm >= a - config.joint_link_mm]
        if b <= a or near:
            continue  # a joint found there
        local = _local_axis(config, line, r, 0.5 * (a + b), 0.5 * (b - a))
        if local is None:
            continue
        off = local.offset()
        if off[0] < max(config.joint_offset_min_mm, 3.0 * off[1]) or abs(off[0] - step[i]) > 0.5 * step[i] + 3.0 * off[1]:
            continue  # not confirmed by the wall, or a different step (a taper's wall)
        w = (b - a) / math.sqrt(12.0)
        out.append(
            Joint(
                axial_mm=0.5 * (a + b),
                axial_sigma_mm=w,
                gap_mm=0.5 * (b - a),
                gap_sigma_mm=w,
                offset_mm=off[0],
                offset_sigma_mm=off[1],
                offset_angle_deg=off[2],
                offset_angle_sigma_deg=off[3],
                depth_mm=None,
                points=0,
            )
        )
    return out


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


def _raised_blocks(raised: np.ndarray, ring_sigma: np.ndarray) -> np.ndarray:
    """(R,) True for the raised rings whose neighbour along the axis is raised too."""
    order = np.argsort(ring_sigma)
    r = raised[order]
    nb = np.zeros(len(r), bool)
    nb[1:] |= r[:-1]
    nb[:-1] |= r[1:]
    out = np.zeros(len(raised), bool)
    out[order] = r & nb
    return out


def _unseen_gap(sigma: np.ndarray) -> float:
    """The widest axial stretch (mm) between consecutive samples (sorted along the axis)."""
    if len(sigma) < 2:
        return 0.0
    return float(np.max(np.diff(np.sort(sigma))))


def _deviations(
    config: FeatureConfig,
    sigma: np.ndarray,
    rho: np.ndarray,
    theta: np.ndarray,
    frame: np.ndarray,
    rings: np.ndarray,
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(N,) each point's outward deviation from its ring's wall profile (a ring lying in
    a gap takes its neighbours' mean radius), (R,) the rings' axial positions and (R,)
    True for rings raised above their neighbours (lying in a gap)."""
    coefs, ring_sigma = [], []
    for k in rings:
        on = frame == k
        order = 2 if on.sum() >= 20 else 0
        c = fit_wall_profile(theta[on], rho[on], order, 0.5)
        coefs.append(np.pad(c, (0, 5 - len(c))))
        ring_sigma.append(float(np.median(sigma[on])))
    coef = np.array(coefs)
    rs = np.array(ring_sigma)
    c0 = coef[:, 0].copy()
    for i in range(len(rings)):
        nb = np.abs(rs - rs[i]) <= config.window_mm
        c0[i] = float(np.median(coef[nb, 0]))
    dev = np.zeros(len(sigma))
    raised = np.zeros(len(rings), bool)
    noise0 = 1.4826 * float(np.median(np.abs(coef[:, 0] - c0))) + 1e-9
    peak = _local_peaks(coef[:, 0], rs, config.min_depth_mm, config.joint_max_gap_mm)
    # A running median lags a taper by up to a ring spacing's drop: a ring counts as
    # raised only above the lines both sides' rings give it too.
    _, hi = _wall_level(coef[:, 0], rs, config.window_mm)
    for i, k in enumerate(rings):
        on = frame == k
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


@dataclass(frozen=True)
class _Band:
    """A joint's band: ``lo`` <= sigma - a cos theta - b sin theta <= ``hi`` (mm; a, b 0:
    across the axis; else the plane of a gap the centreline crosses at a slant)."""

    lo: float
    hi: float
    a: float = 0.0
    b: float = 0.0

    def coordinate(self, r: _Rings) -> np.ndarray:
        """(N,) each point's position along the axis across the band's plane (mm)."""
        if self.a == 0.0 and self.b == 0.0:
            return r.sigma
        return r.sigma - self.a * np.cos(r.theta) - self.b * np.sin(r.theta)

    @property
    def slant_mm(self) -> float:
        """How far the plane strays along the axis from a cross-section (mm)."""
        return math.hypot(self.a, self.b)


def _joint_bands(
    config: FeatureConfig, r: _Rings, cand: np.ndarray, link: float, raised: np.ndarray
) -> list[_Band]:
    """The band of each joint: candidates grouped along the axis (``link`` mm: at least
    the rings' spacing), deep over most of the angles at which any sample lies in the
    group's band: across the axis, or else (a gap the centreline crosses at a slant:
    its rings tilted to it, deep each over a part of the circumference) along the plane
    fitted to the candidates, when it strays further along the axis than
    ``joint_link_mm`` (a smaller slant: the band across the axis, whose edges are then
    found along the wall's local axis)."""
    idx = np.flatnonzero(cand)
    s = r.sigma[idx]
    order = np.argsort(s)
    s = s[order]
    cuts = np.flatnonzero(np.diff(s) > link) + 1
    groups = []
    for group in np.split(np.arange(len(s)), cuts):
        on_raised = raised[r.ring_of[idx[order[group]]]]
        if len(group) and s[group[-1]] - s[group[0]] > config.joint_max_gap_mm and on_raised.any():
            # Too wide for a gap: rings far apart linked the candidates of rings lying
            # in a gap with scattered ones. The gap is the raised rings' band.
            a, b = s[group[on_raised]].min(), s[group[on_raised]].max()
            groups.append(group[(s[group] >= a - config.joint_link_mm) & (s[group] <= b + config.joint_link_mm)])
        else:
            groups.append(group)
    bands = []
    for group in groups:
        group = _without_sector_rings(config, r, idx[order[group]], group)
        if len(group) < config.min_points:
            continue
        lo, hi = np.percentile(s[group], [2.0, 98.0])
        lo, hi = float(lo) - 0.25, float(hi) + 0.25
        band = (r.sigma >= lo) & (r.sigma <= hi)
        seen = np.unique((np.degrees(r.theta[band]) % 360 // 10).astype(int))
        have = np.unique((np.degrees(r.theta[idx[order[group]]]) % 360 // 10).astype(int))
        if len(seen) >= 9 and len(have) >= config.joint_coverage * len(seen):
            along, slanted, plane = _deep_share(config, r, idx[order[group]], lo, hi)
            if along >= 0.5:
                bands.append(_Band(lo, hi))
            elif slanted >= 0.5 and plane is not None and plane.slant_mm > config.joint_link_mm:
                bands.append(plane)
            elif slanted >= 0.5:  # a slant within the link's reach: the local axis's edges
                bands.append(_Band(lo, hi))
    return bands


def _deep_share(
    config: FeatureConfig, r: _Rings, members: np.ndarray, lo: float, hi: float
) -> tuple[float, float, _Band | None]:
    """Share of the 10-degree sectors whose samples in the gap's band lie deep (median
    beyond half the joint threshold): the band along the axis (``lo``, ``hi``) and the
    band of the candidates ``members`` along their own plane (sigma - a cos theta - b sin
    theta fitted to them: a gap crossed by tilted rings, or seen along a tilted
    centreline, is a plane across the axial coordinate); and that plane's band (None: one
    ring holds the candidates)."""
    thr = 0.5 * max(config.min_depth_mm, config.joint_noise_factor * r.noise)
    th, s = r.theta[members], r.sigma[members]
    A = np.column_stack([np.ones(len(s)), np.cos(th), np.sin(th)])
    keep = np.ones(len(s), bool)
    for _ in range(3):
        p, *_ = np.linalg.lstsq(A[keep], s[keep], rcond=None)
        res = s - A @ p
        keep = np.abs(res) <= max(2.5 * 1.4826 * float(np.median(np.abs(res[keep]))), 1.0)
    out = []
    lo_p, hi_p = np.percentile(res[keep], [2.0, 98.0]) + p[0]
    plane = _Band(float(lo_p), float(hi_p), float(p[1]), float(p[2]))
    for coord, a, b in ((r.sigma, lo, hi), (plane.coordinate(r), plane.lo, plane.hi)):
        band = (coord >= a - 0.25) & (coord <= b + 0.25)
        sect = (np.degrees(r.theta[band]) % 360 // 10).astype(int)
        med = np.array([np.median(r.dev[band][sect == q]) for q in np.unique(sect)])
        out.append(float(np.mean(med > thr)) if len(med) else 0.0)
    # The plane stands for the gap's only if two rings or more hold its candidates (one
    # ring's candidates span that ring's own plane, whatever the gap's).
    held = np.bincount(r.ring_of[members[keep]])
    return out[0], out[1], plane if int(np.sum(held >= 0.1 * keep.sum())) >= 2 else None


def _without_sector_rings(
    config: FeatureConfig, r: _Rings, members: np.ndarray, group: np.ndarray
) -> np.ndarray:
    """``group`` (positions, matching the candidate indices ``members``) without the
    candidates of a lateral's opening linked to a joint along the axis (sewer-small: the
    joint's ring at -96 mm and the opening's five rings at -78 to -1 mm made one 85 mm
    band): those on rings that each hold only a sector (< joint_coverage / 2 of the angles
    they see), together a narrow one (at most 1 - joint_coverage of the angles seen), and
    lying along the axis beyond ``margin_mm`` of the candidates of the rings deep all round,
    reaching as far out as a lateral's (``lateral_reach_rel``). Rings crossing a gap obliquely also hold a sector each, but inside the gap, where a
    ring lying in it is deep all round: they stay."""
    bins = (np.degrees(r.theta) % 360 // 10).astype(int)
    rings = r.frame[members]
    narrow = []
    for k in np.unique(rings):
        seen_k = np.unique(bins[r.frame == k])
        have_k = np.unique(bins[members[rings == k]])
        if len(have_k) < 0.5 * config.joint_coverage * len(seen_k):
            narrow.append(k)
    if not narrow or len(narrow) == len(np.unique(rings)):
        return group
    is_narrow = np.isin(rings, narrow)
    sector = np.unique(bins[members[is_narrow]])
    seen = np.unique(bins[np.isin(r.frame, np.unique(rings))])
    if len(sector) > (1.0 - config.joint_coverage) * len(seen):
        return group
    lo, hi = np.percentile(r.sigma[members[~is_narrow]], [2.0, 98.0])
    s = r.sigma[members]
    beyond = is_narrow & ((s < lo - config.margin_mm) | (s > hi + config.margin_mm))
    # Only an opening: its points reach into the branch as a lateral's do (scattered noise
    # candidates beyond a joint's rings are left to the joint's measurement).
    reach = config.lateral_reach_rel * 2.0 * float(np.median(r.rho))
    if not beyond.any() or float(np.max(r.dev[members[beyond]])) < reach:
        return group
    return group[~beyond]


def _split(
    s: np.ndarray, dev: np.ndarray, level: float, lower: bool
) -> tuple[float, float] | None:
    """The edge between shallow samples and deep ones (``dev`` > ``level``) beyond it
    (``lower``: deep above the edge) that misclassifies fewest samples, placed where the
    deviation crosses ``level`` between the two samples around it: (position, their
    spacing); None without both kinds."""
    deep = dev > level
    if deep.all() or not deep.any():
        return None
    o = np.argsort(s)
    s, d, v = s[o], deep[o], dev[o]
    if not lower:
        s, d, v = -s[::-1], d[::-1], v[::-1]
    # cost of an edge just before sample i: deep samples below it + shallow ones above.
    cost = np.concatenate([[0], np.cumsum(d)]) + np.concatenate([np.cumsum((~d)[::-1])[::-1], [0]])
    i = int(np.argmin(cost[1:-1])) + 1
    w = s[i] - s[i - 1]
    a, b = min(v[i - 1], level), max(v[i], level)
    f = 0.5 if b - a < 1e-9 else (level - a) / (b - a)
    e = s[i - 1] + f * w
    return (e, w) if lower else (-e, w)


def _edge(
    r: _Rings, s: np.ndarray, near: np.ndarray, level: float, lower: bool
) -> tuple[float, float]:
    """A gap edge (along ``s``, mm) from the samples ``near`` it: the median of the rings' splits, 1-sigma
    their scatter / sqrt(n) (fewer than 3 rings: the pooled split, its sample spacing /
    sqrt(12))."""
    per_ring = []
    for k in np.unique(r.ring_of[near]):
        on = near & (r.ring_of == k)
        got = _split(s[on], r.dev[on], level, lower)
        if got is not None and got[1] < 3.0:
            per_ring.append(got)
    if len(per_ring) >= 3:
        e = np.array([g[0] for g in per_ring])
        w = float(np.median([g[1] for g in per_ring]))
        spread = 1.2533 * float(np.std(e, ddof=1)) / math.sqrt(len(e))
        return float(np.median(e)), math.hypot(spread, w / math.sqrt(12.0 * len(e)))
    got = _split(s[near], r.dev[near], level, lower)
    # Fewer than 3 rings cross the edge: it lies somewhere between two rings' samples
    # (a ring lying in the gap ends short of it), 1-sigma the rings' spacing / sqrt(12).
    gaps = np.diff(np.sort(r.ring_sigma))
    ring_spacing = float(np.median(gaps)) if len(gaps) else 0.0
    if got is None:  # no shallow sample this side: the edge is beyond the deep ones
        return float(np.median(s[near])), max(float(np.ptp(s[near])), ring_spacing) / math.sqrt(12.0)
    return got[0], max(got[1], ring_spacing, 0.1) / math.sqrt(12.0)


def _joint(
    config: FeatureConfig, line: Centreline, r: _Rings, cand: np.ndarray, band: _Band
) -> tuple[Joint, np.ndarray]:
    """A joint in ``band``: gap edges at half depth, depth, offset.

    The edges are found along the straight local axis of the wall either side (the
    fitted centreline tilts through an offset joint: its axial coordinate would slant
    the gap across the rings); a slanted band's along its own plane (the candidates
    showed the gap's plane; the wall either side is then cleared by the slant too)."""
    coord, lo, hi = band.coordinate(r), band.lo, band.hi
    inband = cand & (coord >= lo) & (coord <= hi)
    depth = float(np.percentile(r.dev[inband], 90))
    mid, half = 0.5 * (lo + hi), 0.5 * (hi - lo)
    reach = max(hi - lo, 4.0)
    local = _local_axis(config, line, r, mid, half + config.margin_mm + band.slant_mm)
    near = np.abs(coord - mid) <= half + 2.0 * reach
    s = coord - mid
    if local is not None and local.axis_from_both_sides and band.slant_mm == 0.0:
        s[near] = (_world(line, r, near) - local.centre) @ local.tangent
    lower = near & (s <= 0.0) & (s >= -half - reach)
    upper = near & (s >= 0.0) & (s <= half + reach)
    e_lo, s_lo = _edge(r, s, lower, 0.5 * depth, True)
    e_hi, s_hi = _edge(r, s, upper, 0.5 * depth, False)
    axial, gap = mid + 0.5 * (e_lo + e_hi), e_hi - e_lo
    off: tuple[float | None, ...] = (None, None, None, None)
    if local is not None:
        off = local.offset()
    f = Joint(
        axial_mm=axial,
        axial_sigma_mm=0.5 * math.hypot(s_lo, s_hi),
        gap_mm=gap,
        gap_sigma_mm=math.hypot(s_lo, s_hi),
        offset_mm=off[0],
        offset_sigma_mm=off[1],
        offset_angle_deg=off[2],
        offset_angle_sigma_deg=off[3],
        depth_mm=depth,
        points=int(inband.sum()),
    )
    # Not wall: the gap, its margin, and each edge's 2-sigma (an edge placed short of
    # the true one leaves its ramp, or an offset's step, in the wall).
    mid_s = 0.5 * (e_lo + e_hi)
    lo_clear = 0.5 * gap + config.margin_mm + 2.0 * min(s_lo, config.margin_mm)
    hi_clear = 0.5 * gap + config.margin_mm + 2.0 * min(s_hi, config.margin_mm)
    return f, near & (s - mid_s >= -lo_clear) & (s - mid_s <= hi_clear)


def _world(line: Centreline, r: _Rings, sel: np.ndarray) -> np.ndarray:
    """(M, 3) world positions of the selected points (the inverse of
    :meth:`.Centreline.coordinates`)."""
    k = r.frame[sel]
    return (
        line.centre[k]
        + (r.sigma[sel] - line.arc_mm[k])[:, None] * line.tangent[k]
        + (r.rho[sel] * np.cos(r.theta[sel]))[:, None] * line.normal[k]
        + (r.rho[sel] * np.sin(r.theta[sel]))[:, None] * line.binormal[k]
    )


@dataclass(frozen=True)
class _LocalAxis:
    """The straight wall axis through a joint and the downstream section's step.

    Attributes:
        centre: (3,) the upstream section's axis at the joint (world, mm).
        tangent: (3,) its direction.
        step: (2,) the downstream section's displacement along (normal, binormal) mm.
        cov: (2, 2) its covariance (jackknife over the rings).
        axis_from_both_sides: False with one ring on a side: the axis (``centre``,
            ``tangent``) then rests on the other side's rings, too weak to measure the
            gap's edges along.
    """

    centre: np.ndarray
    tangent: np.ndarray
    step: np.ndarray
    cov: np.ndarray
    axis_from_both_sides: bool = True

    def offset(self) -> tuple[float, float, float, float]:
        """(offset mm, 1-sigma, direction deg from the normal towards the binormal, 1-sigma)."""
        off = float(np.hypot(*self.step))
        u = self.step / max(off, 1e-9)
        perp = np.array([-u[1], u[0]])
        sig = math.sqrt(max(float(u @ self.cov @ u), 0.0))
        ang_sig = math.degrees(math.sqrt(max(float(perp @ self.cov @ perp), 0.0)) / max(off, 1e-9))
        return off, sig, math.degrees(math.atan2(self.step[1], self.step[0])) % 360.0, min(ang_sig, 180.0)


def _local_axis(
    config: FeatureConfig, line: Centreline, r: _Rings, axial: float, clear: float
) -> _LocalAxis | None:
    """The wall within ``config.window_mm`` either side of a joint at ``axial`` (``clear``
    of it left out) in the centreline's frame there: rho = per-ring radius + centre
    drift (quadratic along the axis; linear with one ring on a side) + ovality + the
    downstream centre's step. None without a ring on either side or with fewer than 3."""
    k0 = int(np.argmin(np.abs(line.arc_mm - axial)))
    t, n, b = line.tangent[k0], line.normal[k0], line.binormal[k0]
    c = line.centre[k0] + (axial - line.arc_mm[k0]) * t
    near = (np.abs(r.sigma - axial) > clear) & (np.abs(r.sigma - axial) <= config.window_mm)
    near &= r.dev < max(config.min_depth_mm, config.noise_factor * r.noise)
    p = _world(line, r, near) - c
    s, x, y = p @ t, p @ n, p @ b
    down = s > 0
    ring = r.ring_of[near]
    sides = (len(np.unique(ring[~down])), len(np.unique(ring[down])))
    if min(sides) < 1 or sum(sides) < 3:
        return None
    # One ring on a side (a joint near the run's end): the drift straight, from the
    # other side's rings.
    quad = min(sides) >= 2
    rho, th = np.hypot(x, y), np.arctan2(y, x)
    u = s / config.window_mm
    cos, sin = np.cos(th), np.sin(th)
    drift = [u * cos, u * sin] + ([u * u * cos, u * u * sin] if quad else [])
    cols = np.column_stack([cos, sin, *drift, np.cos(2 * th), np.sin(2 * th), down * cos, down * sin])
    nc = cols.shape[1]
    _, ring_col = np.unique(ring, return_inverse=True)

    def solve(keep: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        A = np.column_stack([cols[keep], np.eye(ring_col.max() + 1)[ring_col[keep]]])
        coef, *_ = np.linalg.lstsq(A, rho[keep], rcond=None)
        res = rho[keep] - A @ coef
        ok = np.abs(res) <= 4.0 * 1.4826 * np.median(np.abs(res)) + 1e-9
        coef, *_ = np.linalg.lstsq(A[ok], rho[keep][ok], rcond=None)
        res = rho[keep][ok] - A[ok] @ coef
        # The step's least-squares covariance (residual variance x (A^T A)^-1).
        var = float(res @ res) / max(int(ok.sum()) - A.shape[1], 1)
        ls = var * np.linalg.pinv(A[ok].T @ A[ok])[nc - 2 : nc, nc - 2 : nc]
        return coef[:nc], ls

    coef, ls_cov = solve(np.ones(len(rho), bool))
    # Jackknife over the rings (only leaving wall on both sides).
    jack = np.array(
        [solve(ring != q)[0][nc - 2 : nc] for q in np.unique(ring)
         if len(np.unique(ring[~down & (ring != q)])) and len(np.unique(ring[down & (ring != q)]))]
    ).reshape(-1, 2)
    m = len(jack)
    cov = (m - 1) * np.cov(jack.T, bias=True) if m >= 3 else np.eye(2) * r.noise**2
    if not quad:
        cov = cov + ls_cov
    tangent = t + (coef[2] * n + coef[3] * b) / config.window_mm
    return _LocalAxis(
        c + coef[0] * n + coef[1] * b, tangent / np.linalg.norm(tangent), coef[nc - 2 : nc], cov, quad
    )


def _chords(
    sigma: np.ndarray, u: np.ndarray, frame: np.ndarray, members: np.ndarray, sample: float, radius: float
) -> np.ndarray:
    """(M, 4) per ring crossing the hole: axial position, chord centre and half-width
    (arc mm; half a sample added: the edges lie between samples), ring index. The axial
    position is the ring's own at the chord's centre (:func:`_ring_axial`), not its deep
    samples': those lie out in the branch, where the pipe coordinates of a ring tilted
    to the axis, or of a centreline through a bend, stray along the axis by their depth
    (random-features-small seed 1, a 132 mm branch in an elbow: 20-80 mm)."""
    rows = []
    for k in np.unique(frame[members]):
        m = members[frame[members] == k]
        if len(m) < 2:
            continue
        c = 0.5 * (u[m].max() + u[m].min())
        on = np.flatnonzero(frame == k)
        wall = on[~np.isin(on, m)]
        z = _ring_axial(sigma[wall], u[wall] / radius, c / radius) if len(wall) >= 8 else float(np.median(sigma[m]))
        rows.append((z, c, 0.5 * (u[m].max() - u[m].min()) + 0.5 * sample, float(k)))
    return np.array(rows).reshape(-1, 4)


def _ring_axial(sigma: np.ndarray, phi: np.ndarray, at: float) -> float:
    """Axial position (mm) at angle ``at`` (rad) of a ring whose wall samples lie at
    (``sigma`` mm, ``phi`` rad): the plane sigma = a + b cos phi + c sin phi fitted to
    them (twice, without the samples beyond 3 robust sigmas: the rim's stray ones)."""
    A = np.column_stack([np.ones(len(phi)), np.cos(phi), np.sin(phi)])
    keep = np.ones(len(phi), bool)
    for _ in range(2):
        p, *_ = np.linalg.lstsq(A[keep], sigma[keep], rcond=None)
        res = sigma - A @ p
        keep = np.abs(res) <= max(3.0 * 1.4826 * float(np.median(np.abs(res[keep]))), 0.5)
    return float(p[0] + p[1] * math.cos(at) + p[2] * math.sin(at))


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
    sigma: np.ndarray,
    theta: np.ndarray,
    frame: np.ndarray,
    members: np.ndarray,
    radius: float,
    spacing: float,
    gaps: Sequence[ReturnGap] = (),
) -> tuple[Lateral, np.ndarray]:
    """A lateral's opening from its cluster of deep samples ``members`` and the rings'
    stretches without returns across it (``gaps``; either may be empty, not both):
    centre, angle and diameter (jackknife sigmas)."""
    th = np.concatenate([theta[members], [g.centre for g in gaps]])
    th0 = math.atan2(float(np.mean(np.sin(th))), float(np.mean(np.cos(th))))
    u = ((theta - th0 + np.pi) % (2 * np.pi) - np.pi) * radius
    rings = np.unique(np.concatenate([frame[members], [g.ring for g in gaps]]).astype(int))
    steps = []
    for k in rings:
        d_u = np.diff(np.sort(u[frame == k]))
        steps.append(float(np.median(d_u[d_u > 0])) if (d_u > 0).any() else 1.0)
    sample = float(np.median(steps))
    ch = _merged_chords(_chords(sigma, u, frame, members, sample, radius), _gap_chords(gaps, th0, radius))[:, :3]
    zc, uc, b, a = _ellipse(ch)
    est = [(zc, uc, b)]
    if len(ch) >= 4:
        est += [_ellipse(np.delete(ch, i, axis=0))[:3] for i in range(len(ch))]
    arr = np.array(est)
    n = len(arr) - 1
    jk = np.sqrt((n - 1) / n * np.sum((arr[1:] - arr[1:].mean(axis=0)) ** 2, axis=0)) if n >= 3 else np.zeros(3)
    # Beside the jackknife: where the rings fall along the hole (their spacing), and the
    # edge samples' reach (a ring's light is lost or half-lit at the rim: up to a sample).
    s_z = math.hypot(float(jk[0]), spacing / math.sqrt(12.0))
    s_u = math.hypot(float(jk[1]), sample / math.sqrt(12.0))
    s_b = math.hypot(float(jk[2]), sample)
    diameter = 2.0 * radius * math.sin(min(b / radius, 0.5 * math.pi))
    f = Lateral(
        axial_mm=zc,
        axial_sigma_mm=s_z,
        angle_deg=math.degrees(th0 + uc / radius) % 360.0,
        angle_sigma_deg=math.degrees(s_u / radius),
        diameter_mm=diameter,
        diameter_sigma_mm=2.0 * s_b * abs(math.cos(min(b / radius, 0.5 * math.pi))),
        points=len(members),
    )
    m = config.margin_mm
    inside = ((sigma - zc) / (a + m)) ** 2 + ((u - uc) / (b + m)) ** 2 <= 1.0
    inside[members] = True
    return f, inside


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
