"""The analysis' compiled kernels: the defect sizing's bump model and its analytic
Jacobian, and the cylinder fit's residuals and Jacobian.

Cylinder (:class:`omnipipe.analysis.cylinder.CylinderResidual`): :func:`cylinder_residuals`
and :func:`cylinder_jacobian` evaluate the points' distance to the axis minus the radius
and its derivatives in one pass over the points each (the NumPy reference is in
tests/analysis/test_cylinder.py): the centreline's window fits spend most of their time
there.

Bump:

:func:`omnipipe.analysis.sizing.seen_bump_model` is the NumPy reference (the tests
compare the two); the least-squares fits of :mod:`omnipipe.analysis.sizing` call
:func:`seen_bump_with_jacobian`, which evaluates the model and its derivatives with
respect to all eight parameters in one pass over the samples instead of SciPy's nine
model evaluations per finite-difference Jacobian.

The raised-cosine plateau ``P(x; F, f F) = (1 + cos(pi t)) / 2`` with
``t = clip((|x| - (F - f F) / 2) / (f F), 0, 1)`` is continuously differentiable (its
derivative ``-pi sin(pi t) / 2 * dt`` vanishes where ``t`` is clipped), so the analytic
Jacobian is exact everywhere:

    dt/dx = sign(x) / (f F),  dt/dF = -|x| / (f F^2),  dt/df = (F / 2 - |x|) / (f^2 F).
"""

from __future__ import annotations

import math

import numba
import numpy as np


@numba.njit(cache=True)
def _plateau_terms(
    x: float, full: float, frac: float, nodes: np.ndarray, weights: np.ndarray, blur: float
) -> tuple[float, float, float, float]:
    """Blurred plateau at offset ``x`` and its derivatives (d/dx, d/dF, d/df): the
    Gauss-Hermite nodes summed in order, as :func:`..sizing._blurred_plateau` does."""
    ramp = frac * full
    inv_ramp = 1.0 / max(ramp, 1e-9)
    inner = 0.5 * (full - ramp)
    value = 0.0
    d_x = 0.0
    d_full = 0.0
    d_frac = 0.0
    for k in range(len(nodes)):
        xk = x + blur * nodes[k]
        ax = abs(xk)
        t = (ax - inner) * inv_ramp
        if t <= 0.0:
            value += weights[k]  # the plateau: cos(0) = 1, no slope
        elif t < 1.0:
            value += weights[k] * (0.5 * (1.0 + math.cos(math.pi * t)))
            slope = -0.5 * math.pi * math.sin(math.pi * t) * weights[k]
            sign = 1.0 if xk >= 0.0 else -1.0
            d_x += slope * sign * inv_ramp
            d_full += slope * (-ax / (frac * full * full))
            d_frac += slope * (0.5 * full - ax) / (frac * frac * full)
    return value, d_x, d_full, d_frac


@numba.njit(cache=True)
def _bump_kernel(
    params: np.ndarray,
    u: np.ndarray,
    z: np.ndarray,
    nodes_u: np.ndarray,
    weights_u: np.ndarray,
    blur_u: float,
    nodes_z: np.ndarray,
    weights_z: np.ndarray,
    blur_z: float,
    model: np.ndarray,
    jac: np.ndarray,
) -> None:
    h, u0, z0, w, length, fu, fz, b = (
        params[0], params[1], params[2], params[3], params[4], params[5], params[6], params[7]
    )
    for i in range(len(u)):
        pz, pz_x, pz_l, pz_f = _plateau_terms(z[i] - z0, length, fz, nodes_z, weights_z, blur_z)
        if pz == 0.0 and pz_x == 0.0 and pz_l == 0.0 and pz_f == 0.0:
            # Beyond the bump's axial flanks: the wall only (the terms are all 0 exactly).
            model[i] = b
            jac[i, :7] = 0.0
            jac[i, 7] = 1.0
            continue
        pu, pu_x, pu_w, pu_f = _plateau_terms(u[i] - u0, w, fu, nodes_u, weights_u, blur_u)
        model[i] = b + h * pu * pz
        jac[i, 0] = pu * pz
        jac[i, 1] = -h * pu_x * pz
        jac[i, 2] = -h * pu * pz_x
        jac[i, 3] = h * pu_w * pz
        jac[i, 4] = h * pu * pz_l
        jac[i, 5] = h * pu_f * pz
        jac[i, 6] = h * pu * pz_f
        jac[i, 7] = 1.0


# Gauss-Hermite nodes and weights of a unit Gaussian (7 points), as in sizing.py.
GH_X, GH_W = np.polynomial.hermite_e.hermegauss(7)
GH_W = GH_W / GH_W.sum()
_NO_BLUR = (np.zeros(1), np.ones(1))


