"""The one camera interface every stage uses, and what all camera models share.

Every model maps image pixels (col, row), pixel centres at integers, to unit rays in
the rig frame (DATA_CONTRACT.md section 2: origin at the single viewpoint, z along the
mirror axis from the lens towards the mirror, x along columns, y along rows) and back.
The valid image region is the annulus ``radius_min <= |pixel - (cx, cy)| <= radius_max``
inside the image.
"""

from __future__ import annotations

import numpy as np

from omnipipe.errors import ShapeError


def as_points(array: np.ndarray, dim: int, name: str) -> np.ndarray:
    """``array`` as a float (N, dim) array; a single (dim,) vector becomes (1, dim).

    Raises:
        ShapeError: any other shape.
    """
    arr = np.asarray(array, dtype=float)
    if arr.ndim == 1 and arr.shape[0] == dim:
        arr = arr[None, :]
    if arr.ndim != 2 or arr.shape[1] != dim:
        raise ShapeError(f"{name}: expected shape (N, {dim}), got {np.shape(array)}")
    return arr


class CameraModel:
    """Base of every camera model: the valid region and helpers built on project/unproject.

    Subclasses set ``width``, ``height`` (px), ``cx``, ``cy`` (px, the image of the
    mirror axis: centre of the valid annulus), ``radius_min``, ``radius_max`` (px) and
    implement :meth:`project` and :meth:`unproject`.
    """

    model_name = "base"
    width: int
    height: int
    cx: float
    cy: float
    radius_min: float
    radius_max: float

    def _set_image(self, intrinsics) -> None:
        """Principal point, image size and valid annulus (px) from ``CameraIntrinsics``;
        without ``radius_max`` the annulus is the largest circle inside the image."""
        self.cx = float(intrinsics.cx)
        self.cy = float(intrinsics.cy)
        self.width = int(intrinsics.width)
        self.height = int(intrinsics.height)
        inscribed = min(
            self.cx + 0.5, self.width - 0.5 - self.cx, self.cy + 0.5, self.height - 0.5 - self.cy
        )
        rmax = intrinsics.radius_max
        self.radius_max = max(inscribed, 1.0) if rmax is None else float(rmax)
        self.radius_min = 0.0 if intrinsics.radius_min is None else float(intrinsics.radius_min)

    def unproject(self, pixels: np.ndarray) -> np.ndarray:
        """(N, 2) pixels (col, row) -> (N, 3) unit rays in the rig frame (NaN where none)."""
        raise NotImplementedError

    def project(self, points_in_rig: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(N, 3) points or directions in the rig frame -> ((N, 2) pixels, (N,) valid)."""
        raise NotImplementedError

    def is_valid_pixel(self, pixels: np.ndarray) -> np.ndarray:
        """(N,) True for pixels inside the image and the valid annulus."""
        px = as_points(pixels, 2, "pixels")
        r = np.hypot(px[:, 0] - self.cx, px[:, 1] - self.cy)
        inside = (
            (px[:, 0] >= -0.5)
            & (px[:, 0] <= self.width - 0.5)
            & (px[:, 1] >= -0.5)
            & (px[:, 1] <= self.height - 0.5)
        )
        return inside & (r >= self.radius_min) & (r <= self.radius_max)

    def valid_mask(self) -> np.ndarray:
        """(height, width) bool mask of the pixels that see the scene through the mirror."""
        rows, cols = np.mgrid[0 : self.height, 0 : self.width]
        r = np.hypot(cols - self.cx, rows - self.cy)
        return (r >= self.radius_min) & (r <= self.radius_max)

    def elevation_range(self) -> tuple[float, float]:
        """(lowest, highest) ray elevation (rad, from the xy plane towards +z) of valid pixels.

        Sampled around the whole annulus (a model need not be radially symmetric).
        """
        phi = np.linspace(0.0, 2.0 * np.pi, 72, endpoint=False)
        lo = max(self.radius_min, 1e-6)
        px = np.concatenate(
            [
                np.stack([self.cx + r * np.cos(phi), self.cy + r * np.sin(phi)], axis=1)
                for r in (lo, self.radius_max)
            ]
        )
        rays = self.unproject(px)
        elev = np.arcsin(np.clip(rays[:, 2], -1.0, 1.0)).reshape(2, -1)
        return float(np.nanmin(elev[0])), float(np.nanmax(elev[1]))
