"""Openings seen as lost returns alone (no sample in the branch): a round branch's hole
is at least as long along the axis as it is wide; returns lost on two rings across a
seam or a shadow make a stretch shorter than wide (bench seeds 4: 43 mm wide, 36 mm
between the clean rings either side), no lateral."""

from __future__ import annotations

import math

import numpy as np
import pytest

from omnipipe.analysis.centreline import Centreline
from omnipipe.analysis.feature_types import Lateral
from omnipipe.analysis.features import FeatureConfig, find_features

R = 75.0


def _line(arc: np.ndarray) -> Centreline:
    """A straight centreline along world z through the rings' stations."""
    return Centreline.straight(arc, R)


def _rings(seed: int, lost: list[float], width_mm: float, hole_mm: float | None = None):
    """Rings 10 mm apart (jittered) over -60..60 mm of a 150 mm pipe, 540 samples each,
    noise 0.5 mm; no returns over ``width_mm`` of arc about 236 deg on the rings at the
    axial positions ``lost`` (a seam's dropout), or within a round hole of ``hole_mm``
    (an ellipse as long as wide, centred at 0) on every ring crossing it."""
    rng = np.random.default_rng(seed)
    centres = np.arange(-60.0, 61.0, 10.0) + rng.uniform(-0.5, 0.5, 13)
    theta = np.linspace(-np.pi, np.pi, 540, endpoint=False)
    u = ((theta - math.radians(236.0) + np.pi) % (2 * np.pi) - np.pi) * R
    sig, rho, th, frame = [], [], [], []
    for k, c in enumerate(centres):
        keep = np.ones(theta.size, bool)
        if any(abs(c - z) < 1.0 for z in lost):  # the rings nearest those positions
            keep &= np.abs(u) > 0.5 * width_mm
        if hole_mm is not None:
            keep &= (u / (0.5 * hole_mm)) ** 2 + (c / (0.5 * hole_mm)) ** 2 > 1.0
        sig.append(np.full(keep.sum(), c) + rng.normal(0.0, 0.2, keep.sum()))
        rho.append(R + rng.normal(0.0, 0.5, keep.sum()))
        th.append(theta[keep])
        frame.append(np.full(keep.sum(), k))
    return _line(centres), *(np.concatenate(a) for a in (sig, rho, th, frame))


@pytest.mark.parametrize("seed", [1, 2, 3])
def test_returns_lost_on_two_rings_shorter_than_wide_are_no_lateral(seed: int) -> None:
    rng = np.random.default_rng(seed)
    line, sigma, rho, theta, frame = _rings(seed, [0.0, 10.0], 43.0)
    found = find_features(FeatureConfig(), line, sigma, rho, theta, frame, R)
    assert not [f for f in found.features if isinstance(f, Lateral)], found.features
    # A round hole of the same width, lost on every ring crossing it: a lateral.
    line, sigma, rho, theta, frame = _rings(seed, [], 0.0, hole_mm=43.0 + rng.uniform(0.0, 5.0))
    found = find_features(FeatureConfig(), line, sigma, rho, theta, frame, R)
    lats = [f for f in found.features if isinstance(f, Lateral)]
    assert len(lats) == 1, found.features
    assert abs(lats[0].axial_mm) <= 10.0 and abs((lats[0].angle_deg - 236.0 + 180) % 360 - 180) <= 5.0
