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


def _residuals_reference(points: np.ndarray, point: np.ndarray, axis: np.ndarray, radius: float) -> np.ndarray:
    """NumPy reference of :func:`omnipipe.analysis._kernels.cylinder_residuals`."""
    rel = points - point
    perp = rel - (rel @ axis)[:, None] * axis
    return np.sqrt(np.einsum("ij,ij->i", perp, perp)) - radius


def _jacobian_reference(residual: CylinderResidual, x: np.ndarray) -> np.ndarray:
    """NumPy reference of :meth:`CylinderResidual.jacobian` (the compiled kernel's)."""
    norm_m = float(np.linalg.norm(residual.axis0 + x[0] * residual.e1 + x[1] * residual.e2))
    point, axis = residual.unpack(x)
    rel = residual.points - point
    along = rel @ axis
    q = rel - along[:, None] * axis
    d = np.maximum(np.sqrt(np.einsum("ij,ij->i", q, q)), 1e-12)
    q1, q2 = q @ residual.e1 / d, q @ residual.e2 / d
    tilt = -along / norm_m
    return np.column_stack([tilt * q1, tilt * q2, -q1, -q2, -np.ones(len(residual.points))])


def test_compiled_cylinder_residuals_and_jacobian_equal_the_numpy_reference() -> None:
    rng = np.random.default_rng(7)
    pts = rng.normal(0, 60.0, (400, 3))
    pts[:3] = [[1.0, 2.0, 5.0], [1.0, 2.0, -5.0], [1.0, 2.0, 0.0]]  # on the axis: d clipped
    axis0 = np.array([0.0, 0.0, 1.0])
    residual = CylinderResidual(pts, axis0, np.array([1.0, 2.0, 0.0]))
    for x in (np.zeros(5), np.array([0.05, -0.03, 0.5, -0.7, 79.0]), np.array([-0.3, 0.2, 4.0, 3.0, 60.0])):
        point, axis = residual.unpack(x)
        np.testing.assert_allclose(residual(x), _residuals_reference(pts, point, axis, x[4]), rtol=1e-12, atol=1e-9)
        np.testing.assert_allclose(residual.jacobian(x), _jacobian_reference(residual, x), rtol=1e-12, atol=1e-12)
