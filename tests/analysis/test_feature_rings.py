"""What the feature finders share (omnipipe.analysis.feature_rings), against truth."""

from __future__ import annotations

import numpy as np

from omnipipe.analysis.feature_rings import robust_sine_fit


def test_robust_sine_fit_recovers_a_tilted_ring_past_its_stray_samples() -> None:
    """Seeded: a ring tilted to the axis (sigma = 12 + 4 cos phi - 2.5 sin phi mm, 0.05 mm
    noise) with 10 % of its samples thrown 3-8 mm along the axis (a rim's stray ones):
    the plane within 0.03 mm of the truth, every stray sample dropped and 97 % of the
    others kept; a plain least-squares fit is off by more than 0.1 mm."""
    rng = np.random.default_rng(7)
    phi = rng.uniform(0.0, 2.0 * np.pi, 400)
    truth = np.array([12.0, 4.0, -2.5])
    sigma = truth[0] + truth[1] * np.cos(phi) + truth[2] * np.sin(phi) + rng.normal(0, 0.05, len(phi))
    stray = rng.random(len(phi)) < 0.1
    sigma[stray] += rng.uniform(3.0, 8.0, stray.sum()) * rng.choice([-1.0, 1.0], stray.sum())
    for passes, k, floor in ((2, 3.0, 0.5), (3, 2.5, 1.0)):  # openings.ring_axial's, joints' gap plane's
        p, res, keep = robust_sine_fit(sigma, phi, passes, k, floor)
        assert np.abs(p - truth).max() < 0.03
        assert not keep[stray].any() and keep[~stray].mean() > 0.97
        assert np.allclose(res, sigma - (p[0] + p[1] * np.cos(phi) + p[2] * np.sin(phi)))
    A = np.column_stack([np.ones(len(phi)), np.cos(phi), np.sin(phi)])
    plain, *_ = np.linalg.lstsq(A, sigma, rcond=None)
    assert np.abs(plain - truth).max() > 0.1


def test_ring_deviations_are_the_same_on_an_executor() -> None:
    """60 oval rings (three raised in a joint's gap, one too sparse for order 2) fitted on
    two worker processes: the very same deviations, positions and raised rings as here."""
    from omnipipe.analysis.feature_rings import FeatureConfig, ring_deviations
    from omnipipe.executor import open_executor

    rng = np.random.default_rng(5)
    counts = np.full(60, 200)
    counts[17] = 15
    frame = np.repeat(np.arange(60), counts)
    theta = rng.uniform(0, 2 * np.pi, frame.size)
    sigma = 4.0 * frame + rng.normal(0, 0.3, frame.size)
    rho = 80.0 + 0.3 * np.cos(2 * theta) + rng.normal(0, 0.05, frame.size)
    rho[(frame >= 30) & (frame <= 32)] += 3.0  # the rings in a joint's gap
    args = (FeatureConfig(), sigma, rho, theta, frame, np.arange(60))
    here = ring_deviations(*args)
    with open_executor(2) as ex:
        there = ring_deviations(*args, ex)
    assert here[2][30:33].all() and here[2].sum() == 3
    for a, b in zip(here, there, strict=True):
        assert np.array_equal(a, b)
