"""Scaramuzza's polynomial omni-directional model, as OCamCalib calibrates it.

OCamCalib's conventions: a pixel is (row, col) (rows first), 0-based in
calib_results.txt; the centre is (xc, yc) = (row, col); with the affine matrix
A = [[c, d], [e, 1]], (xp, yp) = A^-1 (row - xc, col - yc) and the ray in OCamCalib's
frame is (xp, yp, P(r)), P(r) = sum_i a_i r^i, r = |(xp, yp)| (P(0) = a0 < 0: the
image centre sees -z). So OCamCalib's x runs along rows and its y along columns.

Rig frame (DATA_CONTRACT.md section 2): x along columns, y along rows, the image centre
sees -z. Hence ``rig = (y_ocam, x_ocam, z_ocam)``: a swap of two axes, a reflection
(determinant -1); see docs/camera_models.md.

``project`` inverts P exactly (Newton on the elevation, seeded from a monotone table);
OCamCalib's own inverse polynomial is kept for writing its file back but not used.
"""

from __future__ import annotations

import numpy as np

from omnipipe.camera.base import CameraModel, as_points
from omnipipe.rig import CameraIntrinsics, OcamParams

_TABLE_SIZE = 4096
_NEWTON_ITERATIONS = 6


class OcamCamera(CameraModel):
    """OCamCalib's model behind the rig-frame ``project`` / ``unproject`` interface.

    Args:
        intrinsics: image size, centre (cx = OCamCalib's yc, cy = its xc) and valid
            radii (px); ``radius_max`` None: the largest circle inside the image.
        params: the polynomial a0, a1, ... (lowest order first) and the affine c, d, e.
    """

    model_name = "ocam"

    def __init__(self, intrinsics: CameraIntrinsics, params: OcamParams) -> None:
        self.intrinsics = intrinsics
        self.params = params
        self.poly = np.asarray(params.polynomial, dtype=float)
        self.c, self.d, self.e = float(params.c), float(params.d), float(params.e)
        self._set_image(intrinsics)
        # Monotone table of the elevation atan2(P(r), r) over r, for project's seed.
        r_far = 1.5 * float(np.hypot(self.width, self.height)) / min(1.0, abs(self.c - self.d * self.e))
        r = np.linspace(0.0, r_far, _TABLE_SIZE)
        theta = np.arctan2(self._p(r), r)
        rising = np.diff(theta) > 0
        stop = int(np.argmin(rising)) + 1 if not rising.all() else len(r)
        self._r_table = r[:stop]
        self._theta_table = theta[:stop]

    def _p(self, r: np.ndarray) -> np.ndarray:
        return np.polynomial.polynomial.polyval(r, self.poly)

    def _dp(self, r: np.ndarray) -> np.ndarray:
        return np.polynomial.polynomial.polyval(r, np.polynomial.polynomial.polyder(self.poly))

    def unproject(self, pixels: np.ndarray) -> np.ndarray:
        """Unit rays in the rig frame of (N, 2) pixels (col, row)."""
        px = as_points(pixels, 2, "pixels")
        drow = px[:, 1] - self.cy
        dcol = px[:, 0] - self.cx
        inv = 1.0 / (self.c - self.d * self.e)
        xp = inv * (drow - self.d * dcol)
        yp = inv * (-self.e * drow + self.c * dcol)
        z = self._p(np.hypot(xp, yp))
        rays = np.stack([yp, xp, z], axis=1)  # rig = (y_ocam, x_ocam, z_ocam)
        return rays / np.linalg.norm(rays, axis=1, keepdims=True)

    def project(self, points_in_rig: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Pixels of (N, 3) rig-frame points/directions: ((N, 2) (col, row), (N,) valid)."""
        pts = as_points(points_in_rig, 3, "points_in_rig")
        xo, yo, zo = pts[:, 1], pts[:, 0], pts[:, 2]
        nxy = np.hypot(xo, yo)
        theta = np.arctan2(zo, nxy)
        t_lo, t_hi = self._theta_table[0], self._theta_table[-1]
        seen = (np.linalg.norm(pts, axis=1) > 0) & (theta >= t_lo) & (theta <= t_hi)
        rho = np.interp(theta, self._theta_table, self._r_table)
        for _ in range(_NEWTON_ITERATIONS):
            p = self._p(rho)
            g = np.arctan2(p, rho) - theta
            dg = (self._dp(rho) * rho - p) / (rho * rho + p * p)
            with np.errstate(invalid="ignore", divide="ignore"):
                step = np.where(dg != 0, g / dg, 0.0)
            rho = np.clip(rho - step, 0.0, self._r_table[-1])
        with np.errstate(invalid="ignore", divide="ignore"):
            x = np.where(nxy > 0, xo / nxy, 0.0) * rho
            y = np.where(nxy > 0, yo / nxy, 0.0) * rho
        row = x * self.c + y * self.d + self.cy
        col = x * self.e + y + self.cx
        px = np.stack([col, row], axis=1)
        px[~seen] = np.nan
        valid = seen & self.is_valid_pixel(np.where(seen[:, None], px, 0.0))
        return px, valid

    def project_jacobian(self, points_in_rig: np.ndarray) -> np.ndarray:
        """(N, 2, 3) d(col, row) / d(x, y, z) of :meth:`project`'s pixels (px/mm).

        In OCamCalib's frame (xo, yo, zo) = (y, x, z): theta = atan2(zo, |(xo, yo)|),
        rho(theta) solves atan2(P(rho), rho) = theta, so d rho / d theta =
        (rho^2 + P^2) / (P'(rho) rho - P); (x, y) = rho (xo, yo) / |(xo, yo)| and
        (row, col) = (c x + d y, e x + y) + centre. Non-finite where the model cannot
        see the point (and on the axis, where the direction around it is undefined).
        """
        q = as_points(points_in_rig, 3, "points_in_rig")
        px, _ = self.project(q)
        xo, yo, zo = q[:, 1], q[:, 0], q[:, 2]
        with np.errstate(invalid="ignore", divide="ignore"):
            row_off, col_off = px[:, 1] - self.cy, px[:, 0] - self.cx
            # (x, y) back from the pixel (the affine's inverse), then rho = |(x, y)|.
            inv = 1.0 / (self.c - self.d * self.e)
            x = inv * (row_off - self.d * col_off)
            y = inv * (-self.e * row_off + self.c * col_off)
            rho = np.hypot(x, y)
            p = self._p(rho)
            drho = (rho * rho + p * p) / (self._dp(rho) * rho - p)  # d rho / d theta
            s2 = xo * xo + yo * yo
            nxy = np.sqrt(s2)
            r2 = s2 + zo * zo
            # d theta / d (xo, yo, zo); d (xo/nxy, yo/nxy) / d (xo, yo).
            dtheta = np.stack([-zo * xo / (nxy * r2), -zo * yo / (nxy * r2), nxy / r2], axis=1)
            u, v = xo / nxy, yo / nxy
            n3 = nxy**3
            du = np.stack([yo * yo / n3, -xo * yo / n3, np.zeros(len(q))], axis=1)
            dv = np.stack([-xo * yo / n3, xo * xo / n3, np.zeros(len(q))], axis=1)
            dx = rho[:, None] * du + (u * drho)[:, None] * dtheta
            dy = rho[:, None] * dv + (v * drho)[:, None] * dtheta
        d_row = self.c * dx + self.d * dy  # w.r.t. (xo, yo, zo)
        d_col = self.e * dx + dy
        J = np.stack([d_col, d_row], axis=1)
        return J[:, :, [1, 0, 2]]  # w.r.t. (x, y, z) = (yo, xo, zo)
