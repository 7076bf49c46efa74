"""Analysis stage against analytic ground truth: cylinder fit, centreline, defects."""

from __future__ import annotations

import numpy as np
import pytest

from omnipipe.analysis import AnalysisConfig, AnalysisInputs, fit_cylinder, report_fields, run
from omnipipe.analysis.defects import find_defects
from omnipipe.analysis.sizing import plateau
from omnipipe.analysis.wall_profile import WallSamples
from omnipipe.geometry import make_transform
from omnipipe.sim.scenarios import make_scenario


def _random_rotation(rng: np.random.Generator) -> np.ndarray:
    q, _ = np.linalg.qr(rng.normal(size=(3, 3)))
    return q * np.sign(np.linalg.det(q))


def test_cylinder_fit_with_outliers() -> None:
    rng = np.random.default_rng(1)
    world_from_cyl = _random_rotation(rng)
    axis_true, radius = world_from_cyl[:, 2], 87.3
    point_true = np.array([5.0, -3.0, 2.0])
    n = 5000
    theta = rng.uniform(-np.pi, np.pi, n)
    z = rng.uniform(-150, 150, n)
    local = np.column_stack([radius * np.cos(theta), radius * np.sin(theta), z])
    local[:, :2] *= (1 + rng.normal(0, 0.1, n) / radius)[:, None]  # 0.1 mm radial noise
    outliers = rng.random(n) < 0.1
    local[outliers, :2] *= rng.uniform(0.8, 0.97, outliers.sum())[:, None]  # stray points inside
    pts = local @ world_from_cyl.T + point_true
    guess = axis_true + rng.normal(0, 0.1, 3)  # ~6 deg off
    cyl = fit_cylinder(pts, guess)
    assert abs(cyl.radius_mm - radius) < 0.03
    assert np.degrees(np.arccos(min(abs(cyl.axis @ axis_true), 1.0))) < 0.05
    rel = cyl.point - point_true
    assert np.linalg.norm(rel - (rel @ axis_true) * axis_true) < 0.05


def _synthetic_rings(scenario: str, spacing: float, n_rings: int, seed: int, noise: float = 0.1):
    """Rings of the true pipe wall every ``spacing`` mm, rig z along the centreline."""
    pipe = make_scenario(scenario).pipe
    rng = np.random.default_rng(seed)
    sig = 100.0 + spacing * np.arange(n_rings) + rng.uniform(-1, 1, n_rings)
    theta = np.linspace(-np.pi, np.pi, 720, endpoint=False)
    centre, normal, binormal, tangent = pipe.frame_at(sig)
    pts, frame, poses = [], [], []
    for k in range(n_rings):
        r = pipe.wall_radius(np.full_like(theta, sig[k]), theta) + rng.normal(0, noise, theta.size)
        keep = rng.random(theta.size) > 0.05  # a few missed samples
        p = (
            centre[k]
            + (r * np.cos(theta))[:, None] * normal[k]
            + (r * np.sin(theta))[:, None] * binormal[k]
        )
        pts.append(p[keep])
        frame.append(np.full(keep.sum(), k))
        poses.append(
            make_transform(
                np.stack([normal[k], binormal[k], tangent[k]], axis=1), centre[k] + 82 * tangent[k]
            )
        )
    return pipe, AnalysisInputs(np.concatenate(pts), np.concatenate(frame), np.array(poses))


def test_paper_pipe_table_one_from_exact_rings() -> None:
    """World = pipe frame at sigma 0: contract axial/angle equal the pipe's.

    Rings every 6 mm: the axial half-height crossings are interpolated between rings,
    so the length error grows with the ring spacing (about +-spacing/4 per end).
    """
    pipe, inputs = _synthetic_rings("paper", 6.0, 50, seed=2)
    res = run(AnalysisConfig(), inputs)
    assert res.straight
    assert abs(res.inner_diameter_mm - pipe.inner_diameter_mm) < 0.05
    assert np.nanmax(res.stations_ovality) < 0.002
    assert len(res.defects) == 1
    d, t = res.defects[0], pipe.defects[0]
    assert d.kind == t.kind
    assert abs(d.height_mm - t.height_mm) < 0.3
    assert abs(d.width_mm - t.width_mm) < 0.5
    assert abs(d.length_mm - t.length_mm) < 2.0
    assert abs(d.axial_start_mm - t.axial_start_mm) < 2.0
    assert abs((d.angle_deg - t.angle_deg + 180) % 360 - 180) < 1.0


