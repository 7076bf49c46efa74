"""Cross-section measurements of real pipes (issue 30) against the simulator's true
wall: out-of-round, reducing, partly flooded and bending pipes, rings every few mm."""

from __future__ import annotations

import math

import numpy as np
import pytest

from omnipipe.analysis import AnalysisConfig, AnalysisInputs, report_fields, run
from omnipipe.analysis.feature_types import Feature
from omnipipe.analysis.stations import (
    REACH_MODEL_REL,
    Section,
    SectionConfig,
    Station,
    ring_cut,
    water_depth,
    with_water,
)
from omnipipe.analysis.wall_profile import fit_wall_profile, fourier_design
from omnipipe.geometry import make_transform
from omnipipe.sim.features import Ovality, PipeFeatures, Taper, Water
from omnipipe.sim.scene import Centreline, Defect, Pipe


def _rings(
    pipe: Pipe, first: float, spacing: float, n: int, seed: int, noise: float = 0.1, samples: int = 360
) -> AnalysisInputs:
    """Rings of the true wall every ``spacing`` mm from ``first``, rig z along the
    centreline; wall under the standing water returns no laser."""
    rng = np.random.default_rng(seed)
    sig = first + spacing * np.arange(n) + rng.uniform(-0.5, 0.5, n)
    theta = np.linspace(-np.pi, np.pi, samples, endpoint=False)
    centre, normal, binormal, tangent = pipe.frame_at(sig)
    level = pipe.water_level()
    pts, frame, poses = [], [], []
    for k in range(n):
        r = pipe.wall_radius(np.full_like(theta, sig[k]), theta) + rng.normal(0, noise, theta.size)
        p = centre[k] + (r * np.cos(theta))[:, None] * normal[k] + (r * np.sin(theta))[:, None] * binormal[k]
        keep = rng.random(theta.size) > 0.05
        if level is not None:
            keep &= p @ pipe.up() > level
        pts.append(p[keep])
        frame.append(np.full(int(keep.sum()), k))
        rot = np.stack([normal[k], binormal[k], tangent[k]], axis=1)
        poses.append(make_transform(rot, centre[k] + 82 * tangent[k]))
    return AnalysisInputs(np.concatenate(pts), np.concatenate(frame), np.array(poses))


def _true_mean_diameter(pipe: Pipe, sigma: np.ndarray) -> np.ndarray:
    th = np.linspace(0, 2 * np.pi, 720, endpoint=False)
    return np.array([2 * np.mean(pipe.wall_radius(np.full_like(th, s), th)) for s in sigma])


def _kinds(features: tuple[Feature, ...], kind: str) -> list[Feature]:
    return [f for f in features if f.kind == kind]


@pytest.mark.slow
def test_oval_pipe_mean_diameter_ovality_and_a_bulge_on_it() -> None:
    bulge = Defect("bulge", 2.0, 30.0, 60.0, axial_start_mm=170.0, angle_deg=100.0)
    pipe = Pipe(inner_diameter_mm=250.0, defects=[bulge], ovality=0.06, ovality_angle_deg=30.0)
    res = run(AnalysisConfig(), _rings(pipe, 100.0, 5.0, 40, seed=3))
    # The mean diameter (Dmax + Dmin) / 2 = 250, not a cylinder's compromise.
    assert abs(res.inner_diameter_mm - 250.0) <= 3 * res.inner_diameter_sigma_mm
    assert abs(res.inner_diameter_min_mm - 242.5) < 0.5 and abs(res.inner_diameter_max_mm - 257.5) < 0.5
    away = [s for s in res.stations if not 160.0 <= s.axial_mm <= 240.0]
    assert max(abs(100 * s.ovality - 6.0) for s in away) <= 0.3
    assert max(abs((s.ovality_angle_deg - 30.0 + 90) % 180 - 90) for s in away) < 1.0
    assert len(res.defects) == 1 and res.defects[0].kind == "bulge"
    d = res.defects[0]
    assert abs(d.height_mm - 2.0) <= max(3 * (d.height_sigma_mm or 0.0), 0.3)
    assert abs(d.axial_start_mm + 0.5 * d.length_mm - 200.0) < 5.0
    oval = _kinds(res.features, "ovality")
    assert len(oval) == 1 and abs(oval[0].percent - 6.0) <= 0.3
    assert not _kinds(res.features, "taper") and not _kinds(res.features, "bend")
    assert not _kinds(res.features, "water") and res.water_depth_mm is None


