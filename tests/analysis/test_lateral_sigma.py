"""A lateral's axial sigma covers its true centre where the run's coordinate is tilted
to the pipe (the rings, square to the pipe, lean in it), and adds nothing where the
rings are square to the coordinate."""

from __future__ import annotations

import math

import numpy as np
import pytest

from omnipipe.analysis.centreline import Centreline
from omnipipe.analysis.feature_types import Lateral
from omnipipe.analysis.features import FeatureConfig, find_features

R = 150.0
HOLE_DEG = 236.0


def _oblique_lateral(seed: int, tilt_deg: float, branch_deg: float, dia: float = 70.0):
    """Rings 5 mm apart (jittered) over -200..200 mm of a 300 mm pipe, square to it, 720
    samples each, noise 0.3 mm; a round branch of ``dia`` mm at ``branch_deg`` to the
    axis enters at 0 mm, HOLE_DEG: its hole d / sin(branch) long along the axis, its
    samples 20-80 mm out. Read in a coordinate whose axis is ``tilt_deg`` off the
    pipe's towards the hole's clock (the centreline's tangent off): each sample's axial
    position moves by R tan(tilt) cos(theta - hole), the hole's by R tan(tilt)."""
    rng = np.random.default_rng(seed)
    centres = np.arange(-200.0, 201.0, 5.0) + rng.uniform(-0.5, 0.5, 81)
    theta = np.linspace(-np.pi, np.pi, 720, endpoint=False)
    u = ((theta - math.radians(HOLE_DEG) + np.pi) % (2 * np.pi) - np.pi) * R
    half_u, half_z = R * math.asin(0.5 * dia / R), 0.5 * dia / math.sin(math.radians(branch_deg))
    lean = R * math.tan(math.radians(tilt_deg)) * np.cos(theta - math.radians(HOLE_DEG))
    sig, rho, th, frame = [], [], [], []
    for k, c in enumerate(centres):
        s = c + rng.normal(0.0, 0.1, theta.size)
        r = R + rng.normal(0.0, 0.3, theta.size)
        inside = (u / half_u) ** 2 + (s / half_z) ** 2 < 1.0
        r[inside] += rng.uniform(20.0, 80.0, int(inside.sum()))
        sig.append(s + lean)
        rho.append(r)
        th.append(theta)
        frame.append(np.full(theta.size, k))
    return Centreline.straight(centres, R), *(np.concatenate(a) for a in (sig, rho, th, frame))


def _lateral(seed: int, tilt_deg: float, branch_deg: float) -> Lateral:
    line, sigma, rho, theta, frame = _oblique_lateral(seed, tilt_deg, branch_deg)
    found = find_features(FeatureConfig(), line, sigma, rho, theta, frame, R)
    lats = [f for f in found.features if isinstance(f, Lateral)]
    assert len(lats) == 1, found.features
    return lats[0]


@pytest.mark.parametrize(("seed", "branch_deg"), [(11, 90.0), (12, 60.0), (13, 125.0)])
def test_oblique_laterals_centre_is_covered_where_the_coordinate_is_tilted(seed: int, branch_deg: float) -> None:
    """The coordinate 3 deg off the pipe's axis: the hole reads 7.9 mm off its true
    centre (0 mm), more than 3 x the rings' spacing term (5 mm rings: ~1 mm); its
    rings' footprint at the hole's angle states it (within 3 sigma). Square: the
    centre within 3 mm and its sigma that of the rings' spacing (no footprint term)."""
    tilted = _lateral(seed, 3.0, branch_deg)
    shift = R * math.tan(math.radians(3.0))
    assert abs(tilted.axial_mm - shift) < 3.0, tilted  # the reading moves with the coordinate
    assert abs(tilted.axial_mm) <= 3.0 * tilted.axial_sigma_mm, tilted
    square = _lateral(seed, 0.0, branch_deg)
    assert abs(square.axial_mm) < 3.0, square
    assert square.axial_sigma_mm < 2.0 and tilted.axial_sigma_mm > 2.0 * square.axial_sigma_mm, (square, tilted)
