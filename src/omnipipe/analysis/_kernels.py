"""The defect sizing's bump model and its analytic Jacobian, compiled.

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