@pytest.mark.slow
def test_reducer_is_a_taper_not_a_dent() -> None:
    pipe = Pipe(inner_diameter_mm=250.0, features=PipeFeatures(tapers=(Taper(220.0, 370.0, 180.0),)))
    res = run(AnalysisConfig(), _rings(pipe, 150.0, 7.5, 40, seed=4))
    assert res.defects == []
    truth = _true_mean_diameter(pipe, res.stations_axial_mm)
    assert abs(res.inner_diameter_mm - np.median(truth)) <= 3 * res.inner_diameter_sigma_mm
    assert np.max(np.abs(res.stations_diameter_mm - truth)) < 0.5
    (taper,) = _kinds(res.features, "taper")
    assert abs(taper.axial_from_mm - 220.0) < 8.0 and abs(taper.axial_to_mm - 370.0) < 8.0
    assert abs(taper.diameter_from_mm - 250.0) < 0.5
    assert abs(taper.diameter_to_mm - 180.0) < 0.5
    assert res.inner_diameter_min_mm < 181.0 and res.inner_diameter_max_mm > 249.0


@pytest.mark.slow
def test_partly_flooded_oval_sewer_water_depth_and_wall_above_it() -> None:
    features = PipeFeatures(ovalities=(Ovality(230.0, 430.0, 4.0, angle_deg=0.0, blend_mm=40.0),), water=Water(40.0))
    pipe = Pipe(inner_diameter_mm=300.0, features=features)
    res = run(AnalysisConfig(), _rings(pipe, 150.0, 7.5, 40, seed=5))
    assert res.defects == []
    assert any("water" in w for w in res.warnings)
    # True depth at each station: the water level above its section's invert (40 mm,
    # 37 mm where the 4 % ovality with a horizontal major axis lifts the invert).
    true_depth = pipe.water_level() - pipe.invert_height(res.stations_axial_mm)
    assert res.water_depth_mm is not None
    assert abs(res.water_depth_mm - np.median(true_depth)) <= 2.0
    truth = _true_mean_diameter(pipe, res.stations_axial_mm)
    assert abs(res.inner_diameter_mm - np.median(truth)) <= 3 * res.inner_diameter_sigma_mm
    th = np.linspace(0, 2 * np.pi, 720, endpoint=False)
    for s, depth in zip(res.stations, true_depth, strict=True):
        assert abs(s.water_depth_mm - depth) <= 2.0
        r = pipe.wall_radius(np.full_like(th, s.axial_mm), th)
        true_ov = 100 * (2 * r.max() - 2 * r.min()) / (2 * r.mean())
        assert abs(100 * s.ovality - true_ov) <= 0.3
    (water,) = _kinds(res.features, "water")
    assert abs(water.depth_mm - np.median(true_depth)) <= 2.0 and water.truncated
    (oval,) = _kinds(res.features, "ovality")
    assert 220.0 < oval.axial_from_mm < 260.0 and 400.0 < oval.axial_to_mm < 440.0
    assert abs(oval.percent - 4.0) <= 0.3
    fields, _ = report_fields(res, 0.001)
    assert fields["water_depth_mm"] == round(res.water_depth_mm, 2)
    assert {"axial_mm", "inner_diameter_mm", "inner_diameter_sigma_mm", "ovality_pct",
            "ovality_angle_deg", "water_depth_mm"} <= set(fields["stations"][0])
    assert {f["kind"] for f in fields["features"]} == {"water", "ovality"}


@pytest.mark.parametrize("seed", [11, 12, 13])
def test_short_ovality_stretch_is_sized_from_its_plateau(seed: int) -> None:
    """A 37 mm stretch of 5 % ovality (16 mm blends) on rings 11 mm apart: four stations
    are oval, the first and last (3.3-3.8 %) in the blends; the stretch's size is the
    plateau's within 0.3 percentage points and 3 sigma (the median of all four:
    4.24-4.36 %)."""
    rng = np.random.default_rng(seed)
    start = 205.5 + rng.uniform(0.0, 1.0)
    features = PipeFeatures(ovalities=(Ovality(start, start + 37.0, 5.0, angle_deg=rng.uniform(0, 180), blend_mm=16.0),))
    pipe = Pipe(inner_diameter_mm=300.0, features=features)
    res = run(AnalysisConfig(), _rings(pipe, 120.0, 11.0, 16, seed=seed, noise=0.3))
    (oval,) = _kinds(res.features, "ovality")
    assert abs(oval.percent - 5.0) <= min(0.3, 3 * oval.percent_sigma)


