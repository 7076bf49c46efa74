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
