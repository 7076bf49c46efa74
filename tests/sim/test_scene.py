"""Pipe geometry of the simulator: centreline, pipe coordinates, defect profiles."""

from __future__ import annotations

import numpy as np
import pytest

from omnipipe.errors import ConfigError
from omnipipe.sim import Centreline, Defect, Pipe
from omnipipe.sim.scene import plateau

BENT = Centreline(
    straight_mm=300.0, bend_radius_mm=600.0, bend_angle_deg=45.0, bend_direction_deg=30.0
)


@pytest.mark.parametrize("centreline", [Centreline(), BENT])
def test_pipe_coordinates_invert_the_parameterisation(centreline: Centreline) -> None:
    pipe = Pipe(160.0, centreline)
    rng = np.random.default_rng(0)
    sigma = rng.uniform(-100.0, 1200.0, 5000)
    theta = rng.uniform(-np.pi, np.pi, 5000)
    rho = rng.uniform(0.0, 90.0, 5000)
    centre, normal, binormal, tangent = pipe.frame_at(sigma)
    # Transported frames stay orthonormal.
    assert np.allclose(np.einsum("ij,ij->i", normal, tangent), 0.0, atol=1e-12)
    assert np.allclose(np.cross(normal, binormal), tangent, atol=1e-12)
    pts = centre + rho[:, None] * (
        np.cos(theta)[:, None] * normal + np.sin(theta)[:, None] * binormal
    )
    s2, r2, t2, *_ = pipe.pipe_coordinates(pts)
    assert np.abs(s2 - sigma).max() < 1e-9
    assert np.abs(r2 - rho).max() < 1e-9
    ok = rho > 1e-6
    assert np.abs(np.angle(np.exp(1j * (t2[ok] - theta[ok])))).max() < 1e-9


def test_bend_geometry() -> None:
    pipe = Pipe(160.0, BENT)
    end = 300.0 + 600.0 * np.radians(45.0)
    c, _, _, t = pipe.frame_at(np.array([0.0, 300.0, end, end + 100.0]))
    assert np.allclose(t[0], [0, 0, 1]) and np.allclose(t[1], [0, 0, 1])
    # After the bend the axis turned by 45 deg towards the bend direction (30 deg from x).
    assert np.degrees(np.arccos(t[2] @ [0, 0, 1])) == pytest.approx(45.0)
    assert np.allclose(
        t[2][:2] / np.linalg.norm(t[2][:2]), [np.cos(np.radians(30)), np.sin(np.radians(30))]
    )
    assert np.linalg.norm(c[3] - c[2]) == pytest.approx(100.0)


def test_defect_half_height_extents_are_the_nominal_sizes() -> None:
    x = np.linspace(-10, 10, 200001)
    p = plateau(x, full_width=5.0, ramp=5.0)
    above = x[p >= 0.5]
    assert above.max() - above.min() == pytest.approx(5.0, abs=1e-3)
    bulge = Defect("bulge", 5.0, 5.0, 100.0, axial_start_mm=200.0, angle_deg=90.0)
    pipe = Pipe(202.0, defects=[bulge])
    sigma = np.linspace(150, 350, 40001)
    r = pipe.wall_radius(sigma, np.full_like(sigma, np.pi / 2))
    assert r.min() == pytest.approx(101.0 - 5.0)
    half = sigma[r <= 101.0 - 2.5]
    assert half.min() == pytest.approx(200.0, abs=0.01) and half.max() == pytest.approx(
        300.0, abs=0.01
    )
    arc = np.linspace(-10, 10, 20001)
    r = pipe.wall_radius(np.full_like(arc, 250.0), np.pi / 2 + arc / 101.0)
    half = arc[r <= 101.0 - 2.5]
    assert half.max() - half.min() == pytest.approx(5.0, abs=0.01)


def test_invalid_scene_values_are_named() -> None:
    with pytest.raises(ConfigError, match=r"defect\.kind"):
        Defect("crack", 1.0, 1.0, 1.0, 0.0, 0.0)
    with pytest.raises(ConfigError, match=r"defect\.height_mm"):
        Defect("dent", 0.0, 1.0, 1.0, 0.0, 0.0)
    with pytest.raises(ConfigError, match="bend_radius_mm"):
        Pipe(200.0, Centreline(100.0, bend_radius_mm=50.0, bend_angle_deg=30.0))
