"""A lateral's outline measured from its own rings' samples (arcs made where read, the
outline's mask tested a block at a time) gives the whole-run code's lateral, mask, zone
and verdict, on seeded walls with tees seen as deep samples and as lost returns."""

from __future__ import annotations

import math

import numpy as np
import pytest

from omnipipe.analysis import features, sample_arcs
from omnipipe.analysis.centreline import Centreline
from omnipipe.analysis.feature_types import Lateral
from omnipipe.analysis.features import FeatureConfig, find_features
from omnipipe.analysis.openings import ring_axial

R = 75.0


def _whole_chords(sigma, u, frame, members, sample, radius):
    """The whole-run chords (the reference of :func:`features._chords`)."""
    rows = []
    for k in np.unique(frame[members]):
        m = members[frame[members] == k]
        if len(m) < 2:
            continue
        c = 0.5 * (u[m].max() + u[m].min())
        on = np.flatnonzero(frame == k)
        wall = on[~np.isin(on, m)]
        z = ring_axial(sigma[wall], u[wall] / radius, c / radius) if len(wall) >= 8 else float(np.median(sigma[m]))
        rows.append((z, c, 0.5 * (u[m].max() - u[m].min()) + 0.5 * sample, float(k)))
    return np.array(rows).reshape(-1, 4)


def _whole_lateral(config, r, members, radius, spacing, thr, gaps=(), stops=(), planes=None):
    """The whole-run lateral: every sample's arc made at once, the outline's mask over
    the whole run (the reference of :func:`features._lateral`)."""
    sigma, theta, frame = r.sigma, r.theta, r.frame
    th = np.concatenate([theta[members], [g.centre for g in gaps]])
    th0 = math.atan2(float(np.mean(np.sin(th))), float(np.mean(np.cos(th))))
    u = ((theta - th0 + np.pi) % (2 * np.pi) - np.pi) * radius
    rings = np.unique(np.concatenate([frame[members], [g.ring for g in gaps]]).astype(int))
    steps = []
    for k in rings:
        d_u = np.diff(np.sort(u[frame == k]))
        steps.append(float(np.median(d_u[d_u > 0])) if (d_u > 0).any() else 1.0)
    sample = float(np.median(steps))
    ch = features._merged_chords(_whole_chords(sigma, u, frame, members, sample, radius), features._gap_chords(gaps, th0, radius))
    ch = features._main_block(ch, max(3.0 * spacing, 10.0))
    zc, uc, b, a = features._ellipse(ch[:, :3])
    est = [(zc, uc, b)]
    if len(ch) >= 4:
        est += [features._ellipse(np.delete(ch[:, :3], i, axis=0))[:3] for i in range(len(ch))]
    arr = np.array(est)
    n = len(arr) - 1
    jk = np.sqrt((n - 1) / n * np.sum((arr[1:] - arr[1:].mean(axis=0)) ** 2, axis=0)) if n >= 3 else np.zeros(3)
    s_z = math.hypot(float(jk[0]), spacing / math.sqrt(12.0))
    s_u = math.hypot(float(jk[1]), sample / math.sqrt(12.0))
    s_b = math.hypot(float(jk[2]), sample)
    planes = features._ring_planes(r, thr) if planes is None else planes
    s_rep = s_z
    ext = features._extent(
        r, u - uc, ch, (float(th0 + uc / radius), radius, uc), float(np.max(ch[:, 2])) + sample, thr, stops, planes
    )
    reach = (zc - a, zc + a)
    if ext is not None and all(ext.closed):
        zc, a = 0.5 * (ext.lo_mm + ext.hi_mm), 0.5 * (ext.hi_mm - ext.lo_mm)
        s_z = 0.5 * math.hypot(ext.lo_sigma_mm, ext.hi_sigma_mm)
        s_rep = math.hypot(s_z, 0.5 * math.sqrt(2.0 / 12.0) * r.axial_blur_mm)
        reach = (zc - a, zc + a)
    elif ext is not None:
        reach = (min(zc - a, ext.lo_mm), max(zc + a, ext.hi_mm))
    diameter = 2.0 * radius * math.sin(min(b / radius, 0.5 * math.pi))
    round_hole = len(members) > 0 or not features._shorter_than_wide(ext, diameter)
    f = Lateral(
        axial_mm=zc,
        axial_sigma_mm=math.hypot(s_rep, features._footprint_sigma(planes, ch, ext, float(th0 + uc / radius))),
        angle_deg=math.degrees(th0 + uc / radius) % 360.0,
        angle_sigma_deg=math.degrees(s_u / radius), diameter_mm=diameter,
        diameter_sigma_mm=2.0 * s_b * abs(math.cos(min(b / radius, 0.5 * math.pi))), points=len(members),
    )
    m = config.margin_mm
    zr, ar = 0.5 * (reach[0] + reach[1]), 0.5 * (reach[1] - reach[0])
    inside = ((sigma - zc) / (a + m)) ** 2 + ((u - uc) / (b + m)) ** 2 <= 1.0
    inside |= ((sigma - zr) / (ar + m)) ** 2 + ((u - uc) / (b + m)) ** 2 <= 1.0
    inside[members] = True
    along, around = ar + m + 3.0 * math.hypot(s_z, s_b), b + m + 3.0 * math.hypot(s_u, s_b)
    zone = features.FeatureZone(
        zr - along, zr + along, f"the lateral at {zc:.1f} mm", arc_mm=(math.radians(f.angle_deg) * radius), half_arc_mm=around
    )
    return f, inside, zone, round_hole


