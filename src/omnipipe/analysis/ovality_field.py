"""The wall's ovality along the pipe from every ring's points at their own axial
positions (:func:`ovality_field`), and the ovality stretches read from it
(:func:`field_stretches`).

A station's Fourier fit (:mod:`.station_profiles`) takes its ring as one cross-section.
A laser ring tilted against the pipe spreads its points along the axis (a rig leaning
in a bend, the ring ahead of it: 33-47 mm on random-features seed 26's 211 mm pipe):
an ovality stretch shorter than that footprint is diluted in every ring crossing it
(seed 26's 18 mm, 4.3 % stretch read 0.1-0.9 % by its stations), and a diameter change
within it (a taper's end, a joint) reads as ovality on the stations beside it (seed 26's
1.5-1.9 % past the stretch; seed 11's 5.8-7.0 % past a steep taper's end).

The field models each point's radius rho (mm) about the centreline at its angle theta
and axial position s as

    rho = c0(s) + a1_k cos theta + b1_k sin theta + a2(s) cos 2 theta + b2(s) sin 2 theta,

with c0, a2, b2 linear between nodes every :data:`NODE_MM` along the axis and each ring
k's own first harmonic (its centre's offset from the centreline). The rings crossing a
node at different angles (each tilted ring passes it at two) measure it together. The
fit is robust (soft-L1, iteratively reweighted), done in windows of the run (bounded
size on long runs), and the nodes' ovality 2 |(a2, b2)| / c0 is bias-corrected like a
station's (:func:`.stations.station_from_section`).
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
import scipy.sparse as sparse

from omnipipe.analysis.feature_types import Ovality, Stretch, Taper, Water
from omnipipe.analysis.records import AnalysisConfig
from omnipipe.analysis.station_profiles import ring_groups
from omnipipe.analysis.stations import SectionConfig

NODE_MM = 5.0
"""Spacing (mm) of the field's nodes along the axis: random-features' ovality stretches
blend in and out over 2-5 mm and run 14 mm and more."""

SMOOTHING = 1.0
"""Weight (per mm of radius) of each field's second difference between neighbouring
nodes against the points' residuals: holds nodes few points reach, moves the rest little
(hundreds of points a node)."""

CORE_NODES = 16
"""Nodes a window reports (its core); it fits them with the points up to the rings'
largest axial reach beyond."""

MIN_RING_POINTS = 24
"""A ring takes part in a window with at least this many points inside it (its first
harmonic is fitted there)."""

IRLS_PASSES = 6

RING_POINTS = 720
"""At most this many of a ring's points (every n-th along it) enter the field: half a
degree apart, finer than any ovality's blend; full-size rings hold several thousand."""

MIN_NODE_SHARE = 0.5
"""A node measures the wall with at least this share of the span's median points within
half a node spacing of it (random-features seed 30's square rings 12 mm apart leave
nodes between them with none)."""

FLOOR = 0.005
"""The 1-sigma (a fraction) of a node's ovality that no fit sigma holds: the rings'
shapes, their centres' offsets (random-features seeds 26 and 27 under the true motion:
round nodes read 0.0-0.8 %, median 0.3 %)."""

MAX_REACH = 0.35
"""Rings whose points reach further along the axis than this times the wall's radius
(95th percentile; tilted 19 deg and more against the centreline) stay out of the field:
random-features seed 11's six rings, each over 235 mm of a 500 mm pipe, read 80-140 %
in it (seed 26's rings, tilted 9-12 deg, reach 0.2-0.23)."""


@dataclass(frozen=True)
class OvalityField:
    """The wall's ovality at nodes along the pipe (mm, fractions, degrees).

    Attributes:
        axial_mm: (G,) the nodes' axial positions (the stations' convention).
        ovality, ovality_sigma: (G,) (Dmax - Dmin) / D there (bias-corrected) and its 1-sigma.
        angle_deg, angle_sigma_deg: (G,) the major axis' direction, [0, 180), and its 1-sigma.
        points: (G,) points within half a node spacing.
    """

    axial_mm: np.ndarray
    ovality: np.ndarray
    ovality_sigma: np.ndarray
    angle_deg: np.ndarray
    angle_sigma_deg: np.ndarray
    points: np.ndarray


