"""Rangefinder calibration: the contract's ``rig.yaml`` as typed data classes (read,
validated and written by :mod:`omnipipe.rig_yaml`).

Frame conventions (DATA_CONTRACT.md section 2): the rig frame has its origin at the
mirror focus (single viewpoint), z along the mirror axis from the camera lens towards
the mirror, x along increasing image column, y along increasing image row. Lengths
are millimetres, pixel quantities pixels.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any

import numpy as np

LASER_CHANNELS = ("red", "green", "blue", "gray")
# Closest a laser plane may pass the focus (mm): the light section's range is
# proportional to this distance (Eq. 5), and a real laser plane lies outside the mirror,
# millimetres to centimetres away; anything closer is a calibration mistake.
MIN_LASER_DISTANCE_MM = 1.0
# Largest image side accepted (px): a bound, not a camera model.
MAX_IMAGE_SIDE_PX = 100_000


@dataclass(frozen=True)
class CameraIntrinsics:
    """The perspective camera that looks into the mirror.

    Attributes:
        width, height: image size (px).
        cx, cy: principal point, column and row (px); pixel centres are integers.
        f: image distance f of the paper's Eq. (1)-(3) (px).
        pixel_pitch: sensor pixel size (mm/px), used by the Eq. (9) error model;
            None when unknown.
        radius_min: blind centre radius (px) around the principal point, or None.
        radius_max: mirror-rim radius (px); nothing is imaged outside, or None.
    """

    width: int
    height: int
    cx: float
    cy: float
    f: float
    pixel_pitch: float | None = None
    radius_min: float | None = None
    radius_max: float | None = None


@dataclass(frozen=True)
class Mirror:
    """Hyperboloid mirror (X^2+Y^2)/a^2 - Z^2/b^2 = -1 (mm), Eq. (2): c = sqrt(a^2+b^2)."""

    a: float
    b: float

    @property
    def c(self) -> float:
        """Half the focal distance, Eq. (2) (mm)."""
        return math.hypot(self.a, self.b)


@dataclass(frozen=True)
class LaserPlane:
    """Laser light plane k1 x + k2 y + k3 z + k4 = 0 in the rig frame, Eq. (4).

    Attributes:
        k: (4,) the raw coefficients k1..k4 as calibrated (k4 in mm).
        channel: colour channel the laser shows in: red, green, blue or gray.
        offset_sigma_mm: 1-sigma uncertainty of the plane's distance from the focus (mm)
            as calibrated (rig.yaml ``laser.offset_sigma_mm``, written by ``omnipipe
            calibrate laser``); 0: not stated. Every length the light section measures
            scales with that distance, so it is a relative uncertainty of the whole metric
            (:attr:`scale_sigma_rel`).
    """

    k: tuple[float, float, float, float]
    channel: str = "red"
    offset_sigma_mm: float = 0.0

    @property
    def scale_sigma_rel(self) -> float:
        """Relative 1-sigma of all metric lengths from the plane's calibrated distance."""
        return self.offset_sigma_mm / self.distance_mm if self.distance_mm > 0 else 0.0

    @property
    def normal_in_rig(self) -> np.ndarray:
        """(3,) unit normal of the plane in the rig frame."""
        n = np.asarray(self.k[:3], dtype=float)
        return n / np.linalg.norm(n)

    @property
    def offset_mm(self) -> float:
        """Signed offset o of the normalised plane n.x + o = 0 (mm)."""
        return float(self.k[3] / np.linalg.norm(self.k[:3]))

    @property
    def distance_mm(self) -> float:
        """Distance of the plane from the focus: the paper's baseline l (mm)."""
        return abs(self.offset_mm)


CAMERA_MODELS = ("hyperboloid", "unified", "ocam")


