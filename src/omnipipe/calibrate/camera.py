"""Camera calibration from checkerboard views through the mirror (unified model).

Corners are found by OpenCV's sector-based detector (``findChessboardCornersSB``),
which copes with the strong bending of the board near the mirror's rim, and moved to
the image's saddle point (:func:`refine_saddle`: the detector alone is 0.13 px RMS off
the exact projection, with per-view systematic parts); on colour images the green
channel is used (the red laser line does not show in it). The
unified model (xi, fx, fy, cx, cy, k1, k2, p1, p2; skew fixed at 0, as Kalibr) and one
board pose per view are refined together by least squares on the corner pixels.
OpenCV's own ``cv2.omnidir.calibrate`` lives in opencv-contrib, whose wheel provides
the same ``cv2`` package as the project's opencv-python-headless and cannot be
installed beside it; this module is the replacement (docs/calibration.md).
"""

from __future__ import annotations

import math
import re
from dataclasses import dataclass, field
from pathlib import Path

import cv2
import numpy as np
from scipy.optimize import least_squares
from scipy.sparse import lil_matrix

from omnipipe.camera.unified import unified_project
from omnipipe.errors import ConfigError, OmnipipeError
from omnipipe.rig import CameraIntrinsics, Rig, UnifiedParams

MIN_VIEWS = 4


class CalibrationError(OmnipipeError):
    """A calibration that cannot be done with the given images (one line, exit 1)."""
_MEI = np.array([1.0, 1.0, -1.0])  # rig <-> unified model frame (a reflection)


@dataclass(frozen=True)
class Target:
    """A checkerboard: inner corners ``cols`` x ``rows``, squares ``square_mm`` (mm)."""

    cols: int
    rows: int
    square_mm: float

    def object_points(self) -> np.ndarray:
        """(cols*rows, 3) corners in the board frame (mm), row-major as OpenCV returns them."""
        j, i = np.mgrid[0 : self.rows, 0 : self.cols]
        pts = np.stack([i.ravel(), j.ravel(), np.zeros(i.size)], axis=1)
        return pts * self.square_mm

    def __str__(self) -> str:
        return f"{self.cols}x{self.rows} checkerboard ({self.square_mm:g} mm squares)"


def parse_target(text: str) -> Target:
    """``checkerboard:COLSxROWS:SQUARE_MM`` (inner corners) -> :class:`Target`.

    Raises:
        ConfigError: ``--target``.
    """
    m = re.fullmatch(r"checkerboard:(\d+)x(\d+):([0-9]*\.?[0-9]+)", text.strip().lower())
    if not m:
        raise ConfigError(
            "--target", f"expected checkerboard:COLSxROWS:SQUARE_MM (inner corners), got {text!r}"
        )
    cols, rows, square = int(m.group(1)), int(m.group(2)), float(m.group(3))
    if cols < 3 or rows < 3 or cols > 100 or rows > 100:
        raise ConfigError("--target", f"needs 3-100 inner corners each way, got {cols}x{rows}")
    if not 0 < square < 1e4:
        raise ConfigError("--target", f"square size must be a positive number of mm, got {square}")
    return Target(cols, rows, square)


def load_images(paths: list[str | Path]) -> list[np.ndarray]:
    """Read calibration images (RGB order for colour); all must share one size.

    Raises:
        ConfigError: a missing or unreadable image; images of different sizes.
    """
    from omnipipe.dataset import read_image

    if not paths:
        raise ConfigError("IMAGES", "no images given")
    images = []
    for p in paths:
        img = read_image(Path(p))
        if images and img.shape[:2] != images[0].shape[:2]:
            h0, w0 = images[0].shape[:2]
            raise ConfigError(
                str(p), f"is {img.shape[1]}x{img.shape[0]} but {paths[0]} is {w0}x{h0}: "
                "calibration images must all come from one camera at one size"
            )
        images.append(img)
    return images


def board_gray(image: np.ndarray) -> np.ndarray:
    """8-bit grey image for corner detection: green channel of colour images."""
    img = np.asarray(image)
    g = img[..., 1] if img.ndim == 3 else img
    if g.dtype != np.uint8:
        g = cv2.normalize(g.astype(np.float32), None, 0, 255, cv2.NORM_MINMAX).astype(np.uint8)
    return g