def ovality_field(
    groups: Sequence[np.ndarray],
    theta: np.ndarray,
    rho: np.ndarray,
    sigma: np.ndarray,
    rings: np.ndarray,
    exclude: np.ndarray,
    loss_scale_mm: float,
) -> OvalityField:
    """The field over the stations' axial span (see the module doc).

    Args:
        groups: per ring the indices of its points.
        theta, rho, sigma: (N,) each point's angle (rad), radius (mm) and axial position
            (mm) about the centreline.
        rings: indices of the rings measured (the stations').
        exclude: (N,) points that are not wall (joint gaps, openings, strays).
        loss_scale_mm: the soft-L1 scale of the robust fit.
    """
    empty = OvalityField(*(np.zeros(0) for _ in range(6)))
    if not len(rings):
        return empty
    centres = np.array([float(np.median(sigma[np.asarray(groups[k])])) for k in rings])
    idx, ring, reaches = [], [], []
    for j, k in enumerate(rings):
        on = np.asarray(groups[k])
        use = on[~exclude[on]]
        if len(use) < MIN_RING_POINTS:
            continue
        use = use[:: -(-len(use) // RING_POINTS)]  # every n-th: at most RING_POINTS a ring
        reach_j = float(np.percentile(np.abs(sigma[use] - centres[j]), 95))
        # A ring reaching far along the axis is square to a pipe the centreline runs
        # obliquely through (:mod:`.ring_tilt`): about that axis the wall is no field of s.
        if reach_j > MAX_REACH * float(np.median(rho[use])):
            continue
        idx.append(use)
        ring.append(np.full(len(use), j))
        reaches.append(reach_j)
    lo, hi = float(centres.min()), float(centres.max())
    if not idx:
        nodes = lo + NODE_MM * np.arange(int(math.floor((hi - lo) / NODE_MM)) + 1)
        nan = np.full(len(nodes), np.nan)
        return OvalityField(nodes, nan, nan, nan, nan, np.zeros(len(nodes)))
    pts = np.concatenate(idx)
    ring_of = np.concatenate(ring)
    s, th, r = sigma[pts], theta[pts], rho[pts]
    reach = max(reaches)
    nodes = lo + NODE_MM * np.arange(int(math.floor((hi - lo) / NODE_MM)) + 1)
    out = [np.zeros(len(nodes)) for _ in range(4)]
    count = np.zeros(len(nodes))
    order = np.argsort(s, kind="stable")
    s_sorted = s[order]
    for c0 in range(0, len(nodes), CORE_NODES):
        core = nodes[c0 : c0 + CORE_NODES]
        a = np.searchsorted(s_sorted, core[0] - reach - NODE_MM, side="left")
        b = np.searchsorted(s_sorted, core[-1] + reach + NODE_MM, side="right")
        sel = order[a:b]
        got = _window(s[sel], th[sel], r[sel], ring_of[sel], core, reach, loss_scale_mm)
        for q, v in zip(out, got[:4], strict=True):
            q[c0 : c0 + len(core)] = v
        count[c0 : c0 + len(core)] = got[4]
    return OvalityField(nodes, *out, count)


def _window(
    s: np.ndarray, th: np.ndarray, r: np.ndarray, ring: np.ndarray, core: np.ndarray, reach: float, loss: float
) -> tuple[np.ndarray, ...]:
    """One window's fit: (ovality, sigma, angle deg, angle sigma deg, points) at the
    ``core`` nodes (NaN where the fit cannot tell)."""
    nan = np.full(len(core), np.nan)
    n0 = int(math.floor(reach / NODE_MM)) + 1
    grid = np.concatenate([core[0] - NODE_MM * np.arange(n0, 0, -1), core, core[-1] + NODE_MM * np.arange(1, n0 + 1)])
    inside = (s >= grid[0]) & (s <= grid[-1])
    keep_rings, counts = np.unique(ring[inside], return_counts=True)
    keep_rings = keep_rings[counts >= MIN_RING_POINTS]
    inside &= np.isin(ring, keep_rings)
    s, th, r, ring = s[inside], th[inside], r[inside], np.searchsorted(keep_rings, ring[inside])
    g, k, n = len(grid), len(keep_rings), len(s)
    if n < 3 * g or k == 0:
        return nan, nan, nan, nan, np.zeros(len(core))
    u = (s - grid[0]) / NODE_MM
    i0 = np.clip(np.floor(u).astype(int), 0, g - 2)
    w1 = u - i0
    rows = np.repeat(np.arange(n), 8)
    cols = np.stack(
        [i0, i0 + 1, g + i0, g + i0 + 1, 2 * g + i0, 2 * g + i0 + 1, 3 * g + 2 * ring, 3 * g + 2 * ring + 1], axis=1
    ).ravel()
    c2, s2 = np.cos(2 * th), np.sin(2 * th)
    vals = np.stack([1 - w1, w1, (1 - w1) * c2, w1 * c2, (1 - w1) * s2, w1 * s2, np.cos(th), np.sin(th)], axis=1).ravel()
    design = sparse.csr_matrix((vals, (rows, cols)), shape=(n, 3 * g + 2 * k))
    d2 = sparse.diags([1.0, -2.0, 1.0], [0, 1, 2], shape=(g - 2, g))
    reg = sparse.block_diag([d2, d2, d2], format="csr")
    penalty = (SMOOTHING**2) * (reg.T @ reg).toarray()
    w = np.ones(n)
    x = np.zeros(3 * g + 2 * k)
    reduced = penalty
    for _ in range(IRLS_PASSES):
        aw = design.multiply(w[:, None]).tocsr()
        x, reduced = _solve((design.T @ aw).tocsr(), aw.T @ r, penalty)
        z = (r - design @ x) / loss
        w = 1.0 / np.sqrt(1.0 + z * z)
    res = r - design @ x
    spread = 1.4826 * float(np.median(np.abs(res)))
    cov = np.linalg.pinv(reduced, hermitian=True) * spread**2
    core_at = np.arange(n0, n0 + len(core))
    c0, a2, b2 = x[core_at], x[g + core_at], x[2 * g + core_at]
    var2 = 0.5 * (cov[g + core_at, g + core_at] + cov[2 * g + core_at, 2 * g + core_at])
    raw2 = a2**2 + b2**2
    amp = np.sqrt(np.maximum(raw2 - 2.0 * var2, 0.0))
    c0 = np.where(c0 > 0, c0, np.nan)
    ov, osig = 2.0 * amp / c0, 2.0 * np.sqrt(var2) / c0
    angle = np.degrees(0.5 * np.arctan2(b2, a2)) % 180.0
    asig = np.minimum(np.degrees(0.5 * np.sqrt(var2) / np.maximum(np.sqrt(raw2), 1e-9)), 180.0 / math.sqrt(12.0))
    near = np.abs(s[:, None] - core[None, :]) <= 0.5 * NODE_MM
    return ov, osig, angle, asig, near.sum(axis=0).astype(float)


def _solve(normal: sparse.csr_matrix, rhs: np.ndarray, penalty: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The window's normal equations (the field's 3G parameters, then two per ring; the
    rings' 2 x 2 blocks apart from each other) with ``penalty`` on the field's: the rings'
    parameters eliminated (Schur complement). Returns (every parameter, the field's
    reduced normal matrix)."""
    nf = penalty.shape[0]
    aff = normal[:nf, :nf].toarray() + penalty
    afr = normal[:nf, nf:].toarray()
    rr = normal[nf:, nf:]
    a, d, b = rr.diagonal()[0::2], rr.diagonal()[1::2], rr.diagonal(1)[0::2]
    det = np.where(np.abs(a * d - b * b) > 1e-12, a * d - b * b, 1e-12)
    m = np.empty_like(afr)  # afr times the rings' inverse blocks
    m[:, 0::2] = (afr[:, 0::2] * d - afr[:, 1::2] * b) / det
    m[:, 1::2] = (afr[:, 1::2] * a - afr[:, 0::2] * b) / det
    reduced = aff - m @ afr.T
    try:
        xf = np.linalg.solve(reduced, rhs[:nf] - m @ rhs[nf:])
    except np.linalg.LinAlgError:
        xf = np.linalg.pinv(reduced, hermitian=True) @ (rhs[:nf] - m @ rhs[nf:])
    t = rhs[nf:] - afr.T @ xf
    xr = np.empty_like(t)
    xr[0::2] = (d * t[0::2] - b * t[1::2]) / det
    xr[1::2] = (a * t[1::2] - b * t[0::2]) / det
    return np.concatenate([xf, xr]), reduced


def field_stretches(
    field: OvalityField, span_mm: tuple[float, float], min_pct: float, min_nodes: int
) -> list[Stretch]:
    """Stretches of the field's nodes within ``span_mm`` (the stations' first and last
    axial position) whose ovality is at least ``min_pct`` (percent) on ``min_nodes``
    neighbouring nodes: the nodes' median ovality; its sigma their spread or the nodes'
    median sigma, the larger (neighbouring nodes share points, and a short stretch's
    nodes read its blends), with :data:`FLOOR`; the major axis the nodes' mean. Extents uncertain by half a node spacing; a stretch at the span's
    first or last node is ``truncated``."""
    x = field.axial_mm
    ok = (x >= span_mm[0] - 1e-9) & (x <= span_mm[1] + 1e-9) & np.isfinite(field.ovality)
    if ok.any():  # nodes few points reach (between square rings far apart) hold the smoothing only
        ok &= field.points >= MIN_NODE_SHARE * float(np.median(field.points[ok]))
    mask = ok & (np.nan_to_num(field.ovality) * 100.0 >= min_pct)
    idx = np.flatnonzero(ok)
    out: list[Stretch] = []
    if not len(idx):
        return out
    first, last = int(idx[0]), int(idx[-1])
    i = 0
    while i < len(x):
        if not mask[i]:
            i += 1
            continue
        j = i
        while j + 1 < len(x) and mask[j + 1]:
            j += 1
        if j - i + 1 >= min_nodes:
            sel = slice(i, j + 1)
            ov = field.ovality[sel]
            z = np.exp(2j * np.radians(field.angle_deg[sel]))
            out.append(
                Ovality(
                    axial_from_mm=float(x[i]),
                    axial_from_sigma_mm=0.5 * NODE_MM,
                    axial_to_mm=float(x[j]),
                    axial_to_sigma_mm=0.5 * NODE_MM,
                    percent=100.0 * float(np.median(ov)),
                    percent_sigma=100.0 * math.hypot(
                        max(float(np.std(ov)), float(np.median(field.ovality_sigma[sel]))), FLOOR
                    ),
                    angle_deg=(0.5 * math.degrees(float(np.angle(np.mean(z))))) % 180.0,
                    angle_sigma_deg=float(np.median(field.angle_sigma_deg[sel])),
                    truncated=i == first or j == last,
                    along_rings=True,
                )
            )
        i = j + 1
    return out


def stage_field_ovality(
    features: Sequence[Stretch],
    measured: tuple[np.ndarray, np.ndarray, np.ndarray],
    points: tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray],
    config: AnalysisConfig,
    sec_config: SectionConfig,
) -> list[Stretch]:
    """:func:`with_field_ovality` of the field (robust at ``config.loss_scale_mm``) of the
    ``measured`` rings (each point's ring index, (K,) bool the rings measured, the stations'
    axial positions) from the ``points`` (theta, rho, sigma, not-wall mask): the analysis
    stage's features."""
    frame, ok, axial = measured
    theta, rho, sigma, not_wall = points
    groups = ring_groups(frame, len(ok))
    field = ovality_field(groups, theta, rho, sigma, np.flatnonzero(ok), not_wall, config.loss_scale_mm)
    return with_field_ovality(features, field, axial, sec_config)


def with_field_ovality(
    features: Sequence[Stretch], field: OvalityField, stations_axial: np.ndarray, config: SectionConfig
) -> list[Stretch]:
    """``features`` with the ovality stretches of ``field`` (:func:`field_stretches` over
    the stations' span, ``config.ovality_feature_pct`` on ``config.min_stations`` nodes)
    that no ovality, taper or water stretch overlaps, in axial order. The stations' stretches
    stand: where a ring's own section shows the ovality its fit measures it (the field
    holds no ring's tilt against the centreline, :mod:`.ring_tilt`)."""
    axial = np.asarray(stations_axial, float)
    out = list(features)
    if not len(axial):
        return out
    # Nor on a taper or under water: a cone's rings ride its slope, and below a water line
    # the wall is missing from every ring; the field's harmonics trade against both
    # (random-features seed 25: 4.6 % on a round reducer's ramp under the estimated motion).
    have = [f for f in features if isinstance(f, (Ovality, Taper, Water))]
    span = (float(axial.min()), float(axial.max()))
    for f in field_stretches(field, span, config.ovality_feature_pct, config.min_stations):
        if not any(min(f.axial_to_mm, h.axial_to_mm) >= max(f.axial_from_mm, h.axial_from_mm) for h in have):
            out.append(f)
    return sorted(out, key=lambda f: f.axial_from_mm)
