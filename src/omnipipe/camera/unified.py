"""Mei's unified omni-directional camera model (OpenCV ``omnidir``, Kalibr ``omni``).

Model frame (Mei / OpenCV / Kalibr): z is the axis of the sphere, the image centre
sees +z, x along image columns, y along rows. A direction X is normalised to the unit
sphere Xs, shifted by xi along z and projected: m = (xs, ys) / (zs + xi); the
radial-tangential distortion (k1, k2, p1, p2, OpenCV's order) moves m to md; then
col = fx mdx + skew mdy + cx, row = fy mdy + cy.

Rig frame (DATA_CONTRACT.md section 2): the image centre sees -z, x along columns,
y along rows, so ``rig = diag(1, 1, -1) model``: a reflection (a single mirror
reverses handedness; the calibrated poses stay proper rotations in the model frame).
A hyperboloid mirror with the lens at its second focus is exactly this model with no
distortion (Geyer-Daniilidis); distortion absorbs a slightly misplaced camera.
"""

from __future__ import annotations

import numpy as np

from omnipipe.camera.base import CameraModel, as_points
from omnipipe.rig import CameraIntrinsics, UnifiedParams

_UNDISTORT_ITERATIONS = 20


def distort(
    mx: np.ndarray, my: np.ndarray, k: tuple[float, float, float, float]
) -> tuple[np.ndarray, np.ndarray]:
    """Radial-tangential distortion (OpenCV order k1, k2, p1, p2) of normalised points."""
    k1, k2, p1, p2 = k
    r2 = mx * mx + my * my
    radial = 1.0 + k1 * r2 + k2 * r2 * r2
    dx = mx * radial + 2.0 * p1 * mx * my + p2 * (r2 + 2.0 * mx * mx)
    dy = my * radial + p1 * (r2 + 2.0 * my * my) + 2.0 * p2 * mx * my
    return dx, dy


