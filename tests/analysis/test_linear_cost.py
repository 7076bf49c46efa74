"""The analysis' work grows with the run, not with the run times its features: counts of
the per-ring fits the feature search makes on repeated copies of one run (no timing)."""

from __future__ import annotations

import numpy as np
import pytest

from omnipipe.analysis import feature_rings, features, openings
from omnipipe.analysis.centreline import Centreline
from omnipipe.analysis.features import FeatureConfig, find_features

RADIUS = 150.0
COPY_MM = 400.0  # each copy: rings every 4 mm over 400 mm, a 100 mm tee in its middle


def _copies(n: int, seed: int = 5) -> tuple[Centreline, tuple[np.ndarray, ...]]:
    """``n`` copies of a straight run one after the other along the axis (pipe
    coordinates: axis along z, angle 0 along x): rings every 4 mm (jittered), 360
    samples each with 0.1 mm noise, and in each copy's middle a square tee's hole (100 mm
    diameter at 120 deg) whose samples lie 40-140 mm out on the branch wall. Returns the
    centreline and (sigma, rho, theta, frame) of every sample."""
    rng = np.random.default_rng(seed)
    sig = np.arange(0.0, n * COPY_MM, 4.0) + rng.uniform(-0.5, 0.5, int(n * COPY_MM / 4.0))
    theta = np.linspace(-np.pi, np.pi, 360, endpoint=False)
    half = RADIUS * np.arcsin(50.0 / RADIUS)
    u = ((theta - np.radians(120.0) + np.pi) % (2 * np.pi) - np.pi) * RADIUS
    cols: list[list[np.ndarray]] = [[], [], [], []]
    for k, s in enumerate(sig):
        zc = COPY_MM * (np.floor(s / COPY_MM) + 0.5)
        r = RADIUS + rng.normal(0, 0.1, theta.size)
        in_hole = (u / half) ** 2 + ((s - zc) / 50.0) ** 2 < 1.0
        r[in_hole] += 40.0 + 100.0 * rng.random(in_hole.sum())
        for col, v in zip(cols, (np.full(theta.size, s), r, theta, np.full(theta.size, k)), strict=True):
            col.append(v)
    k = len(sig)
    line = Centreline(
        sig, np.column_stack([np.zeros(k), np.zeros(k), sig]), np.tile([0.0, 0.0, 1.0], (k, 1)),
        np.tile([1.0, 0.0, 0.0], (k, 1)), np.tile([0.0, 1.0, 0.0], (k, 1)), np.full(k, RADIUS), [],
    )
    sigma, rho, th, frame = (np.concatenate(c) for c in cols)
    return line, (sigma, rho, th, frame.astype(int))


def _ring_fits(monkeypatch: pytest.MonkeyPatch, n: int) -> tuple[int, int, int]:
    """(laterals found, rings, per-ring plane fits made) of :func:`find_features` on ``n`` copies."""
    calls = [0]
    real = feature_rings.robust_sine_fit

    def counted(*args, **kwargs):
        calls[0] += 1
        return real(*args, **kwargs)

    # Both the per-ring planes and a ring's axial position at an angle fit through it.
    monkeypatch.setattr(features, "robust_sine_fit", counted, raising=False)
    monkeypatch.setattr(openings, "robust_sine_fit", counted)
    line, (sigma, rho, theta, frame) = _copies(n)
    found = find_features(FeatureConfig(), line, sigma, rho, theta, frame, RADIUS)
    laterals = [f for f in found.features if f.kind == "lateral"]
    return len(laterals), len(line.arc_mm), calls[0]


def test_feature_search_fits_each_ring_a_bounded_number_of_times(monkeypatch: pytest.MonkeyPatch) -> None:
    """One tee and three copies of it: three laterals found, each where its copy put it,
    and the plane fits per ring do not grow with the number of holes (they grew 3x when
    every hole fitted every ring of the run)."""
    one = _ring_fits(monkeypatch, 1)
    three = _ring_fits(monkeypatch, 3)
    assert one[0] == 1 and three[0] == 3, (one, three)
    per_ring_one, per_ring_three = one[2] / one[1], three[2] / three[1]
    assert per_ring_three <= 1.1 * per_ring_one + 0.05, (one, three)
    assert per_ring_one < 1.5, one  # about one fit per ring, plus the holes' own chords