@pytest.mark.slow
def test_tight_elbow_is_a_bend_feature() -> None:
    pipe = Pipe(
        inner_diameter_mm=200.0,
        centreline=Centreline(straight_mm=260.0, bend_radius_mm=300.0, bend_angle_deg=90.0),
    )
    res = run(AnalysisConfig(), _rings(pipe, 150.0, 8.0, 90, seed=6))
    assert res.defects == []
    assert abs(res.inner_diameter_mm - 200.0) <= 3 * res.inner_diameter_sigma_mm
    (bend,) = _kinds(res.features, "bend")
    assert abs(bend.radius_mm - 300.0) <= 0.03 * 300.0
    assert abs(bend.turn_deg - 90.0) <= 1.0
    assert abs(bend.axial_from_mm - 260.0) < 15.0
    assert abs(bend.axial_to_mm - (260.0 + 300.0 * math.pi / 2)) < 15.0


def test_narrow_laser_dropout_at_a_common_angle_is_not_water() -> None:
    """A dry 160 mm pipe whose rings all miss 12 deg at the same angle (a mirror strut, a
    dropout): the chord below such a gap is 0.3 mm deep, under 1 % of the diameter and
    3 sigma of the wall noise, so no water is reported (the bend scenario's rings showed
    a 0.27 mm "water" before)."""
    pipe = Pipe(inner_diameter_mm=160.0)
    rings = _rings(pipe, 150.0, 6.0, 16, seed=7, noise=0.08)
    rig_from_world = np.linalg.inv(rings.world_from_rig[rings.frame_index])
    local = np.einsum("nij,nj->ni", rig_from_world[:, :3, :3], rings.points_in_world) + rig_from_world[:, :3, 3]
    keep = np.abs(np.arctan2(local[:, 1], local[:, 0]) + np.pi / 2) > math.radians(6.0)
    dry = AnalysisInputs(rings.points_in_world[keep], rings.frame_index[keep], rings.world_from_rig)
    res = run(AnalysisConfig(), dry)
    assert all(s.water_depth_mm == 0.0 for s in res.stations)
    assert not _kinds(res.features, "water") and res.water_depth_mm is None
    assert not any("water" in w for w in res.warnings)


def test_section_settings_reach_the_section_measurements() -> None:
    """Every section setting of AnalysisConfig (YAML ``analysis.*``) is the one the
    section measurements use, the water threshold included."""
    from omnipipe.analysis.records import section_config

    cfg = AnalysisConfig(water_min_pct=7.0, cut_min_deg=9.0, taper_min_mm=3.0)
    sec = section_config(cfg)
    assert (sec.water_min_pct, sec.cut_min_deg, sec.taper_min_mm) == (7.0, 9.0, 3.0)


def _flooded(depth: float, reach_mm: float, seed: int, noise: float = 0.1) -> AnalysisInputs:
    """A 300 mm pipe with ``depth`` mm of water, rings every 7.5 mm whose samples run
    ``reach_mm`` along the wall past the water line (the stripe's blur), 0.5 deg apart."""
    pipe = Pipe(inner_diameter_mm=300.0, features=PipeFeatures(water=Water(depth)))
    rng = np.random.default_rng(seed)
    n, radius = 24, 150.0
    sig = 150.0 + 7.5 * np.arange(n) + rng.uniform(-0.5, 0.5, n)
    theta = np.linspace(-np.pi, np.pi, 720, endpoint=False)
    centre, normal, binormal, tangent = pipe.frame_at(sig)
    up = pipe.up()
    pts, frame, poses = [], [], []
    for k in range(n):
        r = radius + rng.normal(0, noise, theta.size)
        p = centre[k] + (r * np.cos(theta))[:, None] * normal[k] + (r * np.sin(theta))[:, None] * binormal[k]
        # Angle of each sample from the invert (the lowest wall point) around the axis.
        down = -(up - (up @ tangent[k]) * tangent[k])
        down /= np.linalg.norm(down)
        from_invert = np.arccos(np.clip(((p - centre[k]) @ down) / radius, -1, 1))
        water_line = math.acos(1.0 - depth / radius)  # half-angle of the water's chord
        keep = from_invert > water_line - reach_mm / radius
        pts.append(p[keep])
        frame.append(np.full(int(keep.sum()), k))
        rot = np.stack([normal[k], binormal[k], tangent[k]], axis=1)
        poses.append(make_transform(rot, centre[k] + 82 * tangent[k]))
    return AnalysisInputs(np.concatenate(pts), np.concatenate(frame), np.array(poses))


