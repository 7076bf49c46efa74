"""The piecewise centreline fit: a bent pipe's radius and axis, the same on any executor."""

from __future__ import annotations

import numpy as np

from omnipipe.analysis.centreline import Centreline, fit_centreline
from omnipipe.executor import open_executor


def _bent_rings(rng: np.random.Generator) -> tuple[list[np.ndarray], np.ndarray]:
    """Rings of a 40 mm radius pipe bent on a 400 mm radius in the x-z plane, 0.05 mm noise."""
    rings, axes = [], []
    for phi in np.linspace(0.0, 0.6, 25):  # bend angle of each station (rad)
        centre = np.array([400.0 * (1 - np.cos(phi)), 0.0, 400.0 * np.sin(phi)])
        tangent = np.array([np.sin(phi), 0.0, np.cos(phi)])
        normal = np.array([np.cos(phi), 0.0, -np.sin(phi)])
        theta = rng.uniform(0, 2 * np.pi, 300)
        ring = centre + 40.0 * (np.cos(theta)[:, None] * normal + np.sin(theta)[:, None] * [0, 1, 0])
        rings.append(ring + rng.normal(0, 0.05, ring.shape))
        axes.append(tangent)
    return rings, np.array(axes)


def test_parallel_fits_equal_serial_and_find_the_radius() -> None:
    rings, axes = _bent_rings(np.random.default_rng(4))
    serial = fit_centreline(rings, axes, np.eye(4), window_mm=30.0, loss_scale_mm=0.3)
    assert np.all(np.abs(np.asarray(serial.radius_mm) - 40.0) < 0.1)
    with open_executor(2) as ex:
        parallel = fit_centreline(rings, axes, np.eye(4), window_mm=30.0, loss_scale_mm=0.3, executor=ex)
    assert np.array_equal(serial.radius_mm, parallel.radius_mm)
    assert np.array_equal(serial.centre, parallel.centre)


def test_nearest_usable_matches_the_brute_force_search() -> None:
    """Each ring's nearest usable ring (the lower of two equally near), as an argmin finds it."""
    from omnipipe.analysis.centreline import _nearest_usable

    rng = np.random.default_rng(3)
    for _ in range(100):
        full = int(rng.integers(2, 40))
        usable = sorted(rng.choice(full, size=int(rng.integers(1, full + 1)), replace=False).tolist())
        brute = [int(np.argmin(np.abs(np.array(usable) - k))) for k in range(full)]
        assert _nearest_usable(usable, full).tolist() == brute


def _elbow_line(rng: np.random.Generator, shared: bool) -> Centreline:
    """Stations every 12 mm along 200 mm straight, a 90 deg bend of radius 300 mm
    (471 mm) and 150 mm straight again, tangents with 0.3 deg noise; ``shared``: every
    third station repeats its neighbour's tangent (the piecewise fits' tangents are
    lines through the same few centres)."""
    arc = np.arange(-200.0, 471.24 + 150.0, 12.0) + rng.uniform(-2, 2)
    phi = np.clip(arc / 300.0, 0.0, np.pi / 2) + rng.normal(0.0, np.radians(0.3), len(arc))
    tangent = np.column_stack([np.sin(phi), rng.normal(0, np.radians(0.3), len(arc)), np.cos(phi)])
    tangent /= np.linalg.norm(tangent, axis=1, keepdims=True)
    if shared:
        tangent[2::3] = tangent[1::3][: len(tangent[2::3])]
    k = len(arc)
    return Centreline(arc, np.zeros((k, 3)), tangent, np.zeros((k, 3)), np.zeros((k, 3)), np.full(k, 100.0), [])


def test_tight_elbow_fit_through_shared_tangents() -> None:
    """A straight - bend - straight centreline whose per-step curvature drops to 0 where
    two stations share a tangent: one bend, its start, end, radius and turn within 3
    sigma and the acceptance (radius 3 %, turn 1 deg), over 5 seeds."""
    from omnipipe.analysis.sections import _bends
    from omnipipe.analysis.stations import SectionConfig

    for seed in range(5):
        (bend,) = _bends(_elbow_line(np.random.default_rng(seed), True), 200.0, SectionConfig())
        assert abs(bend.radius_mm - 300.0) <= min(0.03 * 300.0, 3 * bend.radius_sigma_mm + 1.0), bend
        assert abs(bend.turn_deg - 90.0) <= min(1.0, 3 * bend.turn_sigma_deg + 0.1), bend
        assert abs(bend.axial_from_mm) <= 3 * bend.axial_from_sigma_mm, bend
        assert abs(bend.axial_to_mm - 150 * np.pi) <= 3 * bend.axial_to_sigma_mm, bend
        assert not bend.truncated


