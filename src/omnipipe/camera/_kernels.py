"""Compiled projection kernels of the camera models (numba).

A model that offers a compiled projection (:meth:`CameraModel.compiled_projection`)
names its kernel here by ``kind`` and passes its parameters as one float64 array;
compiled callers (:meth:`OmniCamera.project`, the Eq. 17 candidates of
:mod:`omnipipe.sfm.laser_scale`) call :func:`project_point`, which dispatches on
``kind``. Each kernel does the same floating-point operations in the same order as its
NumPy reference formulation (in the tests), so their pixels and validity are
bit-identical.
"""

from __future__ import annotations

import math

import numba
import numpy as np

HYPERBOLOID = 0
"""``kind`` of :func:`hyperboloid_point`; params (a, b, c, f, cx, cy, width, height,
radius_min, radius_max)."""


@numba.njit(cache=True, error_model="numpy", inline="always")
def hyperboloid_point(
    x, y, z, a, b, c, f, cx, cy, width, height, radius_min, radius_max
):  # pragma: no cover - compiled
    """(col, row, valid) of one rig-frame point through the hyperboloid mirror (Eq. 1-3
    inverted, :class:`~omnipipe.camera.hyperboloid.OmniCamera`); NaN pixels where the
    mirror cannot see it.

    The operations of the NumPy formulation: norm ((x^2 + y^2) + z^2),
    t = a^2 / (b - c d_z), u = ((f t) d_x) / m_z, pixel validity as
    :meth:`CameraModel.is_valid_pixel`. The radius is sqrt(du^2 + dv^2), within a few
    ulp of ``hypot``; the (slow) ``hypot`` itself is taken only when that is within
    1e-9 of a valid-annulus radius, where the rounding could decide.
    """
    aa = a * a
    c2 = 2.0 * c
    b_over_c = b / c
    col_max = width - 0.5
    row_max = height - 0.5
    norm = math.sqrt(x * x + y * y + z * z)
    dx, dy, dz = x / norm, y / norm, z / norm
    # Mirror point t d: root of (t dxy)^2/a^2 - (t dz + c)^2/b^2 = -1 on the
    # mirror's sheet; valid for d_z < b/c (above it the ray misses the mirror).
    t = aa / (b - c * dz)
    mz = t * dz + c2  # mirror point seen from the lens centre
    if norm > 0 and dz < b_over_c and mz > 0:
        col = f * t * dx / mz + cx
        row = f * t * dy / mz + cy
        inside = col >= -0.5 and col <= col_max and row >= -0.5 and row <= row_max
        if inside:
            du, dv = col - cx, row - cy
            r = math.sqrt(du * du + dv * dv)  # within a few ulp of hypot
            if (
                abs(r - radius_min) <= 1e-9 * (1.0 + radius_min)
                or abs(r - radius_max) <= 1e-9 * (1.0 + radius_max)
            ):
                r = math.hypot(du, dv)  # is_valid_pixel's value where it decides
            inside = r >= radius_min and r <= radius_max
        return col, row, inside
    return np.nan, np.nan, False


@numba.njit(cache=True, error_model="numpy", inline="always")
def project_point(kind, params, x, y, z):  # pragma: no cover - compiled
    """(col, row, valid) of one rig-frame point by the kernel ``kind`` with ``params``
    (:class:`~omnipipe.camera.base.CompiledProjection`); (NaN, NaN, False) for an
    unknown kind."""
    if kind == HYPERBOLOID:
        return hyperboloid_point(
            x, y, z, params[0], params[1], params[2], params[3], params[4], params[5],
            params[6], params[7], params[8], params[9],
        )
    return np.nan, np.nan, False


@numba.njit(cache=True, error_model="numpy", inline="always")
def project_block(kind, params, x, y, z, shift, n, col, row, valid):  # pragma: no cover - compiled
    """:func:`project_point` of the ``n`` points (``x[i] + shift[0]``, ``y[i] + shift[1]``,
    ``z[i] + shift[2]``) into ``col``, ``row`` (NaN where not seen) and ``valid``, bit for
    bit (``shift``: a tuple of 3 floats).

    For the hyperboloid, the arithmetic of :func:`hyperboloid_point` in one loop without
    branches (every step computed, validity as a mask), which the compiler vectorises:
    a block of points costs a fifth of point-by-point projection. The rare points whose
    radius lies within 1e-9 of a valid-annulus radius (where ``hypot`` decides) are then
    projected again by :func:`hyperboloid_point` (with the rest of their block). Other
    kinds: point by point.
    """
    if kind != HYPERBOLOID:
        for i in range(n):
            col[i], row[i], valid[i] = project_point(
                kind, params, x[i] + shift[0], y[i] + shift[1], z[i] + shift[2]
            )
        return
    a, b, c, f, cx, cy = params[0], params[1], params[2], params[3], params[4], params[5]
    width, height, radius_min, radius_max = params[6], params[7], params[8], params[9]
    aa = a * a
    c2 = 2.0 * c
    b_over_c = b / c
    col_max = width - 0.5
    row_max = height - 0.5
    tol_min = 1e-9 * (1.0 + radius_min)
    tol_max = 1e-9 * (1.0 + radius_max)
    s0, s1, s2 = shift[0], shift[1], shift[2]
    n_near = 0
    for i in range(n):
        xi, yi, zi = x[i] + s0, y[i] + s1, z[i] + s2
        norm = math.sqrt(xi * xi + yi * yi + zi * zi)
        dx, dy, dz = xi / norm, yi / norm, zi / norm
        t = aa / (b - c * dz)
        mz = t * dz + c2
        ci = f * t * dx / mz + cx
        ri = f * t * dy / mz + cy
        du, dv = ci - cx, ri - cy
        r = math.sqrt(du * du + dv * dv)
        seen = (norm > 0) & (dz < b_over_c) & (mz > 0)
        inside = seen & (ci >= -0.5) & (ci <= col_max) & (ri >= -0.5) & (ri <= row_max)
        near = inside & ((abs(r - radius_min) <= tol_min) | (abs(r - radius_max) <= tol_max))
        n_near += near
        valid[i] = inside & (r >= radius_min) & (r <= radius_max)
        col[i] = ci if seen else np.nan
        row[i] = ri if seen else np.nan
    if n_near:  # rare: the whole block again, point by point
        for i in range(n):
            col[i], row[i], valid[i] = hyperboloid_point(
                x[i] + s0, y[i] + s1, z[i] + s2, a, b, c, f, cx, cy, width, height, radius_min, radius_max
            )


@numba.njit(cache=True, error_model="numpy")
def project_points(pts, kind, params, pixels, valid):  # pragma: no cover - compiled
    """(N, 3) points into (N, 2) ``pixels`` and (N,) ``valid``: :func:`project_point` of
    each, bit for bit, 256 points at a time through :func:`project_block`."""
    block = 256
    x, y, z = np.empty(block), np.empty(block), np.empty(block)
    col, row = np.empty(block), np.empty(block)
    ok = np.empty(block, np.bool_)
    for lo in range(0, pts.shape[0], block):
        m = min(block, pts.shape[0] - lo)
        for i in range(m):
            x[i], y[i], z[i] = pts[lo + i, 0], pts[lo + i, 1], pts[lo + i, 2]
        project_block(kind, params, x, y, z, (0.0, 0.0, 0.0), m, col, row, ok)
        for i in range(m):
            pixels[lo + i, 0] = col[i]
            pixels[lo + i, 1] = row[i]
            valid[lo + i] = ok[i]