def test_water_line_read_back_by_the_stripe_blur_reach() -> None:
    """Samples running 4 mm past a 45 mm water line (the stripe's blur) make the cut
    narrower: read as is, the depth is 2.5 mm shallow, 40 sigma; with the reach
    taken back (``edge_reach_mm``) it is within 3 sigma, station by station and for the
    stretch, and the stretch's sigma keeps the reach's shared 1-sigma whole."""
    rings = _flooded(45.0, 4.0, seed=11)
    naive = run(AnalysisConfig(), rings)
    assert naive.water_depth_mm is not None and 45.0 - naive.water_depth_mm > 3 * naive.water_depth_sigma_mm
    rings.edge_reach_mm, rings.edge_reach_sigma_mm = 4.0, 0.5
    res = run(AnalysisConfig(), rings)
    assert res.water_depth_mm is not None
    assert abs(res.water_depth_mm - 45.0) <= 3 * res.water_depth_sigma_mm
    wet = [s for s in res.stations if s.water_depth_mm > 0]
    assert len(wet) == len(res.stations)
    inside = [abs(s.water_depth_mm - 45.0) <= 3 * s.water_depth_sigma_mm for s in wet]
    assert np.mean(inside) >= 0.9
    # The reach's 1-sigma (its spread, 0.5 mm, and the model's share of the 4 mm) moves
    # both chord ends together: sin(half-angle) x that.
    phi = math.acos(1.0 - 45.0 / 150.0)
    shared = math.sin(phi) * math.hypot(0.5, REACH_MODEL_REL * 4.0)
    for s in wet:
        assert abs(s.water_depth_shared_sigma_mm - shared) <= 0.2 * shared
    (water,) = _kinds(res.features, "water")
    assert water.depth_sigma_mm >= shared and abs(water.depth_mm - 45.0) <= 3 * water.depth_sigma_mm


def test_water_line_read_back_by_each_rings_measured_reach() -> None:
    """The same rings with each one's reach measured at its own cut (the stripe's
    half-height point, ``edge_reach_rings_mm``: here the true distance of its last
    samples past the water line, both ends' mean, stated 0.3 mm): the chord ends are
    taken back by exactly that (no half sample step), every station within 3 sigma and
    0.25 mm; the stated reach sigma is shared by the run's stations (their rings err
    alike: benchmarks/RESULTS.md, wat28) and the stretch keeps it whole."""
    rings = _flooded(45.0, 4.0, seed=11)
    pipe = Pipe(inner_diameter_mm=300.0, features=PipeFeatures(water=Water(45.0)))
    centre, _, _, tangent = pipe.frame_at(rings.points_in_world[:, 2])
    down = -(pipe.up() - np.einsum("ij,j->i", tangent, pipe.up())[:, None] * tangent)
    down /= np.linalg.norm(down, axis=1, keepdims=True)
    rel = rings.points_in_world - centre
    from_invert = np.arccos(np.clip(np.einsum("ij,ij->i", rel, down) / 150.0, -1, 1))
    side = np.sign(np.cross(down, rel) @ np.array([0.0, 0.0, 1.0]))
    line = math.acos(1.0 - 45.0 / 150.0)
    n = len(rings.world_from_rig)
    past = np.array([
        0.5 * sum(150.0 * (line - from_invert[(rings.frame_index == k) & (side == sgn)].min()) for sgn in (-1, 1))
        for k in range(n)
    ])
    rings.edge_reach_rings_mm, rings.edge_reach_rings_sigma_mm = past, np.full(n, 0.3)
    res = run(AnalysisConfig(), rings)
    wet = [s for s in res.stations if s.water_depth_mm > 0]
    assert len(wet) == n
    shared = math.sin(line) * 0.3
    for s in wet:
        assert abs(s.water_depth_mm - 45.0) <= min(3 * s.water_depth_sigma_mm, 0.25)
        assert abs(s.water_depth_shared_sigma_mm - shared) <= 0.2 * shared
    (water,) = _kinds(res.features, "water")
    assert abs(water.depth_mm - 45.0) <= 3 * water.depth_sigma_mm and water.depth_sigma_mm >= shared


