"""Hyperboloid-mirror omni-directional camera (paper Eq. 1-3), single viewpoint.

Geometry (rig frame, mm): the mirror focus is the origin; the hyperboloid
(X^2+Y^2)/a^2 - (Z+c)^2/b^2 = -1 has its second focus, the camera lens centre, at
(0, 0, -2c); the image plane is at distance f (px) from the lens towards the mirror.
A pixel (col, row) with u = col - cx, v = row - cy sees the scene along the ray from
the focus through the mirror point (s u, s v, s f - 2c) (Eq. 1).

``project`` is the closed-form inverse: a direction d meets the mirror at
t d with t = a^2 / (b - c d_z) (the root of the mirror equation on the mirror's
sheet), and that mirror point images at f (x, y) / (z + 2c) through the lens.
"""

from __future__ import annotations

import numpy as np

from omnipipe.camera import _kernels
from omnipipe.camera.base import CameraModel, CompiledProjection, as_points
from omnipipe.rig import CameraIntrinsics, Mirror, Rig


class OmniCamera(CameraModel):
    """The rangefinder's camera: hyperboloid mirror + perspective camera.

    Args:
        intrinsics: image size, principal point, f and the valid radii (px).
        mirror: hyperboloid parameters a, b (mm).
    """

    # Pixels closer than this fraction of the asymptote radius a f / b are invalid:
    # beyond it rays graze the mirror and the model is numerically meaningless.
    _ASYMPTOTE_MARGIN = 0.995
    model_name = "hyperboloid"

    def __init__(self, intrinsics: CameraIntrinsics, mirror: Mirror) -> None:
        self.intrinsics = intrinsics
        self.mirror = mirror
        self.a = float(mirror.a)
        self.b = float(mirror.b)
        self.c = float(mirror.c)
        self.f = float(intrinsics.f)
        self.cx = float(intrinsics.cx)
        self.cy = float(intrinsics.cy)
        self.width = int(intrinsics.width)
        self.height = int(intrinsics.height)
        asymptote = self._ASYMPTOTE_MARGIN * self.a * self.f / self.b
        rmax = intrinsics.radius_max
        self.radius_max = asymptote if rmax is None else min(float(rmax), asymptote)
        self.radius_min = 0.0 if intrinsics.radius_min is None else float(intrinsics.radius_min)
        self._params = (
            self.a, self.b, self.c, self.f, self.cx, self.cy, float(self.width),
            float(self.height), self.radius_min, self.radius_max,
        )

    @classmethod
    def from_rig(cls, rig: Rig) -> OmniCamera:
        """The camera of a calibrated rig."""
        return cls(rig.camera, rig.mirror)

    # -- Eq. (1)-(3) -------------------------------------------------------------
    def unproject(self, pixels: np.ndarray) -> np.ndarray:
        """Unit ray vectors of image pixels.

        Args:
            pixels: (N, 2) image coordinates (col, row) in px.

        Returns:
            rays_in_rig: (N, 3) unit vectors from the focus towards the scene
            (NaN rows for pixels outside the mirror's asymptote).
        """
        px = as_points(pixels, 2, "pixels")
        u = px[:, 0] - self.cx
        v = px[:, 1] - self.cy
        a, b, c, f = self.a, self.b, self.c, self.f
        rho2 = u * u + v * v
        denom = a * a * f * f - b * b * rho2
        with np.errstate(invalid="ignore", divide="ignore"):
            # Eq. (3): scale of the lens ray at the mirror surface.
            s = a * a * (f * c + b * np.sqrt(rho2 + f * f)) / denom
            s = np.where(denom > 0, s, np.nan)
            # Eq. (1): the mirror point seen from the focus (Eq. (2): c = sqrt(a^2+b^2)).
            rays = np.stack([s * u, s * v, s * f - 2.0 * c], axis=1)
            rays /= np.linalg.norm(rays, axis=1, keepdims=True)
        return rays

    def project(self, points_in_rig: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Image coordinates of 3-D points (or directions) in the rig frame.

        Args:
            points_in_rig: (N, 3) points or ray vectors (mm; only the direction matters).

        Returns:
            pixels: (N, 2) (col, row) in px, NaN where the mirror cannot see the point.
            valid: (N,) True where the pixel lies in the valid image region
            (between radius_min and radius_max and inside the image).
        """
        pts = np.ascontiguousarray(as_points(points_in_rig, 3, "points_in_rig"))
        pixels = np.empty((len(pts), 2))
        valid = np.empty(len(pts), bool)
        _kernels.project_points(pts, _kernels.HYPERBOLOID, self._params, pixels, valid)
        return pixels, valid

    def compiled_projection(self) -> CompiledProjection:
        """:func:`omnipipe.camera._kernels.hyperboloid_point`'s kind and parameters."""
        return CompiledProjection(_kernels.HYPERBOLOID, self._params)

    def project_jacobian(self, points_in_rig: np.ndarray) -> np.ndarray:
        """Derivative of :meth:`project`'s pixels with respect to the points.

        With n = |q| and s = a^2 / (b n - c q_z) (the mirror point is s q),
        ``project`` is (col, row) = f (q_x, q_y) / g + (cx, cy) with
        g = q_z + (2c / a^2) (b n - c q_z), so dg/dq = (2c b / a^2) q / n + (1 - 2c^2 / a^2) e_z.

        Args:
            points_in_rig: (N, 3) points or ray vectors (mm).

        Returns:
            (N, 2, 3) d(col, row) / d(x, y, z), px/mm (non-finite where the mirror
            cannot see the point; validity is :meth:`project`'s).
        """
        q = as_points(points_in_rig, 3, "points_in_rig")
        a, b, c, f = self.a, self.b, self.c, self.f
        k = 2.0 * c / (a * a)
        with np.errstate(invalid="ignore", divide="ignore"):
            n = np.sqrt(np.einsum("ni,ni->n", q, q))
            g = q[:, 2] + k * (b * n - c * q[:, 2])
            dg = (k * b / n)[:, None] * q
            dg[:, 2] += 1.0 - k * c
            fg = f / g
            J = np.empty((len(q), 2, 3))
            J[:, 0, :] = -(fg * q[:, 0] / g)[:, None] * dg
            J[:, 1, :] = -(fg * q[:, 1] / g)[:, None] * dg
            J[:, 0, 0] += fg
            J[:, 1, 1] += fg
        return J

    def elevation_range(self) -> tuple[float, float]:
        """(lowest, highest) ray elevation (rad, from the xy plane towards +z) of valid pixels."""
        r = np.array(
            [[self.cx + max(self.radius_min, 1e-6), self.cy], [self.cx + self.radius_max, self.cy]]
        )
        rays = self.unproject(r)
        elev = np.arcsin(np.clip(rays[:, 2], -1.0, 1.0))
        return float(elev[0]), float(elev[1])
