"""Metric ring points: each ring pixel's ray meets the calibrated laser plane (Eq. 4-5).

:func:`triangulate_ring` fills a ring's points from its three-point peak positions (what
camera motion uses); :func:`centroid_ring` gives the analysis's ring, its clipped peaks
moved to their centroids (:attr:`~omnipipe.laser.ring.LaserRing.centroid_shift_px`).
"""

from __future__ import annotations

import math
from dataclasses import replace

import numpy as np

from omnipipe.camera import CameraModel
from omnipipe.laser.ring import LaserRing
from omnipipe.rig import LaserPlane


def intersect_plane(rays_in_rig: np.ndarray, plane: LaserPlane) -> tuple[np.ndarray, np.ndarray]:
    """Points where (N, 3) rays from the focus meet the laser plane.

    Eq. (5): p = -k4 / (k . r) r, with r the (unit) ray of Eq. (1).

    Returns:
        points_in_rig: (N, 3) mm (NaN where the ray misses the plane).
        valid: (N,) True where the ray meets the plane in front of the focus at an
            angle steeper than ~3 deg.
    """
    k = np.asarray(plane.k[:3], float)
    denom = rays_in_rig @ k
    with np.errstate(invalid="ignore", divide="ignore"):
        lam = -plane.k[3] / denom  # Eq. (5)
    valid = np.isfinite(lam) & (lam > 0) & (np.abs(denom) > 0.05 * np.linalg.norm(k))
    pts = rays_in_rig * lam[:, None]
    pts[~valid] = np.nan
    return pts, valid


def triangulate_ring(ring: LaserRing, camera: CameraModel, plane: LaserPlane) -> LaserRing:
    """Fill ``ring.points_in_rig`` and ``ring.sigma_mm`` (drops samples that miss the plane).

    The uncertainty propagates each peak's radial sigma through the forward model:
    sigma_mm = |d point / d radius| * sigma_px, by a central difference along the
    radial direction.
    """
    if len(ring.pixels) == 0:
        ring.points_in_rig = np.zeros((0, 3))
        ring.sigma_mm = np.zeros(0)
        return ring
    centre = np.array([camera.cx, camera.cy])
    radial = ring.pixels - centre
    radial /= np.maximum(np.linalg.norm(radial, axis=1, keepdims=True), 1e-9)
    h = 0.25
    n = len(ring.pixels)
    # The pixels and their two radial neighbours in one call (elementwise: the same
    # values as three calls).
    both = np.concatenate([ring.pixels, ring.pixels + h * radial, ring.pixels - h * radial])
    all_pts, all_ok = intersect_plane(camera.unproject(both), plane)
    pts, p_plus, p_minus = all_pts[:n], all_pts[n : 2 * n], all_pts[2 * n :]
    deriv = np.linalg.norm(p_plus - p_minus, axis=1) / (2 * h)
    ok = all_ok[:n] & all_ok[n : 2 * n] & all_ok[2 * n :] & np.isfinite(pts).all(axis=1)
    for name in ("pixels", "angle_rad", "confidence", "radius_sigma_px", "peak_width_px", "centroid_shift_px"):
        if len(getattr(ring, name)) == n:
            setattr(ring, name, getattr(ring, name)[ok])
    ring.points_in_rig = pts[ok]
    ring.sigma_mm = deriv[ok] * ring.radius_sigma_px
    return ring


def centroid_ring(ring: LaserRing, camera: CameraModel, plane: LaserPlane) -> LaserRing:
    """``ring`` (triangulated) as the analysis measures it: each sample moved along its
    scan line by ``ring.centroid_shift_px`` (a clipped peak to its centroid) and
    triangulated again (:func:`triangulate_ring`: a sample whose moved ray misses the
    plane is dropped), when that makes the ring smoother (:func:`ring_roughness_px`; on
    a ring clipped throughout the centroid halves the roughness, on one clipped here and
    there by a sample it adds some). A new ring with an empty ``centroid_shift_px``;
    ``ring`` itself when it has no move (unclipped peaks, or no centroid asked for)."""
    shift = np.asarray(ring.centroid_shift_px, float)
    if len(shift) == 0:
        return ring
    keep = replace(ring, centroid_shift_px=np.zeros(0, np.float32), warnings=list(ring.warnings))
    if len(shift) != len(ring.pixels) or not np.any(shift):
        return keep
    centre = np.array([camera.cx, camera.cy])
    radius = np.linalg.norm(ring.pixels - centre, axis=1)
    three_point, moved = ring_roughness_px(ring.angle_rad, np.stack([radius, radius + shift]))
    if moved >= three_point:
        return keep
    radial = (ring.pixels - centre) / np.maximum(radius, 1e-9)[:, None]
    return triangulate_ring(replace(keep, pixels=ring.pixels + shift[:, None] * radial), camera, plane)


def ring_roughness_px(angle_rad: np.ndarray, radius_px: np.ndarray, order: int = 8) -> np.ndarray:
    """Robust spread (px) of a ring's image radius about a smooth ring: for each row of
    ``radius_px`` ((N,) or (M, N): M versions of the ring's samples on scan lines at
    ``angle_rad`` (N,)), 1.4826 x the median absolute residual from its least-squares
    Fourier series of ``order`` in the angle (the wall's shape and the rig's offset are
    smooth; the peaks' scatter and their sampling pattern are not); inf with fewer than
    4 samples per coefficient. A float for (N,), (M,) for (M, N)."""
    a, r = np.asarray(angle_rad, float), np.asarray(radius_px, float)
    rows = np.atleast_2d(r)
    if len(a) < 4 * (2 * order + 1):
        out = np.full(len(rows), math.inf)
    else:
        k = np.arange(1, order + 1)[None, :] * a[:, None]
        design = np.column_stack([np.ones_like(a), np.cos(k), np.sin(k)])
        # Normal equations (a 17 x 17 solve), not an SVD per ring.
        coef = np.linalg.solve(design.T @ design, design.T @ rows.T)
        out = 1.4826 * np.median(np.abs(rows - (design @ coef).T), axis=1)
    return out if r.ndim == 2 else float(out[0])


def radial_mm_per_px(ring: LaserRing) -> float:
    """The ring's radial pixel scale: the median over its samples of |d point / d radius|
    (mm on the laser plane per px of image radius, :func:`triangulate_ring`'s derivative,
    ``sigma_mm / radius_sigma_px``): what a sub-pixel error of the peaks shared by the
    ring moves its points by. NaN for a ring without triangulated samples."""
    sig, rad = np.asarray(ring.sigma_mm, float), np.asarray(ring.radius_sigma_px, float)
    if len(sig) == 0 or len(sig) != len(rad):
        return float("nan")
    with np.errstate(invalid="ignore", divide="ignore"):
        ratio = sig / rad
    ratio = ratio[np.isfinite(ratio)]
    return float(np.median(ratio)) if len(ratio) else float("nan")