def test_bent_pipe_diameter_and_defects() -> None:
    pipe, inputs = _synthetic_rings("bend", 11.0, 36, seed=4)
    res = run(AnalysisConfig(), inputs)
    assert not res.straight
    assert abs(res.inner_diameter_mm - pipe.inner_diameter_mm) < 0.3
    found = sorted(res.defects, key=lambda d: d.axial_start_mm)
    assert [d.kind for d in found] == [
        t.kind for t in sorted(pipe.defects, key=lambda t: t.axial_start_mm)
    ]
    for d, t in zip(found, sorted(pipe.defects, key=lambda t: t.axial_start_mm), strict=True):
        assert abs(d.height_mm - t.height_mm) < 0.3
        assert abs(d.width_mm - t.width_mm) < 1.0
        assert abs(d.length_mm - t.length_mm) < 3.0
        assert abs((d.angle_deg - t.angle_deg + 180) % 360 - 180) < 2.0


@pytest.mark.parametrize("centre_deg", [0.0, 359.0, 180.0])
def test_defect_on_a_deviation_map_across_the_seam(centre_deg: float) -> None:
    """A 2 mm dent, 18 mm wide, 45 mm long (half height), 0.05 mm noise; also across angle 0."""
    rng = np.random.default_rng(7)
    radius, circ = 100.0, 2 * np.pi * 100.0
    sig, ang = np.meshgrid(np.arange(0, 200, 5.0), np.arange(720) * circ / 720, indexing="ij")
    sig, arc = sig.ravel(), ang.ravel()
    du = (arc - np.radians(centre_deg) * radius + circ / 2) % circ - circ / 2
    dev = 2.0 * plateau(du, 18.0, 6.0) * plateau(sig - 100.0, 45.0, 15.0)
    dev += rng.normal(0, 0.05, sig.size)
    ring = (sig // 5).astype(int)
    defects, _ = find_defects(
        WallSamples(sig, arc, dev, ring, circ),
        min_height_mm=1.0,
        noise_factor=6,
        min_points=4,
        grid_mm=0.25,
    )
    assert len(defects) == 1
    d = defects[0]
    assert d.kind == "dent" and abs(d.height_mm - 2.0) < 0.05
    assert abs(d.width_mm - 18.0) < 0.3
    assert abs(d.length_mm - 45.0) < 1.0
    assert abs(d.axial_start_mm - 77.5) < 0.5
    assert abs((d.angle_deg - centre_deg + 180) % 360 - 180) < 0.2


def test_oblique_rings_in_a_bend_stay_round() -> None:
    """Real rings are cut by the laser plane of a rig 82 mm further on: oblique in a bend.

    The stations' diameter and ovality must describe the pipe (round, 160 mm), not the
    ellipse the oblique plane cuts from it.
    """
    pipe = make_scenario("bend").pipe
    rng = np.random.default_rng(1)
    sig_o = 180 + 6.0 * np.arange(50)
    phi = np.linspace(-np.pi, np.pi, 720, endpoint=False)
    centre, normal, binormal, tangent = pipe.frame_at(sig_o)
    pts, frame, poses = [], [], []
    for k in range(len(sig_o)):
        c0 = centre[k] - 82 * tangent[k]  # the laser plane, orthogonal to the rig axis
        d = np.cos(phi)[:, None] * normal[k] + np.sin(phi)[:, None] * binormal[k]
        rho = np.full(len(phi), pipe.radius_mm)
        for _ in range(6):  # where the plane meets the wall
            s, r, th, *_ = pipe.pipe_coordinates(c0 + rho[:, None] * d)
            rho += pipe.wall_radius(s, th) - r
        pts.append(c0 + (rho + rng.normal(0, 0.1, len(phi)))[:, None] * d)
        frame.append(np.full(len(phi), k))
        poses.append(make_transform(np.stack([normal[k], binormal[k], tangent[k]], axis=1), centre[k]))
    res = run(AnalysisConfig(), AnalysisInputs(np.concatenate(pts), np.concatenate(frame), np.array(poses)))
    assert abs(res.inner_diameter_mm - 160.0) < 0.1
    assert np.nanmax(res.stations_ovality) < 0.004  # the oblique section itself: 0.8 %
    assert np.all(np.abs(res.stations_diameter_mm - 160.0) < 0.3)
    assert sorted(d.kind for d in res.defects) == ["bulge", "dent"]


def test_lone_outlier_samples_are_not_defects() -> None:
    """Single samples 2-3 mm out (a blurred peak on a steep ring) on several rings at one angle."""
    rng = np.random.default_rng(11)
    circ = 2 * np.pi * 75.0
    sig, arc = np.meshgrid(np.arange(0, 120, 9.0), np.arange(720) * circ / 720, indexing="ij")
    sig, arc = sig.ravel(), arc.ravel()
    dev = rng.normal(0, 0.05, sig.size)
    ring = (sig // 9).astype(int)
    spikes = np.flatnonzero(np.isclose(arc, 300 * circ / 720))  # the same angle on every ring
    dev[spikes] = rng.uniform(2.0, 3.0, len(spikes))
    defects, _ = find_defects(
        WallSamples(sig, arc, dev, ring, circ), min_height_mm=1.0, noise_factor=6, min_points=4, grid_mm=0.25
    )
    assert defects == []


def test_rig_calibration_uncertainty_covers_a_miscalibrated_laser() -> None:
    """A laser plane calibrated 0.15 mm too far (1 sigma of 0.15 mm stated in rig.yaml)
    scales every length by 82.15 / 82: the diameter's stated 2 sigma covers that error
    only when the calibration's share is included; lengths along the pipe carry it too."""
    pipe, inputs = _synthetic_rings("paper", 6.0, 40, seed=5, noise=0.05)
    k = (82.0 + 0.15) / 82.0
    poses = inputs.world_from_rig.copy()
    poses[:, :3, 3] *= k
    scaled = AnalysisInputs(inputs.points_in_world * k, inputs.frame_index, poses)
    plain = run(AnalysisConfig(), scaled)
    err = plain.inner_diameter_mm - pipe.inner_diameter_mm
    assert abs(err - (k - 1) * pipe.inner_diameter_mm) < 0.05  # the miscalibration shows
    assert abs(err) > 2 * plain.inner_diameter_sigma_mm  # and nothing states it
    scaled.calibration_sigma_rel = 0.15 / 82.0
    res = run(AnalysisConfig(), scaled)
    assert abs(err) <= 2 * res.inner_diameter_sigma_mm <= 2 * abs(err) + 0.2
    fields, _ = report_fields(res, 1e-4)
    assert fields["calibration_sigma_rel"] == pytest.approx(0.15 / 82.0, rel=1e-3)
    plain_fields, _ = report_fields(plain, 1e-4)
    assert plain_fields["calibration_sigma_rel"] is None
    assert fields["run_length_sigma_mm"] >= fields["run_length_mm"] * 0.15 / 82.0
    assert fields["run_length_sigma_mm"] > 2 * plain_fields["run_length_sigma_mm"]


@pytest.mark.parametrize(("start", "cut_by"), [(170.0, "end"), (-20.0, "start")])
def test_defect_cut_by_the_measured_stretch_is_truncated(start: float, cut_by: str) -> None:
    """A 2 mm dent 60 mm long (half height) that runs past the last (first) ring at 195 (0)
    mm: flagged truncated, its extent inside the rings (a lower bound of the true one);
    the same dent inside the stretch is not flagged."""
    rng = np.random.default_rng(3)
    radius, circ = 100.0, 2 * np.pi * 100.0
    sig, arc = np.meshgrid(np.arange(0, 200, 5.0), np.arange(720) * circ / 720, indexing="ij")
    sig, arc = sig.ravel(), arc.ravel()
    ring = (sig // 5).astype(int)

    def search(z0: float):
        du = (arc - np.radians(90.0) * radius + circ / 2) % circ - circ / 2
        dev = 2.0 * plateau(du, 18.0, 6.0) * plateau(sig - (z0 + 30.0), 60.0, 15.0)
        dev = dev + rng.normal(0, 0.05, sig.size)
        return find_defects(
            WallSamples(sig, arc, dev, ring, circ), min_height_mm=1.0, noise_factor=6, min_points=4, grid_mm=0.25
        )

    res = search(start)
    assert len(res.defects) == 1
    d = res.defects[0]
    assert d.truncated
    assert 0.0 - 1e-6 <= d.axial_start_mm and d.axial_end_mm <= 195.0 + 1e-6
    assert d.length_mm < 60.0  # the measured part only
    assert abs(d.height_mm - 2.0) < 0.3
    assert any(f"the {cut_by} of the measured stretch" in w for w in res.warnings)
    assert d.to_contract()["truncated"] is True
    inside = search(70.0).defects
    assert len(inside) == 1 and not inside[0].truncated
    assert "truncated" not in inside[0].to_contract()


def test_defect_at_an_unmeasured_band_is_truncated() -> None:
    """A dent whose side lies in a band of the wall without samples (standing water):
    truncated; the same dent on a fully measured wall is not."""
    rng = np.random.default_rng(5)
    radius, circ = 100.0, 2 * np.pi * 100.0
    sig, arc = np.meshgrid(np.arange(0, 200, 5.0), np.arange(720) * circ / 720, indexing="ij")
    sig, arc = sig.ravel(), arc.ravel()
    ring = (sig // 5).astype(int)
    du = (arc - np.radians(90.0) * radius + circ / 2) % circ - circ / 2
    dev = 2.0 * plateau(du, 18.0, 6.0) * plateau(sig - 100.0, 45.0, 15.0) + rng.normal(0, 0.05, sig.size)
    wet = (du > 4.0) & (du < 60.0)  # no samples from just past the dent's centre on
    kw = dict(min_height_mm=1.0, noise_factor=6, min_points=4, grid_mm=0.25)
    cut = find_defects(WallSamples(sig[~wet], arc[~wet], dev[~wet], ring[~wet], circ), **kw)
    assert len(cut.defects) == 1 and cut.defects[0].truncated
    assert any("water line" in w for w in cut.warnings)
    whole = find_defects(WallSamples(sig, arc, dev, ring, circ), **kw)
    assert len(whole.defects) == 1 and not whole.defects[0].truncated


def test_ring_groups_are_each_rings_indices() -> None:
    from omnipipe.analysis.station_profiles import ring_groups

    frame = np.random.default_rng(4).integers(0, 9, size=400)
    groups = ring_groups(frame, 10)
    assert [g.tolist() for g in groups] == [np.flatnonzero(frame == k).tolist() for k in range(10)]


def test_defect_fits_are_the_same_on_an_executor() -> None:
    """A dent and a bulge fitted on two worker processes: the very same defects as here."""
    from omnipipe.executor import open_executor

    rng = np.random.default_rng(11)
    circ = 2 * np.pi * 100.0
    sig, ang = np.meshgrid(np.arange(0, 200, 5.0), np.arange(360) * circ / 360, indexing="ij")
    sig, arc = sig.ravel(), ang.ravel()
    dev = 2.0 * plateau(arc - 100.0, 18.0, 6.0) * plateau(sig - 60.0, 45.0, 15.0)
    dev -= 1.5 * plateau(arc - 400.0, 15.0, 5.0) * plateau(sig - 140.0, 30.0, 10.0)
    dev += rng.normal(0, 0.05, sig.size)
    samples = WallSamples(sig, arc, dev, (sig // 5).astype(int), circ)
    kw = {"min_height_mm": 1.0, "noise_factor": 6, "min_points": 4, "grid_mm": 0.25}
    here = find_defects(samples, **kw)
    with open_executor(2) as ex:
        there = find_defects(samples, **kw, executor=ex)
    assert sorted(d.kind for d in here.defects) == ["bulge", "dent"]
    assert here.defects == there.defects
    assert all(np.array_equal(a, b) for a, b in zip(here.masks, there.masks, strict=True))


def test_station_profiles_are_the_same_on_an_executor() -> None:
    """40 oval rings (one cut by water, one crossing a lateral's opening, some samples
    left out, some stray) fitted on two worker processes: the very same profiles,
    sections and deviations as here."""
    from omnipipe.analysis.defect_search import FeatureZone
    from omnipipe.analysis.station_profiles import ring_groups, station_profiles
    from omnipipe.executor import open_executor

    rng = np.random.default_rng(12)
    theta = np.tile(np.radians(np.arange(0, 360, 1.0)), 40) + rng.normal(0, 1e-3, 40 * 360)
    frame = np.repeat(np.arange(40), 360)
    sigma = 5.0 * frame + rng.normal(0, 0.2, frame.size)
    rho = 100.0 + 0.4 * np.cos(2 * theta) + rng.normal(0, 0.05, frame.size)
    keep = ~((frame == 7) & (np.abs(theta - 1.5 * np.pi) < 0.6))  # a water cut
    keep &= ~((frame == 20) & (np.abs(theta - 1.0) < 0.3))  # the light lost in a branch
    theta, frame, sigma, rho = theta[keep], frame[keep], sigma[keep], rho[keep]
    exclude = rng.random(frame.size) < 0.05
    stray = rng.random(frame.size) < 0.01
    ok = np.ones(41, bool)
    ok[33], ok[40] = False, False  # stations not measured (the last ring has no points)
    zones = (FeatureZone(95.0, 105.0, "a lateral", arc_mm=100.0, half_arc_mm=30.0),)
    args = (AnalysisConfig(), ring_groups(frame, 41), theta, rho, sigma, ok, exclude, zones, 100.0, stray)
    here = station_profiles(*args)
    with open_executor(2) as ex:
        there = station_profiles(*args, executor=ex)
    assert len(here.sections) == 39 and any(s.cut is not None for s in here.sections)
    for name in ("axial", "diameter", "diameter_sigma", "ovality", "ovality_sigma", "deviation", "rings"):
        assert np.array_equal(getattr(here, name), getattr(there, name), equal_nan=True), name
    for a, b in zip(here.sections, there.sections, strict=True):
        assert np.array_equal(a.coef, b.coef) and np.array_equal(a.cov, b.cov)
        assert (a.order, a.cut, a.coverage_deg) == (b.order, b.cut, b.coverage_deg)


def test_peak_bias_term_covers_a_ring_radius_read_off_by_a_fraction_of_a_pixel() -> None:
    """Every ring read 0.06 px of image radius too far out (a sub-pixel bias of the laser
    peaks shared by the ring) at 3 mm per px: its radius 0.18 mm, its diameter 0.36 mm
    long. The fit cannot see that; the stations' stated 3 sigma covers it only with the
    rings' radial pixel scale given (``radial_mm_per_px``, 2 x 0.03 px x 3 mm per px in
    each diameter's sigma), and then the headline's too; a ring of unknown scale (NaN)
    takes the run's median."""
    pipe, inputs = _synthetic_rings("paper", 3.0, 14, seed=4, noise=0.05)  # before its defect
    poses = inputs.world_from_rig
    rel = inputs.points_in_world - poses[inputs.frame_index, :3, 3]
    axis = poses[inputs.frame_index, :3, 2]
    radial = rel - np.einsum("ij,ij->i", rel, axis)[:, None] * axis
    radial /= np.linalg.norm(radial, axis=1, keepdims=True)
    biased = AnalysisInputs(inputs.points_in_world + 0.06 * 3.0 * radial, inputs.frame_index, poses)
    d_true = pipe.inner_diameter_mm
    plain = run(AnalysisConfig(), biased)
    err = plain.stations_diameter_mm - d_true
    assert np.all(np.abs(err - 0.36) < 0.1)  # the bias shows
    assert np.mean(np.abs(err) <= 3 * plain.stations_diameter_sigma_mm) < 0.2  # unstated
    scale = np.full(len(poses), 3.0)
    scale[3] = np.nan
    biased.radial_mm_per_px = scale
    res = run(AnalysisConfig(), biased)
    assert np.all(np.abs(err) <= 3 * res.stations_diameter_sigma_mm)
    assert np.all(res.stations_diameter_sigma_mm >= 2 * 0.03 * 3.0)
    assert res.stations_diameter_sigma_mm[3] == pytest.approx(np.median(res.stations_diameter_sigma_mm), rel=0.3)
    assert abs(res.inner_diameter_mm - d_true) <= 3 * res.inner_diameter_sigma_mm
    assert abs(plain.inner_diameter_mm - d_true) > 3 * plain.inner_diameter_sigma_mm
    assert res.inner_diameter_sigma_mm < 0.25  # the term, not a blanket