def distort_jacobian(
    mx: np.ndarray, my: np.ndarray, k: tuple[float, float, float, float]
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """d(dx, dy) / d(mx, my) of :func:`distort`: (j11, j12, j21, j22), each (N,)."""
    k1, k2, p1, p2 = k
    r2 = mx * mx + my * my
    radial = 1.0 + k1 * r2 + k2 * r2 * r2
    dr = 2.0 * (k1 + 2.0 * k2 * r2)  # d radial / d(m) = dr * m
    j11 = radial + mx * mx * dr + 2.0 * p1 * my + 6.0 * p2 * mx
    j12 = mx * my * dr + 2.0 * p1 * mx + 2.0 * p2 * my
    j21 = my * mx * dr + 2.0 * p1 * mx + 2.0 * p2 * my
    j22 = radial + my * my * dr + 6.0 * p1 * my + 2.0 * p2 * mx
    return j11, j12, j21, j22


def undistort(
    dx: np.ndarray, dy: np.ndarray, k: tuple[float, float, float, float]
) -> tuple[np.ndarray, np.ndarray]:
    """Inverse of :func:`distort` by Newton's method (exact to ~1e-12 for sane distortion)."""
    mx, my = dx.copy(), dy.copy()
    if not any(k):
        return mx, my
    for _ in range(_UNDISTORT_ITERATIONS):
        fx, fy = distort(mx, my, k)
        ex, ey = fx - dx, fy - dy
        j11, j12, j21, j22 = distort_jacobian(mx, my, k)
        det = j11 * j22 - j12 * j21
        with np.errstate(invalid="ignore", divide="ignore"):
            mx = mx - (j22 * ex - j12 * ey) / det
            my = my - (-j21 * ex + j11 * ey) / det
    return mx, my


def unified_project(
    dirs_model: np.ndarray, xi: float, fx: float, fy: float, cx: float, cy: float,
    skew: float, k: tuple[float, float, float, float],
) -> tuple[np.ndarray, np.ndarray]:
    """Pixels of (N, 3) directions in the MODEL frame; returns ((N, 2) px, (N,) seen)."""
    norm = np.linalg.norm(dirs_model, axis=1)
    with np.errstate(invalid="ignore", divide="ignore"):
        xs = dirs_model / norm[:, None]
        den = xs[:, 2] + xi
        mx = xs[:, 0] / den
        my = xs[:, 1] / den
        dx, dy = distort(mx, my, k)
    w = xi if xi <= 1.0 else 1.0 / xi
    seen = (norm > 0) & (xs[:, 2] > -w) & (den > 0)
    px = np.stack([fx * dx + skew * dy + cx, fy * dy + cy], axis=1)
    px[~seen] = np.nan
    return px, seen


class UnifiedCamera(CameraModel):
    """Mei's unified model behind the rig-frame ``project`` / ``unproject`` interface.

    Args:
        intrinsics: image size, principal point (cx, cy) and valid radii (px);
            ``radius_max`` None: the largest circle about (cx, cy) inside the image.
        params: xi, fx, fy, skew (px) and the distortion k1, k2, p1, p2.
    """

    model_name = "unified"

    def __init__(self, intrinsics: CameraIntrinsics, params: UnifiedParams) -> None:
        self.intrinsics = intrinsics
        self.params = params
        self.xi = float(params.xi)
        self.fx = float(params.fx)
        self.fy = float(params.fy)
        self.skew = float(params.skew)
        self.k = (float(params.k1), float(params.k2), float(params.p1), float(params.p2))
        self._set_image(intrinsics)

    def unproject(self, pixels: np.ndarray) -> np.ndarray:
        """Unit rays in the rig frame of (N, 2) pixels (col, row); NaN rows where none."""
        px = as_points(pixels, 2, "pixels")
        dy = (px[:, 1] - self.cy) / self.fy
        dx = (px[:, 0] - self.cx - self.skew * dy) / self.fx
        mx, my = undistort(dx, dy, self.k)
        xi = self.xi
        r2 = mx * mx + my * my
        disc = 1.0 + (1.0 - xi * xi) * r2
        with np.errstate(invalid="ignore", divide="ignore"):
            factor = (xi + np.sqrt(np.where(disc >= 0, disc, np.nan))) / (r2 + 1.0)
            rays = np.stack([factor * mx, factor * my, -(factor - xi)], axis=1)
            rays /= np.linalg.norm(rays, axis=1, keepdims=True)
        return rays

    def project(self, points_in_rig: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Pixels of (N, 3) rig-frame points/directions: ((N, 2) (col, row), (N,) valid)."""
        pts = as_points(points_in_rig, 3, "points_in_rig")
        model = pts * np.array([1.0, 1.0, -1.0])
        px, seen = unified_project(
            model, self.xi, self.fx, self.fy, self.cx, self.cy, self.skew, self.k
        )
        valid = seen & self.is_valid_pixel(np.where(seen[:, None], px, 0.0))
        return px, valid

    def project_jacobian(self, points_in_rig: np.ndarray) -> np.ndarray:
        """(N, 2, 3) d(col, row) / d(x, y, z) of :meth:`project`'s pixels (px/mm).

        In the model frame X = diag(1, 1, -1) q, n = |X|, D = X_z + xi n:
        m = (X_x, X_y) / D, so dm_i / dX_j = delta_ij / D - m_i (delta_zj + xi X_j / n) / D;
        then the distortion's Jacobian (:func:`distort_jacobian`) and the pixel's
        [[fx, skew], [0, fy]]. Non-finite where the model cannot see the point.
        """
        q = as_points(points_in_rig, 3, "points_in_rig")
        X = q * np.array([1.0, 1.0, -1.0])
        with np.errstate(invalid="ignore", divide="ignore"):
            n = np.linalg.norm(X, axis=1)
            D = X[:, 2] + self.xi * n
            mx, my = X[:, 0] / D, X[:, 1] / D
            dD = self.xi * X / n[:, None]  # dD / dX
            dD[:, 2] += 1.0
            dm = np.empty((len(q), 2, 3))
            dm[:, 0, :] = -(mx / D)[:, None] * dD
            dm[:, 1, :] = -(my / D)[:, None] * dD
            dm[:, 0, 0] += 1.0 / D
            dm[:, 1, 1] += 1.0 / D
            j11, j12, j21, j22 = distort_jacobian(mx, my, self.k)
        dmd = np.stack([np.stack([j11, j12], axis=1), np.stack([j21, j22], axis=1)], axis=1)
        K = np.array([[self.fx, self.skew], [0.0, self.fy]])
        return K @ dmd @ dm * np.array([1.0, 1.0, -1.0])  # d/dq = d/dX diag(1, 1, -1)
