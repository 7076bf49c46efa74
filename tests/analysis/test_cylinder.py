"""The cylinder fit's analytic Jacobian equals central differences of its residuals."""

from __future__ import annotations

import numpy as np

from omnipipe.analysis.cylinder import CylinderResidual, fit_cylinder


def test_cylinder_jacobian_equals_central_differences() -> None:
    rng = np.random.default_rng(5)
    t = rng.uniform(0.0, 2 * np.pi, 500)
    pts = np.column_stack([80 * np.cos(t), 80 * np.sin(t), rng.uniform(-50, 50, 500)])
    residual = CylinderResidual(pts, np.array([0.1, 0.0, 1.0]) / np.hypot(0.1, 1.0), np.array([1.0, 2.0, 0.0]))
    for x in (np.array([0.05, -0.03, 0.5, -0.7, 79.0]), np.array([-0.3, 0.2, 4.0, 3.0, 60.0])):
        jac = residual.jacobian(x)
        numeric = np.empty_like(jac)
        for k in range(5):
            step = np.zeros(5)
            step[k] = 1e-6
            numeric[:, k] = (residual(x + step) - residual(x - step)) / 2e-6
        np.testing.assert_allclose(jac, numeric, rtol=0, atol=1e-6)


def test_tilted_cylinder_is_recovered() -> None:
    rng = np.random.default_rng(6)
    axis = np.array([0.2, -0.1, 1.0]) / np.linalg.norm([0.2, -0.1, 1.0])
    e1 = np.cross(axis, [1.0, 0.0, 0.0])
    e1 /= np.linalg.norm(e1)
    e2 = np.cross(axis, e1)
    t, s = rng.uniform(0, 2 * np.pi, 3000), rng.uniform(-60, 60, 3000)
    centre = np.array([3.0, -2.0, 10.0])
    pts = centre + 75.0 * (np.outer(np.cos(t), e1) + np.outer(np.sin(t), e2)) + np.outer(s, axis)
    pts += rng.normal(0, 0.1, pts.shape)
    cyl = fit_cylinder(pts, [0.0, 0.0, 1.0])
    assert abs(cyl.radius_mm - 75.0) < 0.02
    assert abs(abs(cyl.axis @ axis) - 1.0) < 1e-6
    off = (cyl.point - centre) - ((cyl.point - centre) @ axis) * axis
    assert np.linalg.norm(off) < 0.02
