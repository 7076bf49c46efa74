"""Robust cylinder fitting (the paper's Table I inner diameter, Sec. VII).

A cylinder is an axis line (a point on it and a unit direction) and a radius. The
fit minimises the robust sum of ``distance_to_axis(p) - radius`` over the wall
points with SciPy's ``least_squares`` (soft-L1 loss), so defects and stray points
weigh little, then a Cauchy loss at three times the measured noise, whose influence
fades for far points. Parameters: two small rotations of the initial axis, two offsets of
the axis point in the plane orthogonal to it, and the radius.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.optimize import least_squares

from omnipipe.analysis._kernels import cylinder_jacobian, cylinder_residuals
from omnipipe.errors import ShapeError


@dataclass(frozen=True)
class Cylinder:
    """A fitted cylinder (world frame, mm).

    Attributes:
        point: (3,) a point on the axis (the one nearest the points' centroid).
        axis: (3,) unit direction of the axis.
        radius_mm: fitted radius.
        residuals_mm: (N,) signed distance-to-axis minus radius of every input point.
        scale_mm: robust spread of the residuals (1.4826 x median absolute residual).
    """

    point: np.ndarray
    axis: np.ndarray
    radius_mm: float
    residuals_mm: np.ndarray
    scale_mm: float

    @property
    def diameter_mm(self) -> float:
        return 2.0 * self.radius_mm


def basis(axis: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Two unit vectors orthogonal to ``axis`` and to each other."""
    helper = np.array([1.0, 0.0, 0.0]) if abs(axis[0]) < 0.9 else np.array([0.0, 1.0, 0.0])
    e1 = np.cross(axis, helper)
    e1 /= np.linalg.norm(e1)
    return e1, np.cross(axis, e1)


def circle_fit_2d(xy: np.ndarray) -> tuple[np.ndarray, float]:
    """Algebraic (Kasa) circle fit: centre (2,) and radius of 2-D points (N, 2)."""
    A = np.column_stack([2 * xy, np.ones(len(xy))])
    b = np.sum(xy**2, axis=1)
    sol, *_ = np.linalg.lstsq(A, b, rcond=None)
    centre = sol[:2]
    return centre, float(np.sqrt(max(sol[2] + centre @ centre, 0.0)))


class CylinderResidual:
    """Signed distance to the axis minus the radius of every point, and its Jacobian, for
    parameters x = (two tilts of ``axis0`` along its basis e1, e2; the axis point's offsets
    from ``point0`` along e1, e2; the radius) (mm, radians' tangents).

    With d = |q|, q = rel - (rel.n) n, rel = p - point, n = m / |m|,
    m = axis0 + x0 e1 + x1 e2: dd/dpoint = -q / d (q is orthogonal to n) and
    dd/dm = -(rel.n) q / (d |m|).
    """

    def __init__(self, points: np.ndarray, axis0: np.ndarray, point0: np.ndarray) -> None:
        self.points, self.axis0, self.point0 = np.ascontiguousarray(points, np.float64), axis0, point0
        self.e1, self.e2 = basis(axis0)

    def unpack(self, x: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(axis point (3,), unit axis (3,)) of parameters ``x``."""
        axis = self.axis0 + x[0] * self.e1 + x[1] * self.e2
        axis = axis / np.linalg.norm(axis)
        return self.point0 + x[2] * self.e1 + x[3] * self.e2, axis

    def __call__(self, x: np.ndarray) -> np.ndarray:
        point, axis = self.unpack(x)
        return cylinder_residuals(self.points, point, axis, float(x[4]))

    def jacobian(self, x: np.ndarray) -> np.ndarray:
        """(N, 5) d residual / d x (compiled: :func:`._kernels.cylinder_jacobian`)."""
        norm_m = float(np.linalg.norm(self.axis0 + x[0] * self.e1 + x[1] * self.e2))
        point, axis = self.unpack(x)
        return cylinder_jacobian(self.points, point, axis, (self.e1, self.e2), norm_m)


def fit_cylinder(
    points: np.ndarray,
    axis_guess: np.ndarray,
    *,
    loss_scale_mm: float = 0.5,
    max_tilt_rad: float = 0.5,
) -> Cylinder:
    """Fit a cylinder to wall points robustly.

    Args:
        points: (N, 3) wall points, N >= 6, mm.
        axis_guess: (3,) rough axis direction (e.g. the rig's z axis or the path direction).
        loss_scale_mm: residual (mm) where the soft-L1 loss turns from quadratic to linear:
            points further than a few of these from the wall (defects, stray light) have
            little weight.
        max_tilt_rad: the fitted axis may turn at most this far from ``axis_guess``.

    Raises:
        ShapeError: too few or malformed points.
    """
    points = np.asarray(points, dtype=float)
    if points.ndim != 2 or points.shape[1] != 3 or len(points) < 6:
        raise ShapeError(f"fit_cylinder: points must be (N>=6, 3), got {points.shape}")
    axis0 = np.asarray(axis_guess, float)
    axis0 = axis0 / np.linalg.norm(axis0)
    e1, e2 = basis(axis0)
    centroid = points.mean(axis=0)
    rel = points - centroid
    centre2, r0 = circle_fit_2d(np.column_stack([rel @ e1, rel @ e2]))
    point0 = centroid + centre2[0] * e1 + centre2[1] * e2

    residual = CylinderResidual(points, axis0, point0)
    jacobian = residual.jacobian
    unpack = residual.unpack

    lim = np.tan(max_tilt_rad)
    x0 = np.array([0.0, 0.0, 0.0, 0.0, r0])
    lower = [-lim, -lim, -np.inf, -np.inf, 0.0]
    upper = [lim, lim, np.inf, np.inf, np.inf]
    # First a plain fit from the algebraic start, then the robust one from there.
    sol = least_squares(residual, x0, jac=jacobian, bounds=(lower, upper), x_scale="jac")
    sol = least_squares(
        residual,
        sol.x,
        jac=jacobian,
        bounds=(lower, upper),
        loss="soft_l1",
        f_scale=loss_scale_mm,
        x_scale="jac",
    )
    # Finally a redescending (Cauchy) loss at the measured noise: far points stop pulling.
    spread = 1.4826 * float(np.median(np.abs(residual(sol.x))))
    sol = least_squares(
        residual,
        sol.x,
        jac=jacobian,
        bounds=(lower, upper),
        loss="cauchy",
        f_scale=float(np.clip(3.0 * spread, 0.02, loss_scale_mm)),
        x_scale="jac",
    )
    point, axis = unpack(sol.x)
    # Report the axis point nearest the centroid, a canonical choice.
    point = point + ((centroid - point) @ axis) * axis
    res = residual(sol.x)
    return Cylinder(point, axis, float(sol.x[4]), res, float(1.4826 * np.median(np.abs(res))))
