"""The paper's projection-plane refinement of corresponding points (Sec. V-A, Fig. 11).

Features are first found on fixed perspective views (a "distortion-naive" conversion:
a feature far from its view's centre is seen obliquely). With the initial motion,
each correspondence is refined as the paper describes: frame a's feature is described
on a projection plane centred on its own ray (centre d = the ray, axes s_x around the
mirror axis and s_y towards it), and in frame b the plane's centre d is searched along
the epipolar curve of that ray while its axes s_x, s_y are rotated about d; the plane
whose SIFT descriptor is nearest to a's wins, and its centre is the refined ray. The
motion is then estimated again from the refined rays.

All planes of a frame pair are rendered into one mosaic and described by a single
OpenCV SIFT ``compute`` call at the tile centres (one keypoint per rotation).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import cv2
import numpy as np

from omnipipe.camera import CameraModel
from omnipipe.config import bounded
from omnipipe.image import sample_bilinear
from omnipipe.sfm.geometry import triangulate_pairs


@dataclass(frozen=True)
class PlaneRefineConfig:
    """Projection-plane refinement settings.

    Attributes:
        enabled: refine (the paper's method) or keep the view-based correspondences.
        max_matches: matches refined per frame pair (evenly chosen).
        patch_px: side of each projection plane (px).
        keypoint_size_px: SIFT keypoint diameter on the plane.
        depth_span: the plane centre is searched over depths within this factor
            (log-uniform) of the initially triangulated one, along the epipolar curve.
        depth_steps: candidates along the epipolar curve.
        rotations_deg: in-plane rotations of s_x, s_y tried at each candidate.
    """

    enabled: bool = False
    max_matches: int = bounded(300, ge=1)
    patch_px: int = bounded(33, ge=3)
    keypoint_size_px: float = bounded(12.0, gt=0)
    depth_span: float = bounded(1.5, ge=1)
    depth_steps: int = bounded(15, ge=1)
    rotations_deg: tuple[float, ...] = bounded((-6.0, -3.0, 0.0, 3.0, 6.0), ge=-180, le=180)


def _plane_axes(d: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(N, 3) s_x (around the mirror axis) and s_y (towards +z) of planes centred on rays d."""
    z = np.array([0.0, 0.0, 1.0])
    sx = np.cross(z, d)
    sx /= np.maximum(np.linalg.norm(sx, axis=1, keepdims=True), 1e-12)
    sy = np.cross(d, sx)
    return sx, sy


def _mosaic(gray: np.ndarray, camera: CameraModel, centres: np.ndarray, focal: float, size: int) -> np.ndarray:
    """Perspective planes centred on rays ``centres`` (N, 3), tiled in rows of 64."""
    n = len(centres)
    half = (size - 1) / 2
    g = np.arange(size) - half
    gu, gv = np.meshgrid(g, g)
    sx, sy = _plane_axes(centres)
    rays = focal * centres[:, None, :] + gu.ravel()[None, :, None] * sx[:, None, :] + gv.ravel()[None, :, None] * sy[:, None, :]
    rays /= np.linalg.norm(rays, axis=2, keepdims=True)
    px, ok = camera.project(rays.reshape(-1, 3))
    vals = sample_bilinear(gray, np.nan_to_num(px, nan=-1.0))
    vals = np.where(ok, vals, 0.0).reshape(n, size, size)
    cols = 64
    rows = -(-n // cols)
    mosaic = np.zeros((rows * size, cols * size), np.float32)
    for i in range(n):
        r, c = divmod(i, cols)
        mosaic[r * size : (r + 1) * size, c * size : (c + 1) * size] = vals[i]
    return mosaic


def _describe(sift, mosaic: np.ndarray, n: int, size: int, angles: list[float], kp_size: float) -> np.ndarray:
    """(n, len(angles), 128) SIFT descriptors at the tile centres, one per angle."""
    img = cv2.normalize(mosaic, None, 0, 255, cv2.NORM_MINMAX).astype(np.uint8)
    half = (size - 1) / 2
    kps = []
    for i in range(n):
        r, c = divmod(i, 64)
        for a in angles:
            kps.append(cv2.KeyPoint(float(c * size + half), float(r * size + half), kp_size, float(a % 360.0)))
    kps_out, desc = sift.compute(img, kps)
    out = np.full((n * len(angles), 128), np.inf, np.float32)
    if desc is not None and len(kps_out) == len(kps):
        out[:] = desc
    return out.reshape(n, len(angles), 128)


def refine_matches(
    gray_a: np.ndarray,
    gray_b: np.ndarray,
    camera: CameraModel,
    rays_a: np.ndarray,
    rays_b: np.ndarray,
    b_from_a: np.ndarray,
    config: PlaneRefineConfig,
) -> np.ndarray:
    """Refined rays in frame b for the rays of frame a (paper Sec. V-A).

    Args:
        gray_a, gray_b: (H, W) float32 grey images without the laser channel.
        camera: the omni camera.
        rays_a, rays_b: (M, 3) matched unit rays (inliers of the initial motion).
        b_from_a: (4, 4) initial rig_b_from_rig_a with a unit (or metric) translation.

    Returns:
        (M, 3) refined unit rays in b (the initial ray where no plane matched better).
    """
    M = len(rays_a)
    if M == 0:
        return rays_b.copy()
    R, t = b_from_a[:3, :3], b_from_a[:3, 3]
    # Initial depth along each ray of a (midpoint triangulation), for the search range.
    lam = triangulate_pairs(rays_a, rays_b, b_from_a)[1][:, 0]
    ok = np.isfinite(lam) & (lam > 0)
    out = rays_b.copy()
    idx = np.flatnonzero(ok)
    if len(idx) > config.max_matches:
        idx = idx[np.linspace(0, len(idx) - 1, config.max_matches).astype(int)]
    if len(idx) == 0:
        return out
    # Plane focal length: the omni image's angular resolution mid-annulus.
    focal = 1.0 / max(camera.angular_resolution(), 1e-4)
    sift = cv2.SIFT_create()
    size = config.patch_px
    desc_a = _describe(sift, _mosaic(gray_a, camera, rays_a[idx], focal, size), len(idx), size, [0.0], config.keypoint_size_px)[:, 0]
    # Candidate centres along the epipolar curve of each ray of a.
    S = config.depth_steps
    scales = np.exp(np.linspace(-math.log(config.depth_span), math.log(config.depth_span), S))
    depths = lam[idx, None] * scales[None, :]
    pts_b = (rays_a[idx, None, :] * depths[..., None]) @ R.T + t
    cand = pts_b / np.linalg.norm(pts_b, axis=2, keepdims=True)  # (m, S, 3)
    angles = list(config.rotations_deg)
    desc_b = _describe(
        sift, _mosaic(gray_b, camera, cand.reshape(-1, 3), focal, size), len(idx) * S, size, angles,
        config.keypoint_size_px,
    ).reshape(len(idx), S, len(angles), 128)
    dist = np.linalg.norm(desc_b - desc_a[:, None, None, :], axis=3).min(axis=2)  # (m, S)
    best = np.argmin(dist, axis=1)
    # Sub-step refinement of the depth index by a parabola through the neighbours.
    rows = np.arange(len(idx))
    k = best.clip(1, S - 2)
    y0, y1, y2 = dist[rows, k - 1], dist[rows, k], dist[rows, k + 1]
    den = y0 - 2 * y1 + y2
    off = np.where(den > 1e-9, 0.5 * (y0 - y2) / np.where(den > 1e-9, den, 1.0), 0.0).clip(-0.5, 0.5)
    interior = (best > 0) & (best < S - 1) & np.isfinite(dist[rows, best])
    log_s = np.log(scales[k]) + off * (np.log(scales[1]) - np.log(scales[0]))
    p = (rays_a[idx] * (lam[idx] * np.exp(log_s))[:, None]) @ R.T + t
    refined = p / np.linalg.norm(p, axis=1, keepdims=True)
    out[idx[interior]] = refined[interior]
    return out