def test_water_station_on_a_joint_holds_the_joints_step() -> None:
    """A station on a found joint's band may ring both sections (the offset moves the
    invert) and end its cut in the gap's recess: its depth's sigma holds the joint's
    step (offset and gap depth in quadrature, here 5 and 3 mm) and it stays wet; the
    others keep theirs."""
    rng = np.random.default_rng(3)
    stations = [
        Station(axial_mm=float(a), diameter_mm=300.0, diameter_sigma_mm=0.1, diameter_min_mm=300.0,
                diameter_max_mm=300.0, ovality=0.0, ovality_sigma=0.001, ovality_angle_deg=0.0,
                ovality_angle_sigma_deg=1.0, wall_coverage_deg=300.0, cut_centre_deg=-90.0)
        for a in (0.0, 7.5, 15.0, 22.5)
    ]
    sections = [_cut_section(30.0, 0.1, rng) for _ in stations]
    plain, wet = with_water(stations, sections, 0.1, SectionConfig())
    on, wet2 = with_water(stations, sections, 0.1, SectionConfig(), joints=[(5.0, 10.0, math.hypot(5.0, 3.0))])
    assert wet and wet2
    for a, b in zip(plain, on, strict=True):
        assert b.water_depth_mm == a.water_depth_mm
        if a.axial_mm == 7.5:
            assert b.water_depth_sigma_mm >= math.hypot(5.0, 3.0)
        else:
            assert b.water_depth_sigma_mm == a.water_depth_sigma_mm


@pytest.mark.slow
def test_water_stretch_sigma_keeps_the_rings_shared_quantisation() -> None:
    """Every ring is sampled on the same 0.5 deg angles and level water meets each at the
    same angle: the last lit sample falls alike on all 24 rings, so the depth errs alike
    (a saw of about +-0.35 mm as the depth moves through a sample step). The stretch's
    sigma keeps that term whole (averaged over the stations it was 0.04 mm, 9 sigma)."""
    for depth in (40.0, 40.2, 40.45):
        res = run(AnalysisConfig(), _flooded(depth, 0.0, seed=5, noise=0.05))
        (water,) = _kinds(res.features, "water")
        assert abs(water.depth_mm - depth) <= 3.0 * water.depth_sigma_mm
        wet = [s for s in res.stations if s.water_depth_mm > 0]
        assert water.depth_sigma_mm >= 0.9 * float(np.median([s.water_depth_shared_sigma_mm for s in wet]))


def _cut_section(depth: float, noise: float, rng: np.random.Generator) -> Section:
    """One 150 mm ring, 0.5 deg samples, cut off below a water line ``depth`` mm above
    its invert (theta = -90 deg), fitted as the stage fits its stations."""
    radius = 150.0
    theta = np.linspace(-np.pi, np.pi, 720, endpoint=False)
    keep = np.abs(theta + np.pi / 2) > math.acos(1.0 - depth / radius)
    th = theta[keep]
    rho = radius + rng.normal(0, noise, th.size)
    cut, coverage = ring_cut(th, SectionConfig())
    coef = fit_wall_profile(th, rho, 2, AnalysisConfig().loss_scale_mm)
    design = fourier_design(th, 2)
    spread = 1.4826 * float(np.median(np.abs(rho - design @ coef)))
    cov = np.linalg.pinv(design.T @ design) * spread**2
    return Section(coef, cov, 2, cut, coverage)


@pytest.mark.parametrize("noise", [0.1, 1.0])
def test_water_depth_sigma_holds_the_fit_covariance(noise: float) -> None:
    """The wall under the water is the section fit's extrapolation across the cut: its
    covariance carried through the depth (``fit_mm``) grows with the wall noise, and
    the stated sigma covers the true depth within 3 sigma on 90 % of 40 seeded rings."""
    rng = np.random.default_rng(21)
    depths = [water_depth(_cut_section(30.0, noise, rng), noise) for _ in range(40)]
    inside = [abs(d.depth_mm - 30.0) <= 3 * d.sigma_mm for d in depths]
    assert np.mean(inside) >= 0.9
    fit = float(np.median([d.fit_mm for d in depths]))
    # The term scales with the noise (the fit's covariance is spread^2 (A^T A)^-1).
    ref = np.median([water_depth(_cut_section(30.0, 0.1, np.random.default_rng(21)), 0.1).fit_mm])
    assert abs(fit / ref - noise / 0.1) <= 0.3 * noise / 0.1
