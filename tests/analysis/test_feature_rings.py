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
