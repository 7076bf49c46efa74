"""Perspective projection conversion of omni-directional images (paper Sec. V-A, Fig. 11).

A projection plane in the rig frame has its centre at **d** (mm) and axes **s_x**,
**s_y** (mm per output pixel). Output pixel (i, j) (col, row) shows the scene point
seen through the plane point d + (i - (w-1)/2) s_x + (j - (h-1)/2) s_y: the view is
a pinhole camera with its centre at the mirror focus, so it is free of the mirror's
distortion. The omni image is resampled with cv2.remap.
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

from omnipipe.camera.base import CameraModel, as_points
from omnipipe.errors import ShapeError


@dataclass(frozen=True)
class PerspectiveView:
    """A projection plane (Fig. 11) and the perspective image drawn on it.

    Attributes:
        center_in_rig: (3,) plane centre d (mm, rig frame).
        axis_x_in_rig: (3,) s_x, the plane step of one output column (mm).
        axis_y_in_rig: (3,) s_y, the plane step of one output row (mm).
        width, height: output image size (px).
    """

    center_in_rig: np.ndarray
    axis_x_in_rig: np.ndarray
    axis_y_in_rig: np.ndarray
    width: int
    height: int

    @classmethod
    def looking_at(
        cls,
        direction_in_rig: np.ndarray,
        *,
        width: int,
        height: int,
        focal_px: float,
        up_in_rig: np.ndarray | None = None,
        roll_rad: float = 0.0,
    ) -> PerspectiveView:
        """A view along ``direction_in_rig`` with a pinhole focal length ``focal_px``.

        The plane sits at unit distance along the direction (the scale cancels in
        the projection); ``up_in_rig`` (default: the mirror axis, or x when the
        direction is along it) fixes the image's -y axis; ``roll_rad`` rotates the
        axes about the viewing direction.
        """
        d = np.asarray(direction_in_rig, dtype=float)
        if d.shape != (3,) or not np.isfinite(d).all() or np.linalg.norm(d) == 0:
            raise ShapeError(f"direction_in_rig: expected a non-zero (3,) vector, got {d!r}")
        d = d / np.linalg.norm(d)
        up = np.array([0.0, 0.0, 1.0]) if up_in_rig is None else np.asarray(up_in_rig, float)
        if abs(float(up @ d)) > 0.999 * np.linalg.norm(up):
            up = np.array([1.0, 0.0, 0.0])
        x = np.cross(d, up)
        x /= np.linalg.norm(x)
        y = np.cross(d, x)  # image rows grow away from "up"
        if roll_rad:
            cr, sr = np.cos(roll_rad), np.sin(roll_rad)
            x, y = cr * x + sr * y, -sr * x + cr * y
        step = 1.0 / float(focal_px)
        return cls(d, x * step, y * step, int(width), int(height))

    @property
    def normal_in_rig(self) -> np.ndarray:
        """(3,) unit normal of the plane, pointing away from the focus."""
        n = np.cross(self.axis_x_in_rig, self.axis_y_in_rig)
        n /= np.linalg.norm(n)
        return n if n @ self.center_in_rig >= 0 else -n

    def plane_points(self, pixels: np.ndarray) -> np.ndarray:
        """(N, 3) rig-frame plane points of (N, 2) output pixels (col, row)."""
        px = as_points(pixels, 2, "pixels")
        i = px[:, 0:1] - (self.width - 1) / 2.0
        j = px[:, 1:2] - (self.height - 1) / 2.0
        return self.center_in_rig[None, :] + i * self.axis_x_in_rig + j * self.axis_y_in_rig

    def rays(self, pixels: np.ndarray) -> np.ndarray:
        """(N, 3) unit rays (rig frame) of (N, 2) output pixels."""
        p = self.plane_points(pixels)
        return p / np.linalg.norm(p, axis=1, keepdims=True)

    def pixels_of_rays(self, rays_in_rig: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Output pixels where (N, 3) rays cross the plane, and (N,) True where in front."""
        r = as_points(rays_in_rig, 3, "rays_in_rig")
        n = self.normal_in_rig
        depth = r @ n
        with np.errstate(invalid="ignore", divide="ignore"):
            lam = (self.center_in_rig @ n) / depth
            q = r * lam[:, None] - self.center_in_rig[None, :]
        basis = np.stack([self.axis_x_in_rig, self.axis_y_in_rig], axis=1)  # (3, 2)
        ij, *_ = np.linalg.lstsq(basis, np.nan_to_num(q).T, rcond=None)
        pixels = ij.T + np.array([(self.width - 1) / 2.0, (self.height - 1) / 2.0])
        front = depth > 1e-12
        pixels[~front] = np.nan
        return pixels, front

    def grid(self) -> np.ndarray:
        """(height*width, 2) output pixel coordinates, row-major."""
        rows, cols = np.mgrid[0 : self.height, 0 : self.width]
        return np.stack([cols.ravel(), rows.ravel()], axis=1).astype(float)

    def omni_maps(self, camera: CameraModel) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """cv2.remap maps (float32 col, row) into the omni image and the valid mask.

        Returns:
            map_x, map_y: (height, width) float32 omni-image coordinates.
            valid: (height, width) bool, True where the omni pixel is valid.
        """
        px, valid = camera.project(self.plane_points(self.grid()))
        px = np.where(valid[:, None], px, -1.0)
        map_x = px[:, 0].reshape(self.height, self.width).astype(np.float32)
        map_y = px[:, 1].reshape(self.height, self.width).astype(np.float32)
        return map_x, map_y, valid.reshape(self.height, self.width)

    def render(self, omni_image: np.ndarray, camera: CameraModel) -> tuple[np.ndarray, np.ndarray]:
        """Perspective image drawn from an omni image (bilinear, zero outside the mirror).

        Args:
            omni_image: (H, W) or (H, W, C) image of ``camera``.

        Returns:
            image: (height, width[, C]) perspective view, same dtype.
            valid: (height, width) bool mask of pixels that saw the mirror.
        """
        img = np.asarray(omni_image)
        if img.ndim not in (2, 3) or img.shape[:2] != (camera.height, camera.width):
            raise ShapeError(
                f"omni_image: expected ({camera.height}, {camera.width}[, C]), got {img.shape}"
            )
        map_x, map_y, valid = self.omni_maps(camera)
        out = cv2.remap(img, map_x, map_y, cv2.INTER_LINEAR, borderMode=cv2.BORDER_CONSTANT)
        return out, valid
