"""A wide joint gap seen at a slant: the fitted centreline tilted to the pipe (a short run
in a large, noisy pipe), the rings and the gap both slanted across the axial coordinate,
and several rings lying partly in the gap together (issue 30, bench seed 13)."""

from __future__ import annotations

import numpy as np
import pytest

from omnipipe.analysis.centreline import Centreline
from omnipipe.analysis.feature_types import Joint
from omnipipe.analysis.features import FeatureConfig, find_features

R = 267.0
GAP_AT, GAP_MM, DEPTH_MM = -190.0, 10.0, 11.5


def _line(arc: np.ndarray) -> Centreline:
    """A straight centreline along world z through the rings' stations."""
    k = len(arc)
    z = np.tile([0.0, 0.0, 1.0], (k, 1))
    return Centreline(
        arc, arc[:, None] * z, z, np.tile([1.0, 0.0, 0.0], (k, 1)), np.tile([0.0, 1.0, 0.0], (k, 1)),
        np.full(k, R), [],
    )


def _scene(seed: int, gap: bool) -> tuple[Centreline, np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Ten rings 3-8 mm apart over 50 mm, 540 samples each, wall noise 2 mm. Each ring
    strays +-12 mm along the axial coordinate (its plane tilted 2.6 deg to the fitted
    axis); the gap's plane +-8.4 mm (the pipe's true cross-section, 0.8 deg from the
    rings'), so the rings lying near it are partly in it."""
    rng = np.random.default_rng(seed)
    centres = GAP_AT + np.cumsum(np.r_[-22.0, rng.uniform(3.0, 8.0, 9)])
    theta = np.linspace(-np.pi, np.pi, 540, endpoint=False)
    ring_slant = R * np.tan(np.radians(2.6)) * np.cos(theta)
    gap_slant = R * np.tan(np.radians(1.8)) * np.cos(theta - 0.3)
    sig, rho, th, frame = [], [], [], []
    for k, c in enumerate(centres):
        s = c + ring_slant + rng.normal(0.0, 0.3, theta.size)
        r = R + rng.normal(0.0, 2.0, theta.size)
        if gap:
            r += DEPTH_MM * (np.abs(s - gap_slant - GAP_AT) <= 0.5 * GAP_MM)
        sig.append(s)
        rho.append(r)
        th.append(theta)
        frame.append(np.full(theta.size, k))
    return _line(centres), *(np.concatenate(a) for a in (sig, rho, th, frame))


@pytest.mark.parametrize("seed", [1, 2, 3])
def test_wide_gap_crossed_by_slanted_rings_is_one_joint(seed: int) -> None:
    line, sigma, rho, theta, frame = _scene(seed, gap=True)
    found = find_features(FeatureConfig(), line, sigma, rho, theta, frame, R)
    joints = [f for f in found.features if isinstance(f, Joint)]
    assert len(joints) == 1, found.features
    j = joints[0]
    assert abs(j.axial_mm - GAP_AT) <= max(3.0 * j.axial_sigma_mm, 1.0), j
    assert abs(j.gap_mm - GAP_MM) <= 3.0 * j.gap_sigma_mm, j
    assert found.not_wall[np.abs(sigma - GAP_AT) < 3.0].mean() > 0.5


@pytest.mark.parametrize("seed", [1, 2, 3])
def test_slanted_rings_on_plain_wall_hold_no_joint(seed: int) -> None:
    line, sigma, rho, theta, frame = _scene(seed, gap=False)
    found = find_features(FeatureConfig(), line, sigma, rho, theta, frame, R)
    assert found.features == [], found.features