def _wall(seed: int, hole_mm: float, lost: float, tilt_deg: float):
    """Rings 5 mm apart (jittered) over -150..150 mm of a 150 mm pipe, 540 samples each,
    noise 0.3 mm, tilted by ``tilt_deg`` (their samples spread along the axis); a round
    hole of ``hole_mm`` at 0 mm, 236 deg: its samples 20-80 mm out (the branch wall),
    none in the middle ``lost`` of its semi-axes (the light lost in the branch)."""
    rng = np.random.default_rng(seed)
    centres = np.arange(-150.0, 151.0, 5.0) + rng.uniform(-0.5, 0.5, 61)
    theta = np.linspace(-np.pi, np.pi, 540, endpoint=False)
    u = ((theta - math.radians(236.0) + np.pi) % (2 * np.pi) - np.pi) * R
    sig, rho, th, frame = [], [], [], []
    for k, c in enumerate(centres):
        s = c + R * math.tan(math.radians(tilt_deg)) * np.cos(theta - 0.7) + rng.normal(0.0, 0.1, theta.size)
        q = (u / (0.5 * hole_mm)) ** 2 + (s / (0.5 * hole_mm)) ** 2
        r = R + rng.normal(0.0, 0.3, theta.size)
        r[q < 1.0] += rng.uniform(20.0, 80.0, int((q < 1.0).sum()))
        keep = q >= lost**2
        sig.append(s[keep])
        rho.append(r[keep])
        th.append(theta[keep])
        frame.append(np.full(int(keep.sum()), k))
    return Centreline.straight(centres, R), *(np.concatenate(a) for a in (sig, rho, th, frame))


@pytest.mark.parametrize(
    ("seed", "hole_mm", "lost", "tilt_deg", "shuffled"),
    [(1, 60.0, 0.0, 0.0, False), (2, 50.0, 0.6, 3.0, False), (3, 45.0, 0.95, 0.0, False), (4, 60.0, 0.5, 2.0, True)],
)
def test_lateral_from_its_rings_equals_the_whole_run(monkeypatch, seed, hole_mm, lost, tilt_deg, shuffled) -> None:
    line, sigma, rho, theta, frame = _wall(seed, hole_mm, lost, tilt_deg)
    if shuffled:  # rings not in order: every ring's samples gathered by the stable sort
        order = np.random.default_rng(seed).permutation(len(frame))
        sigma, rho, theta, frame = sigma[order], rho[order], theta[order], frame[order]
    calls = []
    windowed = features._lateral

    def both(*args, **kw):
        got = windowed(*args, **kw)
        calls.append((got, _whole_lateral(*args, **kw)))
        return got

    monkeypatch.setattr(features, "_lateral", both)
    monkeypatch.setattr(sample_arcs, "BLOCK", 1000)  # blocks straddle the rings
    found = find_features(FeatureConfig(), line, sigma, rho, theta, frame, R)
    assert calls
    for (f, inside, zone, round_hole), (f0, inside0, zone0, round0) in calls:
        assert f == f0 and zone == zone0 and round_hole == round0
        assert inside.dtype == bool and np.array_equal(inside, inside0)
    # and the hole: one lateral at 0 mm, 236 deg, about its diameter wide
    lats = [f for f in found.features if isinstance(f, Lateral)]
    assert len(lats) == 1, found.features
    assert abs(lats[0].axial_mm) <= 6.0 and abs((lats[0].angle_deg - 236.0 + 180) % 360 - 180) <= 4.0
    assert abs(lats[0].diameter_mm - hole_mm) <= 8.0


def test_sample_arcs_equal_the_whole_run_expression() -> None:
    rng = np.random.default_rng(7)
    theta = rng.uniform(-4.0, 4.0, 5000)
    whole = ((theta - 1.3 + np.pi) % (2 * np.pi) - np.pi) * R
    arcs = sample_arcs.SampleArcs(theta, 1.3, R)
    idx = np.sort(rng.choice(5000, 700, replace=False))
    assert np.array_equal(arcs[idx], whole[idx]) and np.array_equal(arcs[100:900], whole[100:900])
    assert np.array_equal(arcs.minus(2.5)[theta > 0], (whole - 2.5)[theta > 0])
    with pytest.raises(ValueError):
        arcs.minus(1.0).minus(1.0)
