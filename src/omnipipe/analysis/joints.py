"""Joints: found in the rings (:class:`.feature_rings.Rings`), measured, and taken out of
the wall.

Points further out than the threshold (``max(min_depth_mm, joint_noise_factor x
noise)``) are candidates. They are grouped along the axis (a gap between them wider than
``joint_link_mm`` splits groups); a group whose axial band is seen deep over most
(``joint_coverage``) of the angles at which any ring samples that band is a joint. A ring
tilted to the axis crosses a narrow gap along a slant, so the gap is seen by the rings
together, not by one ring covering the circumference; a gap lying between two rings that
no ring crosses cannot be seen (``FeatureSearch.unseen_gap_mm``: the widest axial stretch
no ring sampled), but its offset can (:func:`offset_joints`). Each gap edge (at half the
gap's depth) is where deep samples give way to shallow ones: per ring crossing it, the
split that misclassifies fewest samples; the edge is their median, 1-sigma their scatter
/ sqrt(n) (fewer than 3 rings: the rings' spacing / sqrt(12)). The offset is fitted to
the wall within ``window_mm`` on both sides (the gap left out) in a straight frame
through the joint: rho = per-ring radius + centre drift (quadratic along the axis, so a
bend does not pass for an offset) + ovality + a step of the downstream centre (the
offset); its sigma by jackknife over the rings.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass, replace

import numpy as np

from omnipipe.analysis.centreline import Centreline
from omnipipe.analysis.feature_rings import FeatureConfig, Rings, robust_sine_fit
from omnipipe.analysis.feature_types import Joint, Lateral, PointFeature
from omnipipe.analysis.ring_spans import RingSpans


def gap_joints(
    config: FeatureConfig, line: Centreline, r: Rings, cand: np.ndarray, link: float, raised: np.ndarray
) -> list[tuple[Joint, np.ndarray]]:
    """The joints whose gap the rings sampled: the candidates ``cand`` (N,) grouped into
    bands (:func:`_joint_bands`, ``link`` mm) and measured (:func:`_joint`); a band
    wider than ``joint_max_gap_mm`` (a taper's tilted rings) is none. (joint, its
    not-wall mask) each."""
    out = []
    for band in _joint_bands(config, r, cand, link, raised):
        f, mask = _joint(config, line, r, cand, band)
        if 0.0 < f.gap_mm <= config.joint_max_gap_mm:
            out.append((f, mask))
    return out


def offset_joints_kept(first: Sequence[PointFeature], second: Sequence[PointFeature]) -> list[Joint]:
    """The joints of ``first`` found by their offset alone (:func:`offset_joints`) that
    ``second`` (the search after the sections either side of the offset joints were
    fitted apart) lost: the break at such a joint straightens the centreline's step the
    search saw, and the wall either side then fits one cylinder each with the joint's
    step between them."""
    return [
        f for f in first
        if isinstance(f, Joint) and f.points == 0 and f.offset_mm is not None
        and not any(isinstance(g, Joint) and abs(g.axial_mm - f.axial_mm) <= 3.0 * f.axial_sigma_mm + 0.5 * g.gap_mm
                    for g in second)
    ]


def offset_joints(
    config: FeatureConfig, line: Centreline, r: Rings, found: list[PointFeature]
) -> list[Joint]:
    """Joints seen by their offset alone: a gap that lies between two rings (no ring
    sampled it) but whose downstream section is displaced. The recentred centreline
    steps sideways there (by the offset) between the two rings' stations: a step of at
    least ``joint_offset_min_mm`` and ``joint_offset_factor`` x the median step of the
    run (a bend's or a taper's drift), away from the joints and laterals already found
    (a hole's missing or branch-lit samples pull its rings' section centres sideways:
    bench seeds 4, 18, 27 stepped 4.9-9.8 mm within a lateral's reach), whose offset
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
        if b <= a or near or _at_an_opening(config, found, a, b):
            continue  # a joint found there, or a lateral's hole pulling the centres
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


def _at_an_opening(config: FeatureConfig, found: Sequence[PointFeature], a: float, b: float) -> bool:
    """Whether the axial stretch ``a``..``b`` (mm) meets a found lateral's reach: its
    opening's diameter / 2 + ``margin_mm`` + 3 axial sigmas either side of its centre."""
    for f in found:
        if isinstance(f, Lateral):
            half = 0.5 * f.diameter_mm + config.margin_mm + 3.0 * (f.axial_sigma_mm or 0.0)
            if a <= f.axial_mm + half and b >= f.axial_mm - half:
                return True
    return False


@dataclass(frozen=True)
class _Band:
    """A joint's band: ``lo`` <= sigma - a cos theta - b sin theta <= ``hi`` (mm; a, b 0:
    across the axis; else the plane of a gap the centreline crosses at a slant;
    ``ring_plane``: the plane of one ring lying in the gap, square to it; ``crossed``: a
    gap every ring crosses along a slant, :func:`_crossed_band`)."""

    lo: float
    hi: float
    a: float = 0.0
    b: float = 0.0
    ring_plane: bool = False
    crossed: bool = False

    def coordinate(self, r: Rings) -> np.ndarray:
        """(N,) each point's position along the axis across the band's plane (mm)."""
        if self.a == 0.0 and self.b == 0.0:
            return r.sigma
        with np.errstate(invalid="ignore"):  # a NaN angle (in no sector) stays NaN
            return r.sigma - self.a * np.cos(r.theta) - self.b * np.sin(r.theta)

    @property
    def slant_mm(self) -> float:
        """How far the plane strays along the axis from a cross-section (mm)."""
        return math.hypot(self.a, self.b)


def _joint_bands(
    config: FeatureConfig, r: Rings, cand: np.ndarray, link: float, raised: np.ndarray
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
            # in a gap with scattered ones. Each block of raised rings is a gap's band.
            groups += _raised_groups(config, r, idx[order[group]], group, s[group], raised)
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
            along, slanted, plane = _deep_share(config, r, idx[order[group]], lo, hi, raised)
            if along >= 0.5:
                bands.append(_Band(lo, hi))
            elif slanted >= 0.5 and plane is not None and plane.slant_mm > config.joint_link_mm:
                bands.append(plane)
            elif slanted >= 0.5:  # a slant within the link's reach: the local axis's edges
                bands.append(_Band(lo, hi))
        elif (crossed := _crossed_band(config, r, idx[order[group]])) is not None:
            bands.append(crossed)
    return bands


def _crossed_band(config: FeatureConfig, r: Rings, members: np.ndarray) -> _Band | None:
    """The band of a gap that every ring crosses along a slant (rings tilted to the pipe
    and spanning more of the axis than the rings' travel: each sees the gap on a short
    arc, together on a part of the circumference only; bench seed 10, rings tilted 7.7
    deg spanning 73 mm of a 44 mm run, the gap seen at 60-130 deg): the candidates
    ``members`` held by ``joint_min_rings`` rings or more, none holding half of them,
    lie along one plane (:func:`.feature_rings.robust_sine_fit`) whose band is no wider
    than ``joint_max_gap_mm``; the rings sample that band on at least 9 ten-degree
    sectors and on half of them or more the samples lie deep (median beyond half the
    joint threshold); and the band reaches no further out than a shallow gap does
    (the 90th percentile of the candidates within ``lateral_reach_rel`` of the diameter:
    a lateral's opening reaches into its branch). None otherwise. Along the plane
    where it strays further along the axis than ``joint_link_mm``; else across the axis.
    Its offset is not measured: the rings straddle the gap, none lies wholly on a side."""
    held = np.bincount(r.ring_of[members])
    if np.count_nonzero(held) < config.joint_min_rings or held.max() > 0.5 * len(members):
        return None
    p, res, keep = robust_sine_fit(r.sigma[members], r.theta[members], 3, 2.5, 1.0)
    lo, hi = np.percentile(res[keep], [2.0, 98.0]) + p[0]
    if hi - lo > config.joint_max_gap_mm:
        return None
    if float(np.percentile(r.dev[members], 90)) >= config.lateral_reach_rel * 2.0 * float(np.median(r.rho)):
        return None
    plane = _Band(float(lo), float(hi), float(p[1]), float(p[2]))
    # The band's samples found a block of the run at a time (no whole-run coordinate).
    band = np.concatenate([
        a + np.flatnonzero((c >= plane.lo - 0.25) & (c <= plane.hi + 0.25))
        for a in range(0, len(r.sigma), 1 << 16)
        for c in (plane.coordinate(Rings(
            r.sigma[a : a + (1 << 16)], r.rho, r.theta[a : a + (1 << 16)], r.frame, r.ring_of, r.ring_sigma,
            r.dev, r.noise,
        )),)
    ] or [np.zeros(0, np.intp)])
    sect = (np.degrees(r.theta[band]) % 360 // 10).astype(int)
    seen = np.unique(sect)
    if len(seen) < 9:
        return None
    thr = 0.5 * max(config.min_depth_mm, config.joint_noise_factor * r.noise)
    deep = np.mean([np.median(r.dev[band][sect == q]) > thr for q in seen])
    if deep < 0.5:  # as a band's deep share along its plane (:func:`_deep_share`)
        return None
    if plane.slant_mm > config.joint_link_mm:
        return replace(plane, crossed=True)
    return _Band(float(lo), float(hi), crossed=True)


def _raised_groups(
    config: FeatureConfig, r: Rings, members: np.ndarray, group: np.ndarray, s: np.ndarray, raised: np.ndarray
) -> list[np.ndarray]:
    """``group`` (positions, matching the candidate indices ``members`` at axial ``s``)
    split at its blocks of raised rings (consecutive along the axis: the rings lying in
    one gap; bench seed 31: two joints 37 mm apart on 6-mm spaced rings, tilted 3-10 deg
    to the fitted axis, their candidates linked over the whole run): per block, its
    rings' candidates and the other rings' within ``joint_link_mm`` of their axial
    extent (rings crossing the gap's edges at a slant)."""
    ring = r.ring_of[members]
    pos = np.empty(len(r.ring_sigma), int)
    pos[np.argsort(r.ring_sigma)] = np.arange(len(r.ring_sigma))
    up = np.unique(ring[raised[ring]])
    up = up[np.argsort(pos[up])]
    blocks = np.split(up, np.flatnonzero(np.diff(pos[up]) > 1) + 1)
    out = []
    for block in blocks:
        own = np.isin(ring, block)
        a, b = s[own].min(), s[own].max()
        near = ~raised[ring] & (s >= a - config.joint_link_mm) & (s <= b + config.joint_link_mm)
        out.append(group[own | near])
    return out


def _deep_share(
    config: FeatureConfig, r: Rings, members: np.ndarray, lo: float, hi: float, raised: np.ndarray
) -> tuple[float, float, _Band | None]:
    """Share of the 10-degree sectors whose samples in the gap's band lie deep (median
    beyond half the joint threshold): the band along the axis (``lo``, ``hi``) and the
    band of the candidates ``members`` along their own plane (sigma - a cos theta - b sin
    theta fitted to them: a gap crossed by tilted rings, or seen along a tilted
    centreline, is a plane across the axial coordinate); and that plane's band (None: one
    ring holds the candidates, unless it lies in the gap: ``raised``, (R,) per ring)."""
    thr = 0.5 * max(config.min_depth_mm, config.joint_noise_factor * r.noise)
    p, res, keep = robust_sine_fit(r.sigma[members], r.theta[members], 3, 2.5, 1.0)
    out = []
    lo_p, hi_p = np.percentile(res[keep], [2.0, 98.0]) + p[0]
    plane = _Band(float(lo_p), float(hi_p), float(p[1]), float(p[2]))
    # Each band's samples found a block of the run at a time (no whole-run coordinate
    # nor mask: :func:`_band_samples`).
    for along, a, b in ((_Band(lo, hi), lo, hi), (plane, plane.lo, plane.hi)):
        band = _band_samples(r, along, a - 0.25, b + 0.25)
        sect = (np.degrees(r.theta[band]) % 360 // 10).astype(int)
        med = np.array([np.median(r.dev[band][sect == q]) for q in np.unique(sect)])
        out.append(float(np.mean(med > thr)) if len(med) else 0.0)
    # The plane stands for the gap's only if two rings or more hold its candidates (one
    # ring's candidates span that ring's own plane, whatever the gap's).
    held = np.flatnonzero(np.bincount(r.ring_of[members[keep]]) >= 0.1 * keep.sum())
    if len(held) >= 2:
        return out[0], out[1], plane
    # Or else one ring raised all round (lying in the gap, square to it: its plane is the
    # gap's; bench seed 31's rings, tilted to a centreline fitted off the axis), not at
    # the run's end (with rings on one side only its level says no gap: bench seed 1's
    # first ring in an elbow, 14 deg to the fitted axis).
    inner = len(held) == 1 and r.ring_sigma.min() < r.ring_sigma[held[0]] < r.ring_sigma.max()
    return out[0], out[1], replace(plane, ring_plane=True) if inner and raised[held].all() else None


BAND_BLOCK = 1 << 16
"""Samples whose coordinate across a band's plane :func:`_band_samples` computes at once."""


def _band_samples(r: Rings, plane: _Band, lo: float, hi: float, block: int | None = None) -> np.ndarray:
    """Ascending indices of the samples whose coordinate across ``plane``
    (:meth:`_Band.coordinate`) lies in [lo, hi]: ``np.flatnonzero((c >= lo) & (c <= hi))``
    of the whole run's coordinate ``c``, a block of samples (:data:`BAND_BLOCK`) at a time."""
    block = block or BAND_BLOCK
    parts = [
        a + np.flatnonzero((c >= lo) & (c <= hi))
        for a in range(0, len(r.sigma), block)
        for c in (plane.coordinate(replace(r, sigma=r.sigma[a : a + block], theta=r.theta[a : a + block])),)
    ]
    return np.concatenate(parts) if parts else np.zeros(0, np.intp)


def _without_sector_rings(
    config: FeatureConfig, r: Rings, members: np.ndarray, group: np.ndarray
) -> np.ndarray:
    """``group`` (positions, matching the candidate indices ``members``) without the
    candidates of a lateral's opening linked to a joint along the axis (sewer-small: the
    joint's ring at -96 mm and the opening's five rings at -78 to -1 mm made one 85 mm
    band): those on rings that each hold only a sector (< joint_coverage / 2 of the angles
    they see), together a narrow one (at most 1 - joint_coverage of the angles seen), and
    lying along the axis beyond ``margin_mm`` of the candidates of the rings deep all round,
    reaching as far out as a lateral's (``lateral_reach_rel``). Rings crossing a gap obliquely also hold a sector each, but inside the gap, where a
    ring lying in it is deep all round: they stay."""
    # Each ring's sectors from its own points (:class:`~omnipipe.analysis.ring_spans.RingSpans`:
    # no whole-run array of every point's sector, nor a mask of the run's points per ring).
    def _sector_bins(theta: np.ndarray) -> np.ndarray:
        return (np.degrees(theta) % 360 // 10).astype(int)  # 10-degree sectors, 0..35

    rings = r.frame[members]
    have = _sector_bins(r.theta[members])
    ids = np.unique(rings)
    spans = RingSpans(r.frame, ids)
    seen_of = [np.unique(_sector_bins(spans.values(i, r.theta))) for i in range(len(ids))]
    narrow = [
        k for k, seen_k in zip(ids, seen_of, strict=True)
        if len(np.unique(have[rings == k])) < 0.5 * config.joint_coverage * len(seen_k)
    ]
    if not narrow or len(narrow) == len(ids):
        return group
    is_narrow = np.isin(rings, narrow)
    sector = np.unique(have[is_narrow])
    seen = np.unique(np.concatenate(seen_of))
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
    r: Rings, s: np.ndarray, near: np.ndarray, level: float, lower: bool
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
    config: FeatureConfig, line: Centreline, r: Rings, cand: np.ndarray, band: _Band
) -> tuple[Joint, np.ndarray]:
    """A joint in ``band``: gap edges at half depth, depth, offset.

    The edges are found along the straight local axis of the wall either side (the
    fitted centreline tilts through an offset joint: its axial coordinate would slant
    the gap across the rings); a slanted band's along its own plane (the candidates
    showed the gap's plane; the wall either side is then cleared by the slant too).
    A gap every ring crosses along a slant (``band.crossed``) is read over each ring's
    blur: only 0 < gap <= the reading is known, whose uniform sigma is added."""
    coord, lo, hi = band.coordinate(r), band.lo, band.hi
    inband = cand & (coord >= lo) & (coord <= hi)
    depth = float(np.percentile(r.dev[inband], 90))
    mid, half = 0.5 * (lo + hi), 0.5 * (hi - lo)
    # The edges are sought a band's width beyond it; a ring's plane lying in the gap, at
    # least to the next rings' samples (its edges lie between rings).
    spacing = np.diff(np.sort(r.ring_sigma))
    between = 1.5 * float(np.median(spacing)) if band.ring_plane and len(spacing) else 0.0
    reach = max(hi - lo, 4.0, between)
    # A side with no shallow sample within that reach (one ring lying in the gap, the
    # next ring further out) reaches on to the nearest shallow sample
    # within ``window_mm``: its edge lies between the two rings (else it would be the deep
    # samples' median, inside the gap), along a coordinate that follows the wall
    # (:data:`REACH_TILT_DEG`).
    local = _wall_axis(config, line, r, mid, half + config.margin_mm + band.slant_mm)
    near = np.abs(coord - mid) <= half + 2.0 * reach
    wide = np.abs(coord - mid) <= half + max(2.0 * reach, config.window_mm)
    s = coord - mid
    along = True  # the coordinate follows the wall's axis within REACH_TILT_DEG
    if local is not None and local.axis_from_both_sides and band.slant_mm == 0.0:
        s[wide] = (_world(line, r, wide) - local.centre) @ local.tangent
        k0 = int(np.argmin(np.abs(line.arc_mm - mid)))
        along = abs(float(local.tangent @ line.tangent[k0])) >= math.cos(math.radians(REACH_TILT_DEG))
    shallow = wide & (r.dev <= 0.5 * depth)
    lower = near & (s <= 0.0) & (s >= -half - reach)
    if along and not (lower & shallow).any() and (shallow & (s < 0.0)).any():
        lower = wide & (s <= 0.0) & (s >= float(np.max(s[shallow & (s < 0.0)])) - 1.0)
    upper = near & (s >= 0.0) & (s <= half + reach)
    if along and not (upper & shallow).any() and (shallow & (s > 0.0)).any():
        upper = wide & (s >= 0.0) & (s <= float(np.min(s[shallow & (s > 0.0)])) + 1.0)
    near = near | lower | upper
    e_lo, s_lo = _edge(r, s, lower, 0.5 * depth, True)
    e_hi, s_hi = _edge(r, s, upper, 0.5 * depth, False)
    axial, gap = mid + 0.5 * (e_lo + e_hi), e_hi - e_lo
    gap_sigma = math.hypot(s_lo, s_hi)
    if band.crossed:  # each ring blurs the gap over its slant: only 0 < gap <= read is known
        gap_sigma = math.hypot(gap_sigma, gap / math.sqrt(12.0))
    off: tuple[float | None, ...] = (None, None, None, None)
    if local is not None and not band.crossed:  # rings crossing the gap: no wall either side
        off = local.offset()
    f = Joint(
        axial_mm=axial,
        axial_sigma_mm=0.5 * math.hypot(s_lo, s_hi),
        gap_mm=gap,
        gap_sigma_mm=gap_sigma,
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


def _world(line: Centreline, r: Rings, sel: np.ndarray) -> np.ndarray:
    """(M, 3) world positions of the selected points (the inverse of
    :meth:`.Centreline.coordinates`)."""
    k = r.frame[sel]
    return (
        line.centre[k]
        + (r.sigma[sel] - line.arc_mm[k])[:, None] * line.tangent[k]
        + (r.rho[sel] * np.cos(r.theta[sel]))[:, None] * line.normal[k]
        + (r.rho[sel] * np.sin(r.theta[sel]))[:, None] * line.binormal[k]
    )


REACH_TILT_DEG = 5.0
"""A gap's edge is sought on past the band's reach (to the nearest shallow sample) only
along a coordinate within this angle of the centreline's tangent (deg): a local axis
tilted further (a fit that trades its drift for the step) would carry that search into
another section's wall."""


LOCAL_AXIS_MAX_TILT_DEG = 20.0
"""A joint's local axis whose fitted drift tilts it further than this from the
centreline's tangent (deg) is a degenerate fit, not the wall's: few rings a side, or a
neighbouring joint's step in the window, traded for the drift (bench seeds 13 and 31:
54-68 deg, their offsets tens of mm for 2-7). The wall then is refitted along the
centreline's tangent (no drift terms)."""


def _wall_axis(
    config: FeatureConfig, line: Centreline, r: Rings, axial: float, clear: float
) -> _LocalAxis | None:
    """The joint's local axis (:func:`_local_axis`); where its drift tilts it beyond
    :data:`LOCAL_AXIS_MAX_TILT_DEG` from the centreline's tangent, the fit without drift
    terms instead (the edges then are read along the centreline, as without a local
    axis)."""
    local = _local_axis(config, line, r, axial, clear)
    if local is None:
        return None
    k0 = int(np.argmin(np.abs(line.arc_mm - axial)))
    if abs(float(local.tangent @ line.tangent[k0])) >= math.cos(math.radians(LOCAL_AXIS_MAX_TILT_DEG)):
        return local
    return _local_axis(config, line, r, axial, clear, drift_terms=False)


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
    config: FeatureConfig, line: Centreline, r: Rings, axial: float, clear: float, drift_terms: bool = True
) -> _LocalAxis | None:
    """The wall within ``config.window_mm`` either side of a joint at ``axial`` (``clear``
    of it left out) in the centreline's frame there: rho = per-ring radius + centre
    drift (quadratic along the axis; linear with one ring on a side; none without
    ``drift_terms``: the axis then is the centreline's tangent) + ovality + the
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
    drift = ([u * cos, u * sin] + ([u * u * cos, u * u * sin] if quad else [])) if drift_terms else []
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
    tangent = t + (coef[2] * n + coef[3] * b) / config.window_mm if drift_terms else t
    return _LocalAxis(
        c + coef[0] * n + coef[1] * b, tangent / np.linalg.norm(tangent), coef[nc - 2 : nc], cov, quad
    )