DETECT_UPSCALE = 1  # 2 (before the saddle refinement): corners 0.15 -> 0.10 px, ring -0.24 -> -0.23 mm
SADDLE_RADIUS_PX = 2  # half-size of the saddle fit's window (5 x 5 samples)
SADDLE_SIGMA_PX = 1.0  # Gaussian smoothing before the fit
SADDLE_MAX_SHIFT_PX = 1.0  # a refined corner further than this from the detector's is not trusted


def refine_saddle(
    gray: np.ndarray, corners: np.ndarray, radius: int = SADDLE_RADIUS_PX,
    sigma: float = SADDLE_SIGMA_PX, iterations: int = 10,
) -> np.ndarray:
    """(N, 2) corners (col, row; pixel centres at integers) moved to the image's saddle point.

    The image is smoothed (Gaussian, ``sigma`` px); around each corner a quadratic
    surface z = a x^2 + b xy + c y^2 + d x + e y + f is fitted (Gaussian-weighted least
    squares) to the (2 radius + 1)^2 bilinear samples centred on the current estimate,
    and the estimate moves to the surface's saddle point until it stops (ROCHADE /
    Lucchese-Barreto style). A blurred X-junction is point-symmetric about its corner,
    so the fit centred on it is unbiased; the small window keeps the bias from the
    squares' curvature through the mirror small. Corners whose fit is not a saddle, or
    that move more than ``SADDLE_MAX_SHIFT_PX`` from the input, keep their input value.

    Measured on the simulator's design-rig set (seed 0, 15 views, squares 5-13 px):
    0.134 px RMS against the exact projection with ``findChessboardCornersSB`` alone,
    0.056 px after this refinement (docs/calibration.md).
    """
    img = cv2.GaussianBlur(gray.astype(np.float32), (0, 0), sigma) if sigma > 0 else gray.astype(np.float32)
    yy, xx = np.mgrid[-radius : radius + 1, -radius : radius + 1].astype(float)
    xs, ys = xx.ravel(), yy.ravel()
    wts = np.exp(-0.5 * (xs**2 + ys**2) / (radius / 1.5) ** 2)
    design = np.stack([xs * xs, xs * ys, ys * ys, xs, ys, np.ones_like(xs)], axis=1)
    solve = np.linalg.pinv((design * wts[:, None]).T @ design) @ (design * wts[:, None]).T  # (6, n*n)
    start = np.asarray(corners, float).reshape(-1, 2)
    p = start.copy()
    active = np.ones(len(p), bool)
    ok = np.ones(len(p), bool)
    for _ in range(iterations):
        idx = np.flatnonzero(active)
        if len(idx) == 0:
            break
        mx = (p[idx, 0][:, None] + xs[None]).astype(np.float32)
        my = (p[idx, 1][:, None] + ys[None]).astype(np.float32)
        patch = cv2.remap(img, mx, my, cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE).astype(float)
        a, b, c, d, e, _ = solve @ patch.T  # each (M,)
        det = 4.0 * a * c - b * b
        saddle = det < 0
        with np.errstate(invalid="ignore", divide="ignore"):
            dx = (-2.0 * c * d + b * e) / det
            dy = (b * d - 2.0 * a * e) / det
        step = np.stack([dx, dy], axis=1)
        good = saddle & np.all(np.isfinite(step), axis=1) & (np.abs(step).max(axis=1) <= radius)
        ok[idx[~good]] = False
        active[idx[~good]] = False
        gi = idx[good]
        p[gi] += step[good]
        active[gi[np.abs(step[good]).max(axis=1) < 1e-4]] = False
    ok &= np.linalg.norm(p - start, axis=1) <= SADDLE_MAX_SHIFT_PX
    return np.where(ok[:, None], p, start)


