"""The one camera interface every stage uses, and what all camera models share.

Every model maps image pixels (col, row), pixel centres at integers, to unit rays in
the rig frame (DATA_CONTRACT.md section 2: origin at the single viewpoint, z along the
mirror axis from the lens towards the mirror, x along columns, y along rows) and back.
The valid image region is the annulus ``radius_min <= |pixel - (cx, cy)| <= radius_max``
inside the image.
"""

from __future__ import annotations

import abc
from dataclasses import dataclass

import numpy as np

from omnipipe.errors import ShapeError
from omnipipe.rig import CameraIntrinsics


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


@dataclass(frozen=True)
class CompiledProjection:
    """A model's projection as compiled code can run it, point by point.

    Attributes:
        kind: which kernel of :mod:`omnipipe.camera._kernels` projects (e.g.
            :data:`~omnipipe.camera._kernels.HYPERBOLOID`).
        params: the kernel's parameters (floats, in its order): a tuple, which compiled
            code holds as values (an array could alias the outputs, and its entries
            would be reloaded per point).

    :func:`omnipipe.camera._kernels.project_point` (``kind``, ``params``, x, y, z) ->
    (col, row, valid) gives bit for bit the model's :meth:`CameraModel.project`.
    """

    kind: int
    params: tuple[float, ...]


class CameraModel(abc.ABC):
    """The one camera interface: pixels <-> rig-frame rays, the projection's Jacobian,
    the pixel angle, and the valid region.

    Subclasses set ``width``, ``height`` (px), ``cx``, ``cy`` (px, the image of the
    mirror axis: centre of the valid annulus), ``radius_min``, ``radius_max`` (px) and
    implement :meth:`project` and :meth:`unproject`; they may override
    :meth:`project_jacobian` with an analytic one and offer a compiled projection
    (:meth:`compiled_projection`) that fast paths use.
    """

    model_name = "base"
    intrinsics: CameraIntrinsics
    width: int
    height: int
    cx: float
    cy: float
    radius_min: float
    radius_max: float

    def _set_image(self, intrinsics: CameraIntrinsics) -> None:
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

    @abc.abstractmethod
    def unproject(self, pixels: np.ndarray) -> np.ndarray:
        """(N, 2) pixels (col, row) -> (N, 3) unit rays in the rig frame (NaN where none)."""

    @abc.abstractmethod
    def project(self, points_in_rig: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(N, 3) points or directions in the rig frame -> ((N, 2) pixels, (N,) valid)."""

    def project_jacobian(self, points_in_rig: np.ndarray) -> np.ndarray:
        """(N, 2, 3) d(col, row) / d(x, y, z) of :meth:`project`'s pixels (px/mm).

        This generic one takes central differences, step cbrt(eps) max(|q|, 1) mm per
        point (error ~1e-10 relative); models override it with their analytic one.
        Non-finite where the model cannot see the point (validity is :meth:`project`'s).
        """
        q = as_points(points_in_rig, 3, "points_in_rig")
        h = np.cbrt(np.finfo(float).eps) * np.maximum(np.linalg.norm(q, axis=1), 1.0)
        J = np.empty((len(q), 2, 3))
        for i in range(3):
            plus, minus = q.copy(), q.copy()
            plus[:, i] += h
            minus[:, i] -= h
            step = plus[:, i] - minus[:, i]  # the step as represented
            J[:, :, i] = (self.project(plus)[0] - self.project(minus)[0]) / step[:, None]
        return J

    def compiled_projection(self) -> CompiledProjection | None:
        """The model's projection for compiled callers, or None (then they use
        :meth:`project`). This base offers none."""
        return None

    def pixel_angle(self, pixels: np.ndarray, step: tuple[float, float] = (0.0, 1.0)) -> np.ndarray:
        """(N,) angle (rad) between the rays of (N, 2) ``pixels`` and of ``pixels + step``
        (px, (col, row)): the angle one pixel subtends there (NaN where a ray is missing)."""
        px = as_points(pixels, 2, "pixels")
        r0 = self.unproject(px)
        r1 = self.unproject(px + np.array([step], dtype=float))
        return np.arccos(np.clip(np.sum(r0 * r1, axis=1), -1, 1))

    def angular_resolution(self) -> float:
        """The image's angular resolution (rad/px): :meth:`pixel_angle` of one row step
        at the middle of the valid annulus, (cx + (radius_min + radius_max) / 2, cy)."""
        mid = np.array([[self.cx + 0.5 * (self.radius_min + self.radius_max), self.cy]])
        return float(self.pixel_angle(mid)[0])

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