def seen_bump_with_jacobian(
    params: np.ndarray, u: np.ndarray, z: np.ndarray, blur_u_mm: float, blur_z_mm: float
) -> tuple[np.ndarray, np.ndarray]:
    """(N,) :func:`omnipipe.analysis.sizing.seen_bump_model` at (u, z) and its (N, 8)
    Jacobian with respect to [h, u0, z0, W, L, f_u, f_z, b] (mm per parameter unit).

    Args:
        params: (8,) [h, u0, z0, W, L, f_u, f_z, b] (mm; f_u, f_z fractions).
        u, z: (N,) sample positions around and along the pipe (mm).
        blur_u_mm, blur_z_mm: Gaussian sigmas of the light section's smoothing (0: none).
    """
    u = np.ascontiguousarray(u, np.float64)
    z = np.ascontiguousarray(z, np.float64)
    nodes_u, weights_u = (GH_X, GH_W) if blur_u_mm > 0 else _NO_BLUR
    nodes_z, weights_z = (GH_X, GH_W) if blur_z_mm > 0 else _NO_BLUR
    model = np.empty(len(u))
    jac = np.empty((len(u), 8))
    _bump_kernel(
        np.ascontiguousarray(params, np.float64), u, z,
        nodes_u, weights_u, float(blur_u_mm) if blur_u_mm > 0 else 0.0,
        nodes_z, weights_z, float(blur_z_mm) if blur_z_mm > 0 else 0.0,
        model, jac,
    )
    return model, jac


@numba.njit(cache=True)
def _cylinder_residuals(points: np.ndarray, point: np.ndarray, axis: np.ndarray, radius: float, out: np.ndarray) -> None:
    for i in range(points.shape[0]):
        r0, r1, r2 = points[i, 0] - point[0], points[i, 1] - point[1], points[i, 2] - point[2]
        along = r0 * axis[0] + r1 * axis[1] + r2 * axis[2]
        q0, q1, q2 = r0 - along * axis[0], r1 - along * axis[1], r2 - along * axis[2]
        out[i] = math.sqrt(q0 * q0 + q1 * q1 + q2 * q2) - radius


@numba.njit(cache=True)
def _cylinder_jacobian(
    points: np.ndarray, point: np.ndarray, axis: np.ndarray, e1: np.ndarray, e2: np.ndarray, norm_m: float,
    jac: np.ndarray,
) -> None:
    for i in range(points.shape[0]):
        r0, r1, r2 = points[i, 0] - point[0], points[i, 1] - point[1], points[i, 2] - point[2]
        along = r0 * axis[0] + r1 * axis[1] + r2 * axis[2]
        q0, q1, q2 = r0 - along * axis[0], r1 - along * axis[1], r2 - along * axis[2]
        d = max(math.sqrt(q0 * q0 + q1 * q1 + q2 * q2), 1e-12)
        c1 = (q0 * e1[0] + q1 * e1[1] + q2 * e1[2]) / d
        c2 = (q0 * e2[0] + q1 * e2[1] + q2 * e2[2]) / d
        tilt = -along / norm_m
        jac[i, 0] = tilt * c1
        jac[i, 1] = tilt * c2
        jac[i, 2] = -c1
        jac[i, 3] = -c2
        jac[i, 4] = -1.0


def cylinder_residuals(points: np.ndarray, point: np.ndarray, axis: np.ndarray, radius: float) -> np.ndarray:
    """(N,) distance (mm) of ``points`` (N, 3; C-contiguous float64) from the line through
    ``point`` (3,) along the unit ``axis`` (3,), minus ``radius`` (mm)."""
    out = np.empty(points.shape[0])
    _cylinder_residuals(points, np.ascontiguousarray(point, np.float64), np.ascontiguousarray(axis, np.float64), float(radius), out)
    return out


def cylinder_jacobian(
    points: np.ndarray, point: np.ndarray, axis: np.ndarray, basis: tuple[np.ndarray, np.ndarray], norm_m: float
) -> np.ndarray:
    """(N, 5) derivatives of :func:`cylinder_residuals` with respect to the cylinder's
    parameters (two tilts of the axis along ``basis`` (e1, e2), the axis point's offsets
    along them, the radius; :class:`omnipipe.analysis.cylinder.CylinderResidual`), at the
    axis ``point`` and unit ``axis`` they give; ``norm_m``: the length of the untilted
    axis plus the tilts (the unit axis times it)."""
    jac = np.empty((points.shape[0], 5))
    e1, e2 = (np.ascontiguousarray(e, np.float64) for e in basis)
    _cylinder_jacobian(
        points, np.ascontiguousarray(point, np.float64), np.ascontiguousarray(axis, np.float64), e1, e2,
        float(norm_m), jac,
    )
    return jac