def detect_corners(
    image: np.ndarray, target: Target, upscale: int = DETECT_UPSCALE, refine: bool = True
) -> np.ndarray | None:
    """(cols*rows, 2) sub-pixel corners (col, row) of ``target`` in ``image``, or None.

    OpenCV's ``findChessboardCornersSB`` finds and orders the corners; ``refine`` then
    moves each to the image's saddle point (:func:`refine_saddle`). Against the exact
    projection (simulator, design-rig set): 0.134 px RMS with the detector alone, with
    per-view systematic parts that bend the fitted model; 0.056 px refined.
    ``upscale`` > 1 runs the detector on the image enlarged that many times (bicubic)
    and maps the corners back to the image's pixel centres (0.10 px at 2x unrefined).
    """
    flags = cv2.CALIB_CB_EXHAUSTIVE | cv2.CALIB_CB_ACCURACY
    gray0 = board_gray(image)
    gray = gray0
    if upscale > 1:
        gray = cv2.resize(gray0, None, fx=upscale, fy=upscale, interpolation=cv2.INTER_CUBIC)
    ok, corners = cv2.findChessboardCornersSB(gray, (target.cols, target.rows), flags=flags)
    if not ok or corners is None:
        return None
    out = (corners.reshape(-1, 2).astype(float) + 0.5) / upscale - 0.5
    return refine_saddle(gray0, out) if refine else out


def _rays_pose(rays: np.ndarray, obj: np.ndarray) -> tuple[np.ndarray, np.ndarray] | None:
    """Board pose (rvec, t) from unit rays (any central camera frame) by PnP on a virtual
    perspective view centred on the mean ray."""
    axis = rays.mean(axis=0)
    axis /= np.linalg.norm(axis)
    helper = np.array([1.0, 0.0, 0.0]) if abs(axis[0]) < 0.9 else np.array([0.0, 1.0, 0.0])
    x = np.cross(helper, axis)
    x /= np.linalg.norm(x)
    y = np.cross(axis, x)
    virt_from_cam = np.stack([x, y, axis])
    rv = rays @ virt_from_cam.T
    if np.any(rv[:, 2] <= 0.05):
        return None
    img = (rv[:, :2] / rv[:, 2:3]).astype(np.float64)
    ok, rvec, tvec = cv2.solvePnP(obj.astype(np.float64), img, np.eye(3), None, flags=cv2.SOLVEPNP_IPPE)
    if not ok:
        return None
    r_virt = cv2.Rodrigues(rvec)[0]
    r = virt_from_cam.T @ r_virt
    t = virt_from_cam.T @ tvec.ravel()
    return cv2.Rodrigues(r)[0].ravel(), t


def _unified_rays(px: np.ndarray, x: np.ndarray) -> np.ndarray:
    """Model-frame rays of pixels for parameter vector x (xi, fx, fy, cx, cy, k...)."""
    from omnipipe.camera.unified import UnifiedCamera

    intr = CameraIntrinsics(10**5, 10**5, float(x[3]), float(x[4]), float(x[1]))
    cam = UnifiedCamera(intr, UnifiedParams(float(x[0]), float(x[1]), float(x[2]), 0.0, *map(float, x[5:9])))
    return cam.unproject(px) * _MEI


@dataclass
class CameraCalibration:
    """Result of :func:`calibrate_unified`.

    Attributes:
        params: the unified model; cx, cy its principal point (px).
        per_image_rms_px: reprojection RMS per used image (px), keyed by image index.
        rms_px: overall reprojection RMS (px) over every corner.
        used: indices of the images whose target was found.
        model_from_board: (4, 4) board poses in the unified model frame (mm).
    """

    params: UnifiedParams
    cx: float
    cy: float
    per_image_rms_px: dict[int, float]
    rms_px: float
    used: list[int]
    model_from_board: dict[int, np.ndarray] = field(default_factory=dict)


