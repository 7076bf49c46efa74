"""Laser-plane calibration: the laser line on a checkerboard at several poses.

For each image: the board's corners give its pose through the rig's camera model
(rays in the rig frame, any model); the laser line is extracted with the light-section
extractor (sub-pixel peaks along radial scan lines) inside the board's image; each
laser pixel's ray meets the board plane in a 3-D point (rig frame, mm). A robust
plane fit (RANSAC, then least squares on the inliers) over all views gives k1..k4
with its RMS residual and 1-sigma uncertainties of the normal (deg) and of the offset
at the focus (mm). Boards at two or more distinct poses are needed (one board gives
only a line).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import cv2
import numpy as np
from scipy.optimize import least_squares

from omnipipe.calibrate.camera import CalibrationError, Target, _rays_pose, detect_corners
from omnipipe.camera import camera_from_rig
from omnipipe.camera.base import CameraModel
from omnipipe.rig import LaserPlane, Rig

MIN_LASER_VIEWS = 2
MIN_POINTS_PER_VIEW = 10


@dataclass
class LaserCalibration:
    """Result of :func:`calibrate_laser`.

    Attributes:
        k: (4,) k1..k4, unit normal with k3 >= 0 (mm).
        rms_mm: RMS distance of the inlier points to the plane (mm).
        normal_sigma_deg: 1-sigma uncertainty of the normal's direction (deg), from the
            residuals with each board counted as two independent points.
        offset_sigma_mm: 1-sigma uncertainty of the plane's distance from the focus (mm),
            likewise. Neither includes the camera model's error (docs/calibration.md).
        points: (N, 3) inlier laser points in the rig frame (mm).
        per_view: image index -> (points used, RMS residual mm).
        board_rms_px: image index -> corner reprojection RMS of the board pose (px).
        rig_from_board: image index -> (4, 4) board pose in the rig frame (mm).
    """

    k: np.ndarray
    rms_mm: float
    normal_sigma_deg: float
    offset_sigma_mm: float
    points: np.ndarray
    per_view: dict[int, tuple[int, float]]
    board_rms_px: dict[int, float]
    rig_from_board: dict[int, np.ndarray]


def board_pose(camera: CameraModel, corners: np.ndarray, target: Target) -> tuple[np.ndarray, float]:
    """(4, 4) rig_from_board of a detected board, refined on pixels, and its RMS (px).

    Raises:
        CalibrationError: the camera model does not see the corners.
    """
    obj = target.object_points()
    rays = camera.unproject(corners)
    sol = _rays_pose(rays, obj) if np.isfinite(rays).all() else None
    if sol is None:
        raise CalibrationError("the rig's camera model does not see the detected board")
    v0 = np.concatenate(sol)

    def residual(v: np.ndarray) -> np.ndarray:
        pts = obj @ cv2.Rodrigues(v[:3])[0].T + v[3:]
        px, _ = camera.project(pts)
        return np.nan_to_num(px - corners, nan=1e3).ravel()

    res = least_squares(residual, v0, method="lm")
    pose = np.eye(4)
    pose[:3, :3] = cv2.Rodrigues(res.x[:3])[0]
    pose[:3, 3] = res.x[3:]
    rms = float(np.sqrt(np.mean(res.fun.reshape(-1, 2) ** 2) * 2))
    return pose, rms


def laser_points_on_board(
    image: np.ndarray, camera: CameraModel, pose: np.ndarray, target: Target, channel: str,
    refine: bool = True,
) -> np.ndarray:
    """(N, 3) rig-frame points (mm) of the laser line on the board's printed area.

    The light-section extractor's peaks on the board, kept when they lie on one straight
    line; with ``refine`` moved onto the line fitted to the pixel values
    (:func:`fit_laser_line`; the peaks alone are off by up to 0.3 mm per view).
    """
    from omnipipe.laser.extract import ExtractionConfig, RingExtractor

    h, w = image.shape[:2]
    # the board's outline (half a square beyond the outer corners) in the image
    s = target.square_mm
    u = np.linspace(-0.5, target.cols - 0.5, 60) * s
    v = np.linspace(-0.5, target.rows - 0.5, 60) * s
    outline = np.concatenate([
        np.stack([u, np.full_like(u, v[0])], 1), np.stack([np.full_like(v, u[-1]), v], 1),
        np.stack([u[::-1], np.full_like(u, v[-1])], 1), np.stack([np.full_like(v, u[0]), v[::-1]], 1),
    ])
    pts = np.concatenate([outline, np.zeros((len(outline), 1))], axis=1) @ pose[:3, :3].T + pose[:3, 3]
    px, _ = camera.project(pts)
    if not np.isfinite(px).all():
        return np.zeros((0, 3))
    mask = np.zeros((h, w), np.uint8)
    cv2.fillPoly(mask, [np.round(px).astype(np.int32)], 1)
    masked = image * mask[..., None] if image.ndim == 3 else image * mask
    cfg = ExtractionConfig(min_ring_fraction=0.0, angles=1440)
    ring = RingExtractor(camera, cfg).extract(masked, channel)  # type: ignore[arg-type]
    if len(ring.pixels) == 0:
        return np.zeros((0, 3))
    rays = camera.unproject(ring.pixels)
    n = pose[:3, 2]
    d = float(n @ pose[:3, 3])
    with np.errstate(invalid="ignore", divide="ignore"):
        t = d / (rays @ n)
    p = rays * t[:, None]
    local = (p - pose[:3, 3]) @ pose[:3, :3]
    inside = (
        np.isfinite(t) & (t > 0)
        & (local[:, 0] > -0.3 * s) & (local[:, 0] < (target.cols - 0.7) * s)
        & (local[:, 1] > -0.3 * s) & (local[:, 1] < (target.rows - 0.7) * s)
    )
    p, uv = p[inside], local[inside, :2]
    if len(p) < MIN_POINTS_PER_VIEW:
        return np.zeros((0, 3))
    # The laser's trace on a flat board is a straight line: keep the points on the
    # best line (RANSAC, 0.3 mm), and only a line that crosses at least two squares.
    rng = np.random.default_rng(len(p))
    best = np.zeros(len(p), bool)
    for _ in range(200):
        a, b = uv[rng.choice(len(uv), 2, replace=False)]
        dvec = b - a
        norm = float(np.hypot(*dvec))
        if norm < 1e-6:
            continue
        nrm = np.array([-dvec[1], dvec[0]]) / norm
        inl = np.abs((uv - a) @ nrm) < 0.3
        if inl.sum() > best.sum():
            best = inl
    if best.sum() < MIN_POINTS_PER_VIEW:
        return np.zeros((0, 3))
    q = uv[best]
    span = np.ptp(q @ np.linalg.svd(q - q.mean(axis=0), full_matrices=False)[2][0])
    if span < 2.0 * s:
        return np.zeros((0, 3))
    if not refine:
        return p[best]
    line = fit_laser_line(image, camera, pose, target, q, channel)
    if line is None:  # no clean line on this board: its peaks alone would bias the plane
        return np.zeros((0, 3))
    (c0, direction), _ = line
    # the peaks' positions along the line, moved onto the fitted line (same count)
    along = (q - c0) @ direction
    uv_fit = c0 + along[:, None] * direction
    return np.concatenate([uv_fit, np.zeros((len(uv_fit), 1))], axis=1) @ pose[:3, :3].T + pose[:3, 3]


LINE_BAND_MM = 3.0  # pixels within this distance (board, mm) of the first line take part in the fit
SATURATED = 0.98  # of full scale: saturated samples are left out of the line fit


def fit_laser_line(
    image: np.ndarray, camera: CameraModel, pose: np.ndarray, target: Target, uv: np.ndarray,
    channel: str = "red",
) -> tuple[tuple[np.ndarray, np.ndarray], float] | None:
    """The laser line on a board by a model fit of the pixel values around it.

    The light-section extractor's peaks (``uv``: (N, 2) board coordinates, mm, already on
    one straight line) are sampled on a 1 px radial grid with bilinear interpolation; on
    the board's small image (12 mm squares are 5-13 px at 800 x 600) a 1 px step is
    1-2 mm, and the peaks are pulled towards pixel centres by up to 0.3 mm per view
    (measured against the simulator's truth). Here every pixel of the board's image
    within ``LINE_BAND_MM`` of that line is mapped onto the board (its ray meets the
    board's plane) and the laser channel is fitted as

        value = alpha * other + c + (a0 + a1 * other) * exp(-d^2 / (2 w^2))

    with ``d`` the pixel's board distance to the line (mm), ``other`` the brightest other
    channel (the print seen by the LED light: the laser channel's own share of it, and
    the print's reflectance modulating the laser), least squares over the line's
    offset and angle, w, alpha, c, a0, a1. Saturated pixels are left out. The
    sheet's profile is symmetric about the line, so the fit is unbiased whatever the
    sampling.

    Returns:
        ((point (2,), unit direction (2,)) of the line in board mm, RMS residual in grey
        levels), or None when too few pixels or the fit fails.
    """
    from omnipipe.image import CHANNEL_INDEX

    img = np.asarray(image)
    if img.ndim != 3 or channel not in CHANNEL_INDEX or len(uv) < 2:
        return None
    idx = CHANNEL_INDEX[channel]
    others = [c for c in range(img.shape[2]) if c != idx][:2]
    full = 65535.0 if img.dtype == np.uint16 else 255.0 if img.dtype == np.uint8 else float(img.max() or 1)
    lam = img[..., idx].astype(float) / full
    oth = img[..., others].astype(float).max(axis=2) / full
    centre = uv.mean(axis=0)
    direction = np.linalg.svd(uv - centre, full_matrices=False)[2][0]
    along = (uv - centre) @ direction
    lo, hi = float(along.min()), float(along.max())
    band = _band_pixels(lam, oth, camera, pose, target, centre, direction, (lo, hi))
    if band is None:
        return None
    return _fit_line_profile(*band, centre, direction, full)


def _band_pixels(
    lam: np.ndarray, oth: np.ndarray, camera: CameraModel, pose: np.ndarray, target: Target,
    centre: np.ndarray, direction: np.ndarray, extent: tuple[float, float],
) -> tuple[np.ndarray, np.ndarray, np.ndarray] | None:
    """The pixels within ``LINE_BAND_MM`` of the line (``centre`` + t ``direction``, t in
    ``extent``, board mm) on the board and unsaturated: their board coordinates (M, 2) mm,
    laser-channel and other-channel values (M,) (fractions of full scale); None when
    fewer than 30 or the band does not project."""
    lo, hi = extent
    normal = np.array([-direction[1], direction[0]])
    s = target.square_mm
    # the band's outline on the board -> pixels
    t = np.linspace(lo, hi, 40)
    edge = np.concatenate([
        centre + t[:, None] * direction + LINE_BAND_MM * normal,
        centre + t[::-1, None] * direction - LINE_BAND_MM * normal,
    ])
    pts = np.concatenate([edge, np.zeros((len(edge), 1))], axis=1) @ pose[:3, :3].T + pose[:3, 3]
    px, _ = camera.project(pts)
    if not np.isfinite(px).all():
        return None
    h, w = lam.shape
    mask = np.zeros((h, w), np.uint8)
    cv2.fillPoly(mask, [np.round(px).astype(np.int32)], 1)
    mask = cv2.dilate(mask, np.ones((3, 3), np.uint8))
    rows, cols = np.nonzero(mask)
    pix = np.stack([cols, rows], axis=1).astype(float)
    rays = camera.unproject(pix)
    n = pose[:3, 2]
    with np.errstate(invalid="ignore", divide="ignore"):
        tr = float(n @ pose[:3, 3]) / (rays @ n)
    local = (rays * tr[:, None] - pose[:3, 3]) @ pose[:3, :3]
    buv = local[:, :2]
    d0 = (buv - centre) @ normal
    a0 = (buv - centre) @ direction
    use = (
        np.isfinite(tr) & (tr > 0) & (np.abs(d0) <= LINE_BAND_MM) & (a0 >= lo) & (a0 <= hi)
        & (buv[:, 0] > -0.5 * s) & (buv[:, 0] < (target.cols - 0.5) * s)
        & (buv[:, 1] > -0.5 * s) & (buv[:, 1] < (target.rows - 0.5) * s)
        & (lam[rows, cols] < SATURATED)
    )
    if use.sum() < 30:
        return None
    return buv[use], lam[rows[use], cols[use]], oth[rows[use], cols[use]]


def _fit_line_profile(
    buv: np.ndarray, val: np.ndarray, oth_v: np.ndarray, centre: np.ndarray,
    direction: np.ndarray, full: float,
) -> tuple[tuple[np.ndarray, np.ndarray], float] | None:
    """Least-squares fit of the line's profile model (see :func:`fit_laser_line`) to the
    band's pixels: ((point, unit direction) board mm, RMS grey levels) or None."""

    def model(v: np.ndarray) -> np.ndarray:
        d = (buv - centre) @ np.array([-math.sin(v[1]), math.cos(v[1])]) - v[0]
        prof = np.exp(-0.5 * (d / v[2]) ** 2)
        return v[3] * oth_v + v[4] + (v[5] + v[6] * oth_v) * prof - val

    ang0 = math.atan2(direction[1], direction[0])
    v0 = np.array([0.0, ang0, 0.6, 0.7, 0.0, 0.5, 0.0])
    sol = least_squares(model, v0, method="lm", x_scale=np.array([0.1, 0.01, 0.1, 0.1, 0.05, 0.1, 0.1]))
    v = sol.x
    amp = v[5] + v[6] * np.array([oth_v.min(), oth_v.max()])
    if (not sol.success or not (0.05 < abs(v[2]) < LINE_BAND_MM) or abs(v[0]) > LINE_BAND_MM
            or amp.min() <= 0.0):
        return None
    dirf = np.array([math.cos(v[1]), math.sin(v[1])])
    nf = np.array([-dirf[1], dirf[0]])
    rms = float(np.sqrt(np.mean(sol.fun**2)) * full)
    return (centre + v[0] * nf, dirf), rms


def fit_plane(points: np.ndarray, rng: np.random.Generator, threshold_mm: float = 0.5) -> tuple[np.ndarray, np.ndarray, float, float, float]:
    """Robust plane through (N, 3) points: RANSAC, then total least squares on inliers.

    Returns:
        (k, inliers, rms_mm, normal_sigma_rad, offset_sigma_mm); k has a unit normal with
        k3 >= 0. Uncertainties from the residual variance and the points' spread.
    """
    n_pts = len(points)
    best = np.zeros(n_pts, bool)
    for _ in range(300):
        sample = points[rng.choice(n_pts, 3, replace=False)]
        nrm = np.cross(sample[1] - sample[0], sample[2] - sample[0])
        if np.linalg.norm(nrm) < 1e-9:
            continue
        nrm /= np.linalg.norm(nrm)
        inl = np.abs((points - sample[0]) @ nrm) < threshold_mm
        if inl.sum() > best.sum():
            best = inl
    for _ in range(3):
        q = points[best]
        centre = q.mean(axis=0)
        _, _, vt = np.linalg.svd(q - centre, full_matrices=False)
        nrm = vt[2]
        resid = (points - centre) @ nrm
        sigma = 1.4826 * np.median(np.abs(resid[best]))
        best = np.abs(resid) < max(3.0 * sigma, 1e-3)
    q = points[best]
    centre = q.mean(axis=0)
    _, _, vt = np.linalg.svd(q - centre, full_matrices=False)
    nrm = vt[2]
    if nrm[2] < 0:
        nrm = -nrm
    off = -float(nrm @ centre)
    resid = (q - centre) @ nrm
    rms = float(np.sqrt(np.mean(resid**2)))
    # z' = alpha x' + beta y' + gamma in the plane's own frame: cov = s^2 (A^T A)^-1
    a_mat = np.stack([(q - centre) @ vt[0], (q - centre) @ vt[1], np.ones(len(q))], axis=1)
    s2 = float(np.sum(resid**2) / max(len(q) - 3, 1))
    cov = s2 * np.linalg.inv(a_mat.T @ a_mat)
    normal_sigma = float(math.sqrt(max(np.linalg.eigvalsh(cov[:2, :2]).max(), 0.0)))
    origin = -centre  # the focus in the plane's frame: offset at (x0', y0')
    g = np.array([origin @ vt[0], origin @ vt[1], 1.0])
    offset_sigma = float(math.sqrt(max(g @ cov @ g, 0.0)))
    return np.array([*nrm, off]), best, rms, normal_sigma, offset_sigma


def calibrate_laser(
    images: list[np.ndarray], rig: Rig, target: Target, channel: str = "red", seed: int = 0
) -> LaserCalibration:
    """The laser plane from images of a checkerboard cut by the laser line.

    Raises:
        CalibrationError: too few boards found, or too few views with laser points on
            the board, or all boards in one plane.
    """
    camera = camera_from_rig(rig)
    per_pts: dict[int, np.ndarray] = {}
    board_rms: dict[int, float] = {}
    poses: dict[int, np.ndarray] = {}
    normals = []
    for i, img in enumerate(images):
        corners = detect_corners(img, target)
        if corners is None:
            continue
        pose, rms = board_pose(camera, corners, target)
        board_rms[i] = rms
        poses[i] = pose
        pts = laser_points_on_board(img, camera, pose, target, channel)
        if len(pts) >= MIN_POINTS_PER_VIEW:
            per_pts[i] = pts
            normals.append(pose[:3, 2])
    if not board_rms:
        raise CalibrationError(f"no {target} found in any of the {len(images)} images")
    if len(per_pts) < MIN_LASER_VIEWS:
        raise CalibrationError(
            f"the laser line ({channel}) crosses the board in {len(per_pts)} of {len(board_rms)} "
            f"views with the target; at least {MIN_LASER_VIEWS} are needed"
        )
    nn = np.array(normals)
    if np.linalg.svd(nn - nn.mean(axis=0), compute_uv=False)[0] < 0.05:
        raise CalibrationError("every board faces the same way: the laser lines give no plane")
    points = np.concatenate(list(per_pts.values()))
    k, inl, rms, ns, os_ = fit_plane(points, np.random.default_rng(seed))
    per_view = {}
    for i, pts in per_pts.items():
        r = pts @ k[:3] + k[3]
        per_view[i] = (len(pts), float(np.sqrt(np.mean(r**2))))
    # The points of one board lie on its fitted line: their errors are shared, not
    # independent. Count each board as two independent points (a line's two degrees of
    # freedom in the plane) for the uncertainties.
    views_used = sum(1 for pts in per_pts.values() if np.any(np.abs(pts @ k[:3] + k[3]) < 0.5))
    inflate = math.sqrt(max(int(inl.sum()) / max(2 * views_used, 1), 1.0))
    return LaserCalibration(k, rms, math.degrees(ns) * inflate, os_ * inflate, points[inl], per_view,
                            board_rms, poses)


# The board poses' share of the plane offset's error (camera model and corners, common to
# every board, so the laser fit cannot see it): RMS 0.023 mm over bench_calibration's 10
# random sets at 800x600, where the fit's own 1-sigma averaged 0.008 mm.
CAMERA_SHARE_OFFSET_SIGMA_MM = 0.025


def laser_plane(cal: LaserCalibration, channel: str) -> LaserPlane:
    """The calibrated plane for rig.yaml, with its offset's 1-sigma (mm): the laser fit's
    own (each board counted as two points) and, in quadrature, the board poses' share
    :data:`CAMERA_SHARE_OFFSET_SIGMA_MM` (docs/calibration.md)."""
    sigma = math.hypot(float(cal.offset_sigma_mm), CAMERA_SHARE_OFFSET_SIGMA_MM)
    return LaserPlane(k=tuple(float(v) for v in cal.k), channel=channel,  # type: ignore[arg-type]
                      offset_sigma_mm=sigma)


def ring_section_axes(camera: CameraModel, k: np.ndarray, pixels: np.ndarray) -> tuple[float, float]:
    """(minor, major) axes (mm) of the laser ring seen at (N, 2) ``pixels`` through a rig.

    Each pixel's ray meets the laser plane ``k`` (k1..k4, Eq. 4, rig frame); an ellipse
    is fitted (algebraic least squares) to the points in the plane. A plane cuts a
    straight pipe in an ellipse whose minor axis is the pipe's diameter, whatever the
    plane's tilt: with the ring of a pipe of known diameter this checks a calibrated
    camera and laser together.

    Raises:
        CalibrationError: fewer than 6 pixels whose rays meet the plane, or no ellipse.
    """
    kk = np.asarray(k, float)
    nrm = kk[:3] / np.linalg.norm(kk[:3])
    rays = camera.unproject(np.asarray(pixels, float))
    with np.errstate(invalid="ignore", divide="ignore"):
        t = -kk[3] / np.linalg.norm(kk[:3]) / (rays @ nrm)
    pts = rays * t[:, None]
    pts = pts[np.isfinite(t) & (t > 0)]
    if len(pts) < 6:
        raise CalibrationError(f"only {len(pts)} ring pixels meet the laser plane; 6 are needed")
    c = pts.mean(axis=0)
    helper = np.array([1.0, 0.0, 0.0]) if abs(nrm[0]) < 0.9 else np.array([0.0, 1.0, 0.0])
    u = np.cross(nrm, helper)
    u /= np.linalg.norm(u)
    v = np.cross(nrm, u)
    x, y = (pts - c) @ u, (pts - c) @ v
    a_mat = np.stack([x * x, x * y, y * y, x, y, np.ones_like(x)], axis=1)
    a, b, cc, d, e, f = np.linalg.svd(a_mat, full_matrices=False)[2][-1]
    m = np.array([[a, b / 2.0], [b / 2.0, cc]])
    ev = np.linalg.eigvalsh(m)
    if not (ev[0] * ev[1] > 0):
        raise CalibrationError("the ring's points do not form an ellipse")
    x0 = np.linalg.solve(2.0 * m, [-d, -e])
    f0 = f + 0.5 * (d * x0[0] + e * x0[1])
    axes = np.sqrt(-f0 / ev)
    return float(2.0 * axes.min()), float(2.0 * axes.max())