def _short_tapered_run(rng: np.random.Generator) -> tuple[list[np.ndarray], np.ndarray]:
    """Eleven rings over 50 mm of a 270 mm radius pipe along z: a taper to 265 mm, 1.5 mm
    wall noise, each ring's centre off the axis by 1 mm (sd; the rings' systematic errors
    of a real run), each ring in a light plane tilted 1 deg; the rig's z axis (the prior)
    tilted 0.8 deg from the pipe's."""
    rings = []
    for z in np.linspace(0.0, 50.0, 11):
        theta = rng.uniform(0, 2 * np.pi, 200)
        r = 270.0 - 0.1 * z + rng.normal(0, 1.5, theta.shape)
        off = rng.normal(0.0, 1.0, 2)
        x, y = r * np.cos(theta) + off[0], r * np.sin(theta) + off[1]
        rings.append(np.column_stack([x, y, z + np.tan(np.radians(1.0)) * x]))
    tilt = np.radians(0.8)
    axes = np.tile([np.sin(tilt), 0.0, np.cos(tilt)], (len(rings), 1))
    return rings, axes


def test_short_run_axis_stays_on_the_pipe_axis_through_scattered_centres_and_a_taper() -> None:
    """Over 6 seeded short runs the prior (0.8 deg off the pipe's axis) takes a third off
    the centres' line's mean tilt (1.7 deg) and keeps every tangent within 1.5 deg."""
    from omnipipe.analysis.centreline import AxisPrior, recentred
    from omnipipe.analysis.cylinder import circle_fit_2d

    z = np.array([0.0, 0.0, 1.0])
    free_tilt, tilt = [], []
    for seed in range(6):
        rings, axes = _short_tapered_run(np.random.default_rng(seed))
        line = fit_centreline(rings, axes, np.eye(4), window_mm=130.0, loss_scale_mm=0.5)
        # each ring's own section centre in its station's (normal, binormal) plane
        offsets = np.array([
            circle_fit_2d(np.column_stack([(r - c) @ n, (r - c) @ b]))[0]
            for r, c, n, b in zip(rings, line.centre, line.normal, line.binormal, strict=True)
        ])
        free = recentred(line, offsets, np.eye(4), 65.0)
        prior = AxisPrior(axes, np.full(len(axes), np.radians(1.0)))
        fixed = recentred(line, offsets, np.eye(4), 65.0, axis_prior=prior)
        free_tilt.append(np.degrees(np.arccos(np.abs(free.tangent @ z))).max())
        tilt.append(np.degrees(np.arccos(np.abs(fixed.tangent @ z))).max())
    assert np.mean(free_tilt) > 1.5, free_tilt  # the case this guards: the centres alone tilt
    assert np.mean(tilt) < 0.7 * np.mean(free_tilt), (tilt, free_tilt)
    assert max(tilt) < 1.5, tilt


def test_well_spread_centres_outweigh_the_axis_prior() -> None:
    """50 centres over 500 mm along a line 3 deg off the prior: the direction is the
    centres' (within 0.1 deg), the prior only steadies short, scattered runs."""
    from omnipipe.analysis.centreline import _ridge_direction

    rng = np.random.default_rng(2)
    true = np.array([np.sin(np.radians(3.0)), 0.0, np.cos(np.radians(3.0))])
    centres = np.outer(np.linspace(0, 500, 50), true) + rng.normal(0, 0.05, (50, 3))
    d = _ridge_direction(centres, np.array([0.0, 0.0, 1.0]), np.radians(1.0))
    assert np.degrees(np.arccos(abs(d @ true))) < 0.1


def _rig_poses(turn_rad: float, travel_mm: float, n: int) -> np.ndarray:
    """(n, 4, 4) rig poses moving ``travel_mm`` along z while z turns ``turn_rad`` about y."""
    poses = np.tile(np.eye(4), (n, 1, 1))
    for k, f in enumerate(np.linspace(0.0, 1.0, n)):
        a = f * turn_rad
        poses[k, :3, :3] = [[np.cos(a), 0, np.sin(a)], [0, 1, 0], [-np.sin(a), 0, np.cos(a)]]
        poses[k, :3, 3] = [0.0, 0.0, f * travel_mm]
    return poses


def test_rig_axis_prior_fades_with_the_turn_between_rig_and_ring() -> None:
    """Rings 200 mm behind the rig: a straight run keeps the head-tilt spread, a run whose
    rig turns 5 deg over 50 mm (a bend) widens it to about 20 deg (5 deg x 200 / 50)."""
    from omnipipe.analysis.centreline import rig_axis_prior

    for turn_deg, want_deg in ((0.0, 1.0), (5.0, np.hypot(1.0, 20.0))):
        poses = _rig_poses(np.radians(turn_deg), 50.0, 11)
        centre = poses[:, :3, 3] - 200.0 * poses[:, :3, 2]
        prior = rig_axis_prior(poses, centre, np.radians(1.0))
        assert np.allclose(np.degrees(prior.sigma_rad), want_deg, atol=0.05)
        assert np.allclose(prior.direction, poses[:, :3, 2])