def calibrate_unified(
    corners: dict[int, np.ndarray],
    target: Target,
    size: tuple[int, int],
    init: UnifiedParams | None = None,
    init_centre: tuple[float, float] | None = None,
    distortion: bool = True,
) -> CameraCalibration:
    """Bundle adjustment of the unified model and the board poses on detected corners.

    Args:
        corners: image index -> (K, 2) corners (col, row), K = cols*rows.
        target: the board.
        size: (width, height) of the images (px).
        init: a starting model (e.g. a nominal rig fitted to unified), or None: xi = 1
            and the focal scale scanned for the smallest reprojection error.
        init_centre: starting principal point, default the image centre.
        distortion: estimate k1, k2, p1, p2 (else fixed at 0).

    Raises:
        CalibrationError: fewer than MIN_VIEWS views, or the fit fails.
    """
    idx = sorted(corners)
    if len(idx) < MIN_VIEWS:
        raise CalibrationError(f"only {len(idx)} views with the target; at least {MIN_VIEWS} are needed")
    obj = target.object_points()
    w, h = size
    cx0, cy0 = init_centre if init_centre is not None else ((w - 1) / 2.0, (h - 1) / 2.0)
    x0, poses = _starting_model(corners, idx, obj, size, init, (cx0, cy0))
    x, p, res = _adjust_unified(corners, idx, obj, x0, poses, distortion)
    per = {i: float(np.sqrt(np.mean(np.sum(res[k] ** 2, axis=1)))) for k, i in enumerate(idx)}
    rms = float(np.sqrt(np.mean(np.sum(res**2, axis=2))))
    if not (math.isfinite(rms) and x[0] >= 0 and x[1] > 0 and x[2] > 0):
        raise CalibrationError(
            f"the calibration did not converge (xi < 0 or focal <= 0): the corners do not fit "
            f"one camera; is the board really {target.cols}x{target.rows} inner corners (check "
            "--target: a smaller one matches part of a bigger board)? nothing written"
        )
    poses_out = {}
    for k, i in enumerate(idx):
        m = np.eye(4)
        m[:3, :3] = cv2.Rodrigues(p[k, :3])[0]
        m[:3, 3] = p[k, 3:]
        poses_out[i] = m
    params = UnifiedParams(float(x[0]), float(x[1]), float(x[2]), 0.0, *map(float, x[5:9]))
    return CameraCalibration(params, float(x[3]), float(x[4]), per, rms, idx, poses_out)


def _seed_poses(
    corners: dict[int, np.ndarray], idx: list[int], obj: np.ndarray, x: np.ndarray
) -> tuple[list[np.ndarray], float]:
    """Board poses (rvec, t) of each view under intrinsics ``x`` (9,) and their squared
    reprojection error (px^2); ([], inf) when a view's rays do not give a pose."""
    poses, err = [], 0.0
    for i in idx:
        rays = _unified_rays(corners[i], x)
        sol = _rays_pose(rays, obj) if np.isfinite(rays).all() else None
        if sol is None:
            return [], math.inf
        rvec, t = sol
        pts = obj @ cv2.Rodrigues(rvec)[0].T + t
        pred, _ = unified_project(pts, x[0], x[1], x[2], x[3], x[4], 0.0, tuple(x[5:9]))
        e = np.nan_to_num(pred - corners[i], nan=1e3)
        err += float(np.sum(e * e))
        poses.append(np.concatenate([rvec, t]))
    return poses, err


def _starting_model(
    corners: dict[int, np.ndarray],
    idx: list[int],
    obj: np.ndarray,
    size: tuple[int, int],
    init: UnifiedParams | None,
    centre: tuple[float, float],
) -> tuple[np.ndarray, list[np.ndarray]]:
    """Starting intrinsics (xi, fx, fy, cx, cy, k1, k2, p1, p2) and board poses: ``init``,
    or xi = 1 with the focal scale scanned for the smallest reprojection error."""
    w, h = size
    cx0, cy0 = centre
    if init is not None:
        x0 = np.array([init.xi, init.fx, init.fy, cx0, cy0, init.k1, init.k2, init.p1, init.p2])
        poses, _ = _seed_poses(corners, idx, obj, x0)
    else:
        best: tuple[float, np.ndarray, list[np.ndarray]] | None = None
        for gamma in np.geomspace(0.05, 3.0, 48) * min(w, h):
            x = np.array([1.0, gamma, gamma, cx0, cy0, 0, 0, 0, 0])
            poses, err = _seed_poses(corners, idx, obj, x)
            if poses and (best is None or err < best[0]):
                best = (err, x, poses)
        if best is None:
            raise CalibrationError("no starting model explains the corners (give --init RIG.yaml)")
        _, x0, poses = best
    if not poses:
        raise CalibrationError("the starting model (--init) does not see the detected corners")
    return x0, poses


