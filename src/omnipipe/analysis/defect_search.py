"""The defect search's candidates: where they may not be told from a feature, the
detector's scales, and the connected groups of samples beyond its threshold.

:class:`FeatureZone` is a found feature's reach (axial band, mm, and optionally an arc
around the pipe, mm). :func:`scales` measures a deviation map (:class:`Scales`: robust
noise, threshold, ring and sample spacings and the link distances, all mm);
:func:`clusters` yields each candidate of one sign (-1: bulges, +1: dents) as ascending
sample indices: samples beyond the threshold with a supported neighbour on their ring
(:func:`_supported_beyond`), linked across neighbouring rings and around the seam.
"""

from __future__ import annotations

from collections.abc import Iterator
from dataclasses import dataclass

import numpy as np
from scipy.sparse import coo_matrix
from scipy.sparse.csgraph import connected_components
from scipy.spatial import cKDTree

from omnipipe.analysis.ring_spans import RingSpans
from omnipipe.analysis.wall_profile import WallSamples, axial_range


@dataclass(frozen=True)
class FeatureZone:
    """Where a found feature (a joint's gap, a lateral's opening) may reach, with its
    uncertainty: a detection there seen by one ring cannot be told from the feature's rim.

    Attributes:
        axial_from_mm, axial_to_mm: the axial band (contract convention, mm).
        arc_mm: centre of the zone around the pipe (mm, as :attr:`.wall_profile.WallSamples.arc_mm`), or
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


@dataclass(frozen=True)
class Scales:
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


def scales(samples: WallSamples, min_height_mm: float, noise_factor: float) -> Scales:
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
    return Scales(
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


def clusters(
    samples: WallSamples, sc: Scales, sign: float, min_points: int
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
        for members in split_at_clean_rings(samples, sc, sign, cand[label == c]):
            if len(members) < min_points:
                continue
            if len(np.unique(samples.ring[members])) == 1 and len(members) < 2 * min_points:
                # A speck on one ring, narrower than a few samples: an extraction outlier
                # cluster (seen beside deep, steep defects), below any size the run resolves.
                continue
            yield members


def split_at_clean_rings(samples: WallSamples, sc: Scales, sign: float, members: np.ndarray) -> list[np.ndarray]:
    """``members`` (ascending sample indices of one linked group) cut wherever a ring
    not in it measured the wall clean between two of its rings along the axis, at
    their angles (:func:`_clean_between`): the link distance across rings (1.5 wide
    ring spacings) reaches past a ring, and a bump cannot skip the ring through its
    middle. Streaks of stray peaks at the same angles of every other ring (a brick
    wall's mortar lines taken for the laser peak, random-features-small seed 14: 7-9 mm
    on two rings 16 mm apart, the ring between them within 3 mm) are then each one
    ring's, judged as such (:func:`.defect_truncation.one_sided`). Pieces in axial
    order of their rings; ``members`` itself when nothing cuts it."""
    ring = samples.ring[members]
    rings = np.unique(ring)
    if len(rings) < 2:
        return [members]
    z = np.array([float(np.median(samples.sigma_mm[members[ring == k]])) for k in rings])
    order = np.argsort(z, kind="stable")
    rings, z = rings[order], z[order]
    pieces, start = [], 0
    for i in range(len(rings) - 1):
        if _clean_between(samples, sc, sign, members, rings, (rings[i], rings[i + 1]), (z[i], z[i + 1])):
            pieces.append(rings[start : i + 1])
            start = i + 1
    if not pieces:
        return [members]
    pieces.append(rings[start:])
    return [members[np.isin(ring, p)] for p in pieces]


CLEAN_MIN_SAMPLES = 5
"""Samples a ring needs at a candidate's angles to show the wall there clean
(:func:`_clean_between`)."""


def _clean_between(
    samples: WallSamples,
    sc: Scales,
    sign: float,
    members: np.ndarray,
    rings: np.ndarray,
    pair: tuple[int, int],
    z: tuple[float, float],
) -> bool:
    """Whether a ring outside ``rings`` (the group's) measured the wall clean strictly
    between the group's rings ``pair`` (median axial positions ``z``, mm) at their
    angles: at least :data:`CLEAN_MIN_SAMPLES` of its samples within the arc the two
    rings' members span (plus a link distance) and between their axial extents, none
    beyond the threshold (``sign`` x deviation) and their median within half of it."""
    circ = samples.circumference_mm
    on = members[np.isin(samples.ring[members], pair)]
    ref = float(samples.arc_mm[on[0]])
    du = (samples.arc_mm[on] - ref + 0.5 * circ) % circ - 0.5 * circ
    lo_u, hi_u = float(du.min()) - sc.du, float(du.max()) + sc.du
    z_lo = float(samples.sigma_mm[members[samples.ring[members] == pair[0]]].max())
    z_hi = float(samples.sigma_mm[members[samples.ring[members] == pair[1]]].min())
    if not z[0] < z[1] or z_hi <= z_lo:
        return False
    idx = axial_range(samples, z_lo, z_hi)
    u = (samples.arc_mm[idx] - ref + 0.5 * circ) % circ - 0.5 * circ
    zs = samples.sigma_mm[idx]
    idx = idx[(u >= lo_u) & (u <= hi_u) & (zs > z_lo) & (zs < z_hi) & ~np.isin(samples.ring[idx], rings)]
    for k in np.unique(samples.ring[idx]):
        value = sign * samples.deviation_mm[idx[samples.ring[idx] == k]]
        if len(value) >= CLEAN_MIN_SAMPLES and value.max() <= sc.threshold and np.median(value) <= 0.5 * sc.threshold:
            return True
    return False


def _supported_beyond(samples: WallSamples, sign: float, sc: Scales) -> np.ndarray:
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
    arc: np.ndarray, ring: np.ndarray, value: np.ndarray, circ: float, sc: Scales, wrap: bool
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
