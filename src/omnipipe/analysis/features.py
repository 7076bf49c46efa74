"""Joints and laterals: found in the rings, measured, and taken out of the wall.

A joint's gap and a lateral's opening are parts of a sound pipe: their points are not
wall (they would read as dents, and pull the rings' wall profiles). Per ring, a robust
Fourier profile (order 2: the ring's offset and ovality) is fitted; a ring whose mean
radius stands out from its neighbours' running median (the ring lies in a joint's gap)
takes the neighbours' mean radius instead. Points further out than the threshold
(``max(min_depth_mm, noise_factor x noise)``) are linked into clusters across rings; a
cluster covering most of the observed circumference is a joint, a narrower one reaching
far out (the branch wall behind the hole) a lateral. Smaller clusters are left to the
defect finder.

* joint: the gap's edges are midway between the last sample deeper than half the gap's
  depth and the first shallower one (1-sigma: that spacing / sqrt(12)); the offset is
  the median ring centre downstream minus upstream (rings within ``offset_window_mm``),
  perpendicular to the axis, its sigma from the centres' scatter.
* lateral: each ring crossing the hole gives a chord (centre, half-width) at its axial
  position; the hole's outline, an ellipse in (axial, arc), is fitted through the
  half-widths (h^2 quadratic in the axial position); the opening's diameter is the chord
  2 R sin(b / R) of its circumferential semi-axis b. Sigmas by jackknife over the rings.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from scipy.sparse import coo_matrix
from scipy.sparse.csgraph import connected_components
from scipy.spatial import cKDTree

from omnipipe.analysis.centreline import Centreline
from omnipipe.analysis.defects import fit_wall_profile, fourier_design
from omnipipe.analysis.point_feature import PointFeature as Feature


@dataclass(frozen=True)
class FeatureConfig:
    """Feature finder settings.

    Attributes:
        min_depth_mm: smallest outward step counted as a gap or an opening.
        noise_factor: the threshold is at least this many noise sigmas.
        joint_coverage: a cluster covering this fraction of the observed circumference
            at its position is a joint.
        lateral_reach_rel: a narrower cluster reaching this fraction of the diameter
            beyond the wall is a lateral (the branch wall seen through the hole).
        min_points: points a cluster needs.
        margin_mm: wall points this close to a gap or an opening are excluded too
            (the edges' ramps and the ring's blur).
        window_mm: running-median window of the rings' mean radius; offset window.
    """

    min_depth_mm: float = 1.5
    noise_factor: float = 6.0
    joint_coverage: float = 0.6
    lateral_reach_rel: float = 0.08
    min_points: int = 8
    margin_mm: float = 3.0
    window_mm: float = 60.0


@dataclass(frozen=True)
class FeatureSearch:
    """What :func:`find_features` found.

    Attributes:
        features: joints and laterals, ordered along the pipe.
        not_wall: (N,) True for the points inside a gap or an opening (and their margin).
        threshold_mm: outward deviation beyond which a point counted.
    """

    features: list[Feature]
    not_wall: np.ndarray
    threshold_mm: float


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
    dev, ring_sigma, ring_centre, raised = _deviations(config, line, sigma, rho, theta, frame, rings)
    noise = 1.4826 * float(np.median(np.abs(dev - np.median(dev))))
    thr = max(config.min_depth_mm, config.noise_factor * noise)
    out = dev > thr
    not_wall = np.zeros(len(sigma), bool)
    idx = np.flatnonzero(out)
    if len(idx) < config.min_points:
        return FeatureSearch([], not_wall, thr)
    gaps = np.diff(np.sort(ring_sigma))
    spacing = float(np.percentile(gaps, 90)) if len(gaps) else 5.0
    link = max(1.5 * spacing, 3.0)
    feats: list[Feature] = []
    # Joints: rings (or runs of neighbouring rings) mostly beyond the threshold.
    ring_of = np.searchsorted(rings, frame)
    gap_ring = np.zeros(len(rings), bool)
    for i in range(len(rings)):
        on = ring_of == i
        seen = np.unique((np.degrees(theta[on]) % 360 // 10).astype(int))
        have = np.unique((np.degrees(theta[on & out]) % 360 // 10).astype(int))
        gap_ring[i] = raised[i] or len(have) >= config.joint_coverage * max(len(seen), 1)
    order = np.argsort(ring_sigma)
    runs: list[list[int]] = []
    prev_gap = False
    for i in order:
        if gap_ring[i] and prev_gap:
            runs[-1].append(int(i))
        elif gap_ring[i]:
            runs.append([int(i)])
        prev_gap = bool(gap_ring[i])
    for run in runs:
        deep = dev > (0.5 * thr if raised[run].any() else thr)
        members = np.flatnonzero(np.isin(ring_of, run) & deep)
        if len(members) < config.min_points:
            continue
        f, mask = _joint(
            config, line, sigma, dev, members, ring_sigma, ring_centre, rings, frame, noise
        )
        feats.append(f)
        not_wall |= mask
    # Laterals: the rest, linked across rings, narrow and reaching far out.
    idx = np.flatnonzero(out & ~not_wall)
    if len(idx) >= config.min_points:
        xyz = np.stack([sigma[idx], radius * np.cos(theta[idx]), radius * np.sin(theta[idx])], axis=1)
        pairs = cKDTree(xyz).query_pairs(link, output_type="ndarray")
        m = len(idx)
        graph = coo_matrix((np.ones(len(pairs)), (pairs[:, 0], pairs[:, 1])), shape=(m, m))
        _, label = connected_components(graph, directed=False)
        for lab in np.unique(label):
            members = idx[label == lab]
            if len(members) < config.min_points:
                continue
            if float(np.max(dev[members])) < config.lateral_reach_rel * 2 * radius:
                continue
            f, mask = _lateral(config, sigma, theta, frame, members, radius, spacing)
            feats.append(f)
            not_wall |= mask
    feats.sort(key=lambda f: f.axial_mm)
    return FeatureSearch(feats, not_wall, thr)


def _deviations(
    config: FeatureConfig,
    line: Centreline,
    sigma: np.ndarray,
    rho: np.ndarray,
    theta: np.ndarray,
    frame: np.ndarray,
    rings: np.ndarray,
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """(N,) each point's outward deviation from its ring's wall profile (a ring lying in
    a gap takes its neighbours' mean radius), (R,) the rings' axial positions, (R, 3)
    their fitted centres in the world frame and (R,) True for rings raised above their
    neighbours (lying in a gap)."""
    coefs, ring_sigma, ring_centre = [], [], []
    for k in rings:
        on = frame == k
        order = 2 if on.sum() >= 20 else 0
        c = fit_wall_profile(theta[on], rho[on], order, 0.5)
        coefs.append(np.pad(c, (0, 5 - len(c))))
        ring_sigma.append(float(np.median(sigma[on])))
        ring_centre.append(line.centre[k] + c[1] * line.normal[k] + c[2] * line.binormal[k] if order else line.centre[k])
    coef = np.array(coefs)
    rs = np.array(ring_sigma)
    c0 = coef[:, 0].copy()
    for i in range(len(rings)):
        nb = np.abs(rs - rs[i]) <= config.window_mm
        c0[i] = float(np.median(coef[nb, 0]))
    dev = np.zeros(len(sigma))
    raised = np.zeros(len(rings), bool)
    noise0 = 1.4826 * float(np.median(np.abs(coef[:, 0] - c0))) + 1e-9
    for i, k in enumerate(rings):
        on = frame == k
        c = coef[i].copy()
        if abs(c[0] - c0[i]) > max(config.min_depth_mm, config.noise_factor * noise0):
            raised[i] = c[0] > c0[i]
            c[0] = c0[i]
        dev[on] = rho[on] - fourier_design(theta[on], 2) @ c
    return dev, rs, np.array(ring_centre), raised


def _edge(inside: np.ndarray, outside: np.ndarray, lower: bool) -> tuple[float, float]:
    """A gap edge midway between the outermost inside sample and the nearest outside
    one beyond it, and its 1-sigma (their spacing / sqrt(12))."""
    if lower:
        a = float(inside.min())
        o = outside[outside < a]
        b = float(o.max()) if len(o) else a
    else:
        a = float(inside.max())
        o = outside[outside > a]
        b = float(o.min()) if len(o) else a
    return 0.5 * (a + b), max(abs(a - b), 0.1) / math.sqrt(12.0)


def _joint(
    config: FeatureConfig,
    line: Centreline,
    sigma: np.ndarray,
    dev: np.ndarray,
    members: np.ndarray,
    ring_sigma: np.ndarray,
    ring_centre: np.ndarray,
    rings: np.ndarray,
    frame: np.ndarray,
    noise: float,
) -> tuple[Feature, np.ndarray]:
    """A joint from its cluster: gap edges, depth and the sections' offset."""
    depth = float(np.percentile(dev[members], 90))
    # Edges between ring positions (a ring's points spread along the axis by its tilt).
    ring_of = np.searchsorted(rings, frame)
    frac = np.bincount(ring_of[members], minlength=len(rings)) / np.maximum(
        np.bincount(ring_of, minlength=len(rings)), 1
    )
    inside = ring_sigma[frac >= 0.5]
    if len(inside) == 0:
        inside = ring_sigma[[int(np.argmax(frac))]]
    lo, slo = _edge(inside, ring_sigma[frac < 0.5], True)
    hi, shi = _edge(inside, ring_sigma[frac < 0.5], False)
    axial, gap = 0.5 * (lo + hi), hi - lo
    k = int(np.argmin(np.abs(line.arc_mm - axial)))
    t, n, b = line.tangent[k], line.normal[k], line.binormal[k]
    clear = 0.5 * gap + config.margin_mm
    up = (ring_sigma < axial - clear) & (ring_sigma > axial - config.window_mm)
    down = (ring_sigma > axial + clear) & (ring_sigma < axial + config.window_mm)
    off = off_sig = ang = ang_sig = None
    if up.any() and down.any():
        pu, pd = ring_centre[up], ring_centre[down]
        mu, md = pu.mean(axis=0), pd.mean(axis=0)
        if up.sum() + down.sum() >= 4:
            # The sections' common direction (the fitted centreline bends through an offset).
            _, _, vt = np.linalg.svd(np.concatenate([pu - mu, pd - md]))
            t = vt[0] * np.sign(vt[0] @ t)
        v = md - mu
        v -= (v @ t) * t
        ru = (pu - mu) - np.outer((pu - mu) @ t, t)
        rd = (pd - md) - np.outer((pd - md) @ t, t)
        res = np.concatenate([np.linalg.norm(ru, axis=1), np.linalg.norm(rd, axis=1)])
        spread = float(np.sqrt(np.mean(res**2))) if len(res) > 2 else 0.1
        # Plus half the wall noise: ring centres share errors the scatter of a few rings
        # cannot show (water-cut rings, ovality, the ring's blur).
        off_sig = math.hypot(1.25 * spread * math.sqrt(1.0 / up.sum() + 1.0 / down.sum()), 0.5 * noise)
        off = float(np.linalg.norm(v))
        n = n - (n @ t) * t
        b = np.cross(t, n / np.linalg.norm(n))
        n = n / np.linalg.norm(n)
        ang = math.degrees(math.atan2(v @ b, v @ n)) % 360.0
        ang_sig = min(math.degrees(off_sig / max(off, 1e-9)), 180.0)
    f = Feature(
        kind="joint",
        axial_mm=axial,
        axial_sigma_mm=0.5 * math.hypot(slo, shi),
        gap_mm=gap,
        gap_sigma_mm=math.hypot(slo, shi),
        depth_mm=depth,
        offset_mm=off,
        offset_sigma_mm=off_sig,
        offset_angle_deg=ang,
        offset_angle_sigma_deg=ang_sig,
        points=len(members),
    )
    in_gap = np.abs(ring_sigma - axial) <= clear
    # The gap's rings, and the deep points of rings crossing its edges.
    edge = (np.abs(sigma - axial) <= clear) & (dev > 0.5 * float(np.min(dev[members])))
    return f, edge | in_gap[ring_of]


def _chords(
    sigma: np.ndarray, u: np.ndarray, frame: np.ndarray, members: np.ndarray, sample: float
) -> np.ndarray:
    """(M, 3) per ring crossing the hole: axial position, chord centre and half-width
    (arc mm; half a sample added: the edges lie between samples)."""
    rows = []
    for k in np.unique(frame[members]):
        m = members[frame[members] == k]
        if len(m) < 2:
            continue
        rows.append((float(np.median(sigma[m])), 0.5 * (u[m].max() + u[m].min()),
                     0.5 * (u[m].max() - u[m].min()) + 0.5 * sample))
    return np.array(rows).reshape(-1, 3)


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
) -> tuple[Feature, np.ndarray]:
    """A lateral's opening from its cluster: centre, angle and diameter (jackknife sigmas)."""
    th0 = math.atan2(float(np.mean(np.sin(theta[members]))), float(np.mean(np.cos(theta[members]))))
    u = ((theta - th0 + np.pi) % (2 * np.pi) - np.pi) * radius
    steps = []
    for k in np.unique(frame[members]):
        d_u = np.diff(np.sort(u[frame == k]))
        steps.append(float(np.median(d_u[d_u > 0])) if (d_u > 0).any() else 1.0)
    sample = float(np.median(steps))
    ch = _chords(sigma, u, frame, members, sample)
    zc, uc, b, a = _ellipse(ch)
    est = [(zc, uc, b)]
    if len(ch) >= 4:
        est += [_ellipse(np.delete(ch, i, axis=0))[:3] for i in range(len(ch))]
    arr = np.array(est)
    n = len(arr) - 1
    jk = np.sqrt((n - 1) / n * np.sum((arr[1:] - arr[1:].mean(axis=0)) ** 2, axis=0)) if n >= 3 else np.zeros(3)
    s_z = math.hypot(float(jk[0]), spacing / math.sqrt(12.0) if len(ch) < 3 else 0.0)
    s_u = math.hypot(float(jk[1]), sample / math.sqrt(12.0))
    s_b = math.hypot(float(jk[2]), sample / math.sqrt(12.0))
    diameter = 2.0 * radius * math.sin(min(b / radius, 0.5 * math.pi))
    f = Feature(
        kind="lateral",
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