def _adjust_unified(
    corners: dict[int, np.ndarray],
    idx: list[int],
    obj: np.ndarray,
    x0: np.ndarray,
    poses: list[np.ndarray],
    distortion: bool,
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Least squares over intrinsics and poses: (x (9,), poses (V, 6), residuals (V, K, 2) px)."""
    n_int = 9
    n_corner = len(obj)
    free = np.ones(n_int, bool)
    if not distortion:
        free[5:] = False
    free_idx = np.flatnonzero(free)

    # Internally fx, fy are divided by (1 + xi): the small-angle scale, which the corners
    # fix well; xi and fx themselves are strongly correlated (slow convergence).
    y0 = x0.copy()
    y0[1:3] = x0[1:3] / (1.0 + x0[0])

    def unpack(v: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        y = y0.copy()
        y[free_idx] = v[: len(free_idx)]
        x = y.copy()
        x[1:3] = y[1:3] * (1.0 + y[0])
        return x, v[len(free_idx) :].reshape(-1, 6)

    def residual(v: np.ndarray) -> np.ndarray:
        x, p = unpack(v)
        out = []
        for k, i in enumerate(idx):
            r = cv2.Rodrigues(p[k, :3])[0]
            pts = obj @ r.T + p[k, 3:]
            pred, _ = unified_project(pts, x[0], x[1], x[2], x[3], x[4], 0.0, tuple(x[5:9]))
            out.append(np.nan_to_num(pred - corners[i], nan=1e3).ravel())
        return np.concatenate(out)

    nf = len(free_idx)
    sparsity = lil_matrix((2 * n_corner * len(idx), nf + 6 * len(idx)), dtype=int)
    for k in range(len(idx)):
        rows = slice(2 * n_corner * k, 2 * n_corner * (k + 1))
        sparsity[rows, :nf] = 1
        sparsity[rows, nf + 6 * k : nf + 6 * k + 6] = 1
    v0 = np.concatenate([y0[free_idx], np.concatenate(poses)])
    sol = least_squares(residual, v0, jac_sparsity=sparsity, x_scale="jac", method="trf",
                        ftol=1e-9, max_nfev=120)
    x, p = unpack(sol.x)
    return x, p, sol.fun.reshape(len(idx), n_corner, 2)


def mirror_annulus(images: list[np.ndarray], cx: float, cy: float) -> tuple[float | None, float]:
    """(radius_min, radius_max) (px) of the mirror's image: where the mean image is lit.

    The radial profile of the mean green level about (cx, cy): the rim is the outermost
    radius above half the profile's median, the blind centre the innermost (None when
    the centre is lit). A 2 px margin is kept inside both.
    """
    mean = np.mean([board_gray(im).astype(np.float32) for im in images], axis=0)
    h, w = mean.shape
    rows, cols = np.mgrid[0:h, 0:w]
    r = np.hypot(cols - cx, rows - cy).astype(int)
    counts = np.bincount(r.ravel())
    prof = np.bincount(r.ravel(), mean.ravel()) / np.maximum(counts, 1)
    lit = prof > 0.5 * np.median(prof[counts > 0])
    lit_idx = np.flatnonzero(lit)
    inscribed = min(cx + 0.5, w - 0.5 - cx, cy + 0.5, h - 0.5 - cy)
    if len(lit_idx) == 0:
        return None, float(inscribed)
    r_max = float(min(lit_idx[-1] - 2, inscribed)) if lit_idx[-1] < inscribed else float(inscribed)
    r_min = float(lit_idx[0] + 2) if lit_idx[0] > 3 else None
    return r_min, r_max


def calibrated_rig(cal: CameraCalibration, size: tuple[int, int], radii: tuple[float | None, float],
                   pixel_pitch: float | None = None, laser_from: Rig | None = None) -> Rig:
    """The calibrated camera as a rig (model ``unified``; laser copied or none)."""
    intr = CameraIntrinsics(
        width=size[0], height=size[1], cx=cal.cx, cy=cal.cy,
        f=0.5 * (cal.params.fx + cal.params.fy), pixel_pitch=pixel_pitch,
        radius_min=radii[0], radius_max=radii[1],
    )
    return Rig(camera=intr, mirror=None, laser=None if laser_from is None else laser_from.laser,
               model=cal.params)
