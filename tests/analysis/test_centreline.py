"""The piecewise centreline fit: a bent pipe's radius and axis, the same on any executor."""

from __future__ import annotations

import numpy as np

from omnipipe.analysis.centreline import fit_centreline
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
