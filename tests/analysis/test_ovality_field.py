"""The ovality field (issue 30, random-features seed 26): an ovality stretch shorter than
the tilted rings' axial footprint, read from every ring's points at their own axial
positions, and a round pipe read round. Seeded synthetic rings against their truth."""

from __future__ import annotations

import math

import numpy as np

from omnipipe.analysis.ovality_field import field_stretches, ovality_field

RADIUS = 105.0


def _ovality_at(s: np.ndarray, start: float, end: float, percent: float, blend: float) -> np.ndarray:
    """(N,) the true ovality (fraction) at axial ``s``: ``percent`` between ``start`` and
    ``end``, blended linearly over ``blend`` mm either side."""
    up = np.clip((s - (start - blend)) / blend, 0.0, 1.0)
    down = np.clip(((end + blend) - s) / blend, 0.0, 1.0)
    return 0.01 * percent * np.minimum(up, down)


def _rings(rng: np.random.Generator, percent: float) -> tuple[list[np.ndarray], np.ndarray, np.ndarray, np.ndarray]:
    """Rings 5 mm apart tilted 11 deg against the axis (each over +-20 mm of a 210 mm
    pipe), their centres up to 0.3 mm off the axis, 0.05 mm of noise; the wall oval by
    ``percent`` over -72..-56 mm (blends 3.8 mm), major axis at 4 deg."""
    tilt, angle = math.radians(11.0), math.radians(4.0)
    groups, theta, rho, sigma = [], [], [], []
    n = 0
    for k, centre in enumerate(np.arange(-120.0, 0.0, 5.0)):
        th = np.linspace(0.0, 2.0 * np.pi, 720, endpoint=False)
        psi = 0.7 * k
        s = centre + RADIUS * math.tan(tilt) * np.cos(th - psi)
        ov = _ovality_at(s, -72.0, -56.0, percent, 3.8)
        off = rng.normal(0.0, 0.3, 2)
        r = RADIUS * (1.0 + 0.5 * ov * np.cos(2.0 * (th - angle))) + off[0] * np.cos(th) + off[1] * np.sin(th)
        r = r + rng.normal(0.0, 0.05, len(th))
        groups.append(np.arange(n, n + len(th)))
        n += len(th)
        theta.append(th)
        rho.append(r)
        sigma.append(s)
    return groups, np.concatenate(theta), np.concatenate(rho), np.concatenate(sigma)


def test_a_stretch_shorter_than_the_rings_footprint_is_found() -> None:
    """A 4.3 % stretch 16 mm long under rings 40 mm long along the axis: found (the
    stations' own fits read a fraction of it), its percent within 3 sigma of the truth
    and within 1 point, its ends within 5 mm, its axis within 5 deg; over 3 seeds."""
    for seed in range(3):
        groups, theta, rho, sigma = _rings(np.random.default_rng(seed), 4.3)
        rings = np.arange(len(groups))
        field = ovality_field(groups, theta, rho, sigma, rings, np.zeros(len(rho), bool), 0.5)
        centres = np.array([float(np.median(sigma[g])) for g in groups])
        got = field_stretches(field, (float(centres.min()), float(centres.max())), 2.0, 2)
        assert len(got) == 1, (seed, got)
        f = got[0]
        assert abs(f.percent - 4.3) <= max(3.0 * f.percent_sigma, 0.0) and abs(f.percent - 4.3) < 1.0, (seed, f)
        assert abs(f.axial_from_mm - -72.0) < 5.0 and abs(f.axial_to_mm - -56.0) < 5.0, (seed, f)
        assert abs((f.angle_deg - 4.0 + 90.0) % 180.0 - 90.0) < 5.0, (seed, f)


def test_round_pipe_has_no_stretch() -> None:
    """The same rings in a round pipe: every node under 0.5 %, no stretch; over 3 seeds."""
    for seed in range(3):
        groups, theta, rho, sigma = _rings(np.random.default_rng(10 + seed), 0.0)
        field = ovality_field(groups, theta, rho, sigma, np.arange(len(groups)), np.zeros(len(rho), bool), 0.5)
        centres = np.array([float(np.median(sigma[g])) for g in groups])
        inside = (field.axial_mm >= centres.min()) & (field.axial_mm <= centres.max())
        assert np.nanmax(field.ovality[inside]) < 0.005, (seed, np.round(100 * field.ovality, 2))
        assert field_stretches(field, (float(centres.min()), float(centres.max())), 2.0, 2) == []


def test_stretches_read_along_the_rings_stay_out_of_tapers_water_and_station_stretches() -> None:
    """A field stretch is added only where the stations report no ovality, taper or water
    stretch over it; it says it was read along the rings."""
    from omnipipe.analysis.feature_types import Ovality, Taper, Water
    from omnipipe.analysis.ovality_field import OvalityField, with_field_ovality
    from omnipipe.analysis.stations import SectionConfig

    nodes = np.arange(-100.0, 1.0, 5.0)
    ov = np.where((nodes >= -70) & (nodes <= -55), 0.04, 0.002)
    ones = np.ones(len(nodes))
    field = OvalityField(nodes, ov, 0.001 * ones, 4.0 * ones, 1.0 * ones, 500.0 * ones)
    axial = np.arange(-100.0, 1.0, 8.0)
    got = with_field_ovality([], field, axial, SectionConfig())
    assert len(got) == 1 and got[0].along_rings and abs(got[0].percent - 4.0) < 1e-6, got
    taper = Taper(axial_from_mm=-80.0, axial_to_mm=-60.0, diameter_from_mm=200.0, diameter_to_mm=190.0)
    water = Water(axial_from_mm=-65.0, axial_to_mm=-20.0, depth_mm=20.0)
    station = Ovality(axial_from_mm=-58.0, axial_to_mm=-40.0, percent=3.0, angle_deg=4.0)
    for other in (taper, water, station):
        assert with_field_ovality([other], field, axial, SectionConfig()) == [other]