@dataclass(frozen=True)
class UnifiedParams:
    """Mei's unified (sphere) model, the OpenCV ``omnidir`` / Kalibr ``omni`` convention.

    A direction X in the model frame goes to the unit sphere, is shifted by ``xi``
    along z and projected: m = (x, y) / (z + xi); radial-tangential distortion
    (k1, k2, p1, p2) acts on m; then col = fx mx + skew my + cx, row = fy my + cy
    (cx, cy in :class:`CameraIntrinsics`). The model frame is the rig frame with z
    reversed (the image centre sees +z there, -z in the rig frame): a reflection,
    see docs/camera_models.md.
    """

    xi: float
    fx: float
    fy: float
    skew: float = 0.0
    k1: float = 0.0
    k2: float = 0.0
    p1: float = 0.0
    p2: float = 0.0

    name = "unified"


@dataclass(frozen=True)
class OcamParams:
    """Scaramuzza's polynomial model as OCamCalib writes it (calib_results.txt).

    A pixel's offset from the centre, in OCamCalib's row-first order and through the
    inverse of the affine matrix [[c, d], [e, 1]], is (xp, yp) (px); its ray in
    OCamCalib's frame is (xp, yp, sum_i polynomial[i] r^i), r = |(xp, yp)|.
    ``inverse_polynomial`` (rho as a polynomial of the elevation theta = atan(z / |xy|))
    is OCamCalib's fast world2cam; it only seeds the exact inverse here.
    The centre (OCamCalib's xc = row, yc = col) is :class:`CameraIntrinsics` (cy, cx).
    """

    polynomial: tuple[float, ...]
    inverse_polynomial: tuple[float, ...] | None = None
    c: float = 1.0
    d: float = 0.0
    e: float = 0.0

    name = "ocam"


@dataclass(frozen=True)
class Rig:
    """A calibrated omni-directional rangefinder: camera, mirror and laser plane.

    Attributes:
        camera: image size, principal point, valid radii (and f for the hyperboloid).
        mirror: the hyperboloid (required for ``model`` None, optional otherwise).
        laser: the laser plane, or None for a camera-only rig (``reconstruct`` refuses it).
        model: the camera model's parameters: None for the hyperboloid of Eq. (1)-(3),
            :class:`UnifiedParams` or :class:`OcamParams`.
    """

    camera: CameraIntrinsics
    mirror: Mirror | None
    laser: LaserPlane | None
    model: UnifiedParams | OcamParams | None = None

    @property
    def camera_model(self) -> str:
        """``hyperboloid``, ``unified`` or ``ocam``."""
        return "hyperboloid" if self.model is None else self.model.name

    def to_dict(self) -> dict[str, Any]:
        """The rig as the contract's rig.yaml mapping (optional keys only when set)."""
        cam = self.camera
        camera: dict[str, Any] = {}
        if self.model is not None:
            camera["model"] = self.model.name
        camera.update(
            {"width": cam.width, "height": cam.height, "cx": float(cam.cx), "cy": float(cam.cy)}
        )
        if self.model is None:
            camera["f"] = float(cam.f)
        for key in ("pixel_pitch", "radius_min", "radius_max"):
            value = getattr(cam, key)
            if value is not None:
                camera[key] = float(value)
        if isinstance(self.model, UnifiedParams):
            m = self.model
            camera["unified"] = {
                "xi": float(m.xi),
                "fx": float(m.fx),
                "fy": float(m.fy),
                "skew": float(m.skew),
                "distortion": [float(m.k1), float(m.k2), float(m.p1), float(m.p2)],
            }
        elif isinstance(self.model, OcamParams):
            m = self.model
            block: dict[str, Any] = {"polynomial": [float(v) for v in m.polynomial]}
            if m.inverse_polynomial is not None:
                block["inverse_polynomial"] = [float(v) for v in m.inverse_polynomial]
            block["affine"] = [float(m.c), float(m.d), float(m.e)]
            camera["ocam"] = block
        out: dict[str, Any] = {"camera": camera}
        if self.mirror is not None:
            out["mirror"] = {"a": float(self.mirror.a), "b": float(self.mirror.b)}
        if self.laser is not None:
            out["laser"] = {
                "plane": [float(v) for v in self.laser.k],
                "channel": self.laser.channel,
            }
            if self.laser.offset_sigma_mm > 0:
                out["laser"]["offset_sigma_mm"] = float(self.laser.offset_sigma_mm)
        return out
