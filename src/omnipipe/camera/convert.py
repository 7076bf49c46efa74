"""Re-express a camera in another model by fitting that model to its rays.

Used to convert a rig (e.g. the simulator's hyperboloid) to the ``unified`` or ``ocam``
model, and to seed calibrations. Both fits sample the valid annulus, take the source
camera's rays and fit the target model's pixels of those rays (least squares, px).
"""

from __future__ import annotations

from dataclasses import replace

import numpy as np
from scipy.optimize import least_squares

from omnipipe.camera.base import CameraModel
from omnipipe.camera.factory import camera_from_rig
from omnipipe.camera.ocam import OcamCamera
from omnipipe.camera.unified import unified_project
from omnipipe.errors import ConfigError
from omnipipe.rig import OcamParams, Rig, UnifiedParams


def _samples(camera: CameraModel, n_radii: int = 40, n_angles: int = 64) -> np.ndarray:
    """(M, 2) pixels on circles across the valid annulus (inside the image)."""
    lo = max(camera.radius_min, 0.02 * camera.radius_max)
    radii = np.linspace(lo, camera.radius_max, n_radii)
    phi = np.linspace(0.0, 2.0 * np.pi, n_angles, endpoint=False)
    rr, pp = np.meshgrid(radii, phi)
    px = np.stack([camera.cx + rr.ravel() * np.cos(pp.ravel()),
                   camera.cy + rr.ravel() * np.sin(pp.ravel())], axis=1)
    return px[camera.is_valid_pixel(px)]


def fit_unified(camera: CameraModel, distortion: bool = False) -> tuple[UnifiedParams, float, float, float]:
    """Unified-model parameters reproducing ``camera``'s rays.

    Returns:
        (params, cx, cy, rms_px): the parameters, principal point (px) and the RMS
        pixel residual of the fit over the valid annulus.
    """
    px = _samples(camera)
    rays = camera.unproject(px)
    ok = np.isfinite(rays).all(axis=1)
    px, rays = px[ok], rays[ok]
    model = rays * np.array([1.0, 1.0, -1.0])
    rho = np.hypot(px[:, 0] - camera.cx, px[:, 1] - camera.cy)
    best = None
    for xi in np.linspace(0.2, 2.0, 37):  # 1-D scan for a seed: f by linear least squares
        w = xi if xi <= 1.0 else 1.0 / xi
        m = np.hypot(model[:, 0], model[:, 1]) / (model[:, 2] + xi)
        good = model[:, 2] > -w
        if good.sum() < 10:
            continue
        f = float(m[good] @ rho[good] / (m[good] @ m[good]))
        err = float(np.sum((f * m[good] - rho[good]) ** 2) + 1e6 * (~good).sum())
        if best is None or err < best[0]:
            best = (err, xi, f)
    if best is None:
        raise ConfigError(
            "camera: fewer than 10 of its valid pixels' rays fit a unified model at any xi; "
            "it cannot be converted"
        )
    n_dist = 4 if distortion else 0
    x0 = np.array([best[1], best[2], best[2], camera.cx, camera.cy] + [0.0] * n_dist)

    def residual(x: np.ndarray) -> np.ndarray:
        k = tuple(x[5:9]) if distortion else (0.0, 0.0, 0.0, 0.0)
        pred, _ = unified_project(model, x[0], x[1], x[2], x[3], x[4], 0.0, k)  # type: ignore[arg-type]
        return np.nan_to_num((pred - px).ravel(), nan=1e3)

    sol = least_squares(residual, x0, method="lm", x_scale="jac")
    x = sol.x
    rms = float(np.sqrt(np.mean(sol.fun**2) * 2))
    k = tuple(x[5:9]) if distortion else (0.0, 0.0, 0.0, 0.0)
    params = UnifiedParams(float(x[0]), float(x[1]), float(x[2]), 0.0, *map(float, k))
    return params, float(x[3]), float(x[4]), rms


def ocam_inverse_polynomial(poly: np.ndarray, r_max: float, degree: int = 14) -> np.ndarray:
    """OCamCalib's world2cam polynomial rho(theta) for ``poly`` over r in [0, r_max]."""
    r = np.linspace(0.0, r_max, 400)
    theta = np.arctan2(np.polynomial.polynomial.polyval(r, poly), r)
    return np.polynomial.polynomial.polyfit(theta, r, degree)


def fit_ocam(camera: CameraModel, degree: int = 5) -> tuple[OcamParams, float, float, float]:
    """OCamCalib polynomial (a1 = 0, no affine term) reproducing ``camera``'s rays.

    The centre is ``camera``'s (cx, cy); P(r) = r z / |xy| per sample, fitted linearly
    in r / radius_max (for conditioning) and rescaled.

    Returns:
        (params, cx, cy, rms_px): parameters, centre and RMS pixel residual.
    """
    px = _samples(camera)
    rays = camera.unproject(px)
    ok = np.isfinite(rays).all(axis=1)
    px, rays = px[ok], rays[ok]
    r = np.hypot(px[:, 0] - camera.cx, px[:, 1] - camera.cy)
    p = r * rays[:, 2] / np.hypot(rays[:, 0], rays[:, 1])
    scale = camera.radius_max
    s = r / scale
    powers = [0, *range(2, degree + 1)]
    design = np.stack([s**i for i in powers], axis=1)
    coef, *_ = np.linalg.lstsq(design, p / scale, rcond=None)
    poly = np.zeros(degree + 1)
    for c, i in zip(coef, powers, strict=True):
        poly[i] = c * scale ** (1 - i)
    inv = ocam_inverse_polynomial(poly, camera.radius_max * 1.02)
    params = OcamParams(tuple(float(v) for v in poly), tuple(float(v) for v in inv))
    fitted = OcamCamera(replace(camera.intrinsics), params)
    pred, _ = fitted.project(rays)
    rms = float(np.sqrt(np.nanmean(np.sum((pred - px) ** 2, axis=1))))
    return params, camera.cx, camera.cy, rms


def rig_in_model(rig: Rig, model: str, **kwargs: object) -> tuple[Rig, float]:
    """``rig`` re-expressed in ``model`` (``unified`` or ``ocam``), same laser and radii.

    Returns:
        (rig, rms_px): the converted rig and the fit's RMS pixel residual.
    """
    camera = camera_from_rig(rig)
    if model == "unified":
        params, cx, cy, rms = fit_unified(camera, **kwargs)  # type: ignore[arg-type]
    elif model == "ocam":
        params, cx, cy, rms = fit_ocam(camera, **kwargs)  # type: ignore[arg-type]
    else:
        raise ConfigError(f"unknown target model {model!r}")
    f = 0.5 * (params.fx + params.fy) if model == "unified" else abs(params.polynomial[0])  # type: ignore[union-attr]
    cam = replace(rig.camera, cx=cx, cy=cy, f=float(f))
    return Rig(camera=cam, mirror=None, laser=rig.laser, model=params), rms
