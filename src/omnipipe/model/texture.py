"""Texture mapping (paper Sec. VI): the unrolled wall image and the mesh's texture.

The wall is unrolled into an image: columns are arc length around the axis (angle
x reference radius), rows distance along the pipe, ``mm_per_px`` each. Every cell
gets a 3-D wall point by linear interpolation of the measured points over the
unrolled Delaunay triangulation (the same one the mesh uses), and its colour from
the keyframe that sees it best:

* visible: the point projects into the valid image (mirror rim, blind centre);
* not in the laser light: farther than ``laser_band_mm`` from the laser plane
  (there the red laser dominates the LED-lit colour);
* sharpest and brightest: the largest image footprint in pixels per millimetre of
  wall (a near, frontal view covers more pixels), from the camera model's
  projection of two small steps on the wall, over the squared distance (the LEDs'
  light falls with it, and with it the signal to noise).

The image is also the mesh's texture atlas: a vertex's UV is its unrolled position.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import cv2
import numpy as np
from scipy.interpolate import LinearNDInterpolator

from omnipipe.camera import camera_from_rig
from omnipipe.geometry import apply, invert
from omnipipe.image import sample_bilinear
from omnipipe.rig import Rig


@dataclass(frozen=True)
class UnrolledImage:
    """The unrolled wall.

    Attributes:
        image: (H, W, 3) uint8; row 0 is the smallest axial position, column 0 angle 0.
        alpha: (H, W) bool, True where the wall was measured and seen.
        mm_per_px: cell size.
        axial_min_mm: axial position of row 0's centre.
        circumference_mm: arc length of the W columns (one full turn).
        source_frame: (H, W) int, the keyframe each cell's colour came from (-1: none).
    """

    image: np.ndarray
    alpha: np.ndarray
    mm_per_px: float
    axial_min_mm: float
    circumference_mm: float
    source_frame: np.ndarray

    @property
    def extent(self) -> tuple[float, float, float, float]:
        """(angle_min_deg, angle_max_deg, axial_min_mm, axial_max_mm) of the image."""
        h = self.image.shape[0]
        return (0.0, 360.0, self.axial_min_mm, self.axial_min_mm + h * self.mm_per_px)


def wall_points_on_grid(
    arc_mm: np.ndarray,
    axial_mm: np.ndarray,
    points_in_world: np.ndarray,
    circumference_mm: float,
    mm_per_px: float,
    max_gap_mm: float,
) -> tuple[np.ndarray, float]:
    """(H, W, 3) interpolated wall points (NaN outside the measured wall) and the axial origin.

    Args:
        arc_mm, axial_mm: (N,) unrolled coordinates of the points, arc in [0, circumference).
        points_in_world: (N, 3).
        max_gap_mm: cells farther than this from every point stay NaN (holes stay holes).
    """
    from scipy.spatial import cKDTree

    circ = circumference_mm
    margin = 0.1 * circ
    lo, hi = arc_mm < margin, arc_mm > circ - margin
    u = np.concatenate([arc_mm, arc_mm[lo] + circ, arc_mm[hi] - circ])
    z = np.concatenate([axial_mm, axial_mm[lo], axial_mm[hi]])
    xyz = np.concatenate([points_in_world, points_in_world[lo], points_in_world[hi]])
    width = int(np.ceil(circ / mm_per_px))
    z0 = float(np.floor(axial_mm.min()))
    height = int(np.ceil((axial_mm.max() - z0) / mm_per_px)) + 1
    gu, gz = np.meshgrid(
        (np.arange(width) + 0.5) * (circ / width), z0 + np.arange(height) * mm_per_px
    )
    grid = LinearNDInterpolator(np.column_stack([u, z]), xyz)(gu, gz)
    # Cells far from any measured point (gaps in the rings, the hull's long edges).
    dist, _ = cKDTree(np.column_stack([u, z])).query(np.column_stack([gu.ravel(), gz.ravel()]))
    grid.reshape(-1, 3)[dist > max_gap_mm] = np.nan
    return grid, z0


def unrolled_image(
    rig: Rig,
    world_from_rig: np.ndarray,
    read_frame: Callable[[int], np.ndarray],
    grid_points: np.ndarray,
    axial_min_mm: float,
    circumference_mm: float,
    mm_per_px: float,
    laser_band_mm: float = 3.0,
    progress: Callable[[int], None] | None = None,
) -> UnrolledImage:
    """Colour every grid cell from the keyframe that sees it best.

    Args:
        rig: calibration (camera model and laser plane).
        world_from_rig: (K, 4, 4) keyframe poses.
        read_frame: k -> (H, W, 3) or (H, W) image of keyframe k.
        grid_points: (H, W, 3) wall point of each cell (NaN: none).
    """
    camera = camera_from_rig(rig)
    h, w = grid_points.shape[:2]
    flat = grid_points.reshape(-1, 3)
    ok = np.isfinite(flat).all(axis=1)
    idx = np.flatnonzero(ok)
    p = flat[idx]
    # Two small steps on the wall per cell (along the rows and columns) for the footprint.
    gp = np.where(np.isfinite(grid_points), grid_points, 0.0)
    step_u = np.gradient(gp, axis=1).reshape(-1, 3)[idx]
    step_z = np.gradient(gp, axis=0).reshape(-1, 3)[idx]
    best = np.full(len(idx), -1)
    best_score = np.zeros(len(idx))
    best_px = np.zeros((len(idx), 2), np.float32)
    n_plane, o_plane = rig.laser.normal_in_rig, rig.laser.offset_mm
    for k, T in enumerate(world_from_rig):
        rig_from_world = invert(T)
        q = apply(rig_from_world, p)
        px, valid = camera.project(q)
        valid &= np.abs(q @ n_plane + o_plane) > laser_band_mm
        px_u, _ = camera.project(q + step_u @ rig_from_world[:3, :3].T)
        px_z, _ = camera.project(q + step_z @ rig_from_world[:3, :3].T)
        a, b = px_u - px, px_z - px
        # Pixels per cell area, over the cell area in mm^2: the footprint's scale.
        # Sharpness (pixels per mm of wall) times the LEDs' inverse-square light: the
        # near view is both finer and brighter.
        dist2 = np.maximum(np.sum(q * q, axis=1), 1e-6)
        score = np.sqrt(np.abs(a[:, 0] * b[:, 1] - a[:, 1] * b[:, 0])) / mm_per_px / dist2
        score = np.where(valid & np.isfinite(score), score, 0.0)
        better = score > best_score
        best[better], best_score[better], best_px[better] = k, score[better], px[better]
    image = np.zeros((h * w, 3), np.uint8)
    for k in np.unique(best[best >= 0]):
        sel = np.flatnonzero(best == k)
        img = read_frame(int(k))
        if img.ndim == 2:
            img = np.repeat(img[:, :, None], 3, axis=2)
        if img.dtype == np.uint16:
            img = (img // 257).astype(np.uint8)
        image[idx[sel]] = sample_bilinear(img, best_px[sel], border=cv2.BORDER_REPLICATE)
        if progress:
            progress(int(k) + 1)
    source = np.full(h * w, -1)
    source[idx] = best
    alpha = source >= 0
    return UnrolledImage(
        image.reshape(h, w, 3),
        alpha.reshape(h, w),
        mm_per_px,
        axial_min_mm,
        circumference_mm,
        source.reshape(h, w),
    )
