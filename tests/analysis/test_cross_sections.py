"""Cross-section measurements of real pipes (issue 30) against the simulator's true
wall: out-of-round, reducing, partly flooded and bending pipes, rings every few mm."""

from __future__ import annotations

import math

import numpy as np
import pytest

from omnipipe.analysis import AnalysisConfig, AnalysisInputs, report_fields, run
from omnipipe.analysis.feature_types import Feature
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
    from omnipipe.analysis.stage import section_config

    cfg = AnalysisConfig(water_min_pct=7.0, cut_min_deg=9.0, taper_min_mm=3.0)
    sec = section_config(cfg)
    assert (sec.water_min_pct, sec.cut_min_deg, sec.taper_min_mm) == (7.0, 9.0, 3.0)
