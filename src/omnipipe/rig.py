"""Rangefinder calibration: the contract's ``rig.yaml`` as typed data classes.

Frame conventions (DATA_CONTRACT.md section 2): the rig frame has its origin at the
mirror focus (single viewpoint), z along the mirror axis from the camera lens towards
the mirror, x along increasing image column, y along increasing image row. Lengths
are millimetres, pixel quantities pixels.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import yaml

from omnipipe.errors import ConfigError
from omnipipe.safe_yaml import load_yaml_file

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

    def signed_distance(self, points_in_rig: np.ndarray) -> np.ndarray:
        """Signed distance (mm) of (N, 3) points in the rig frame to the plane."""
        return np.asarray(points_in_rig) @ self.normal_in_rig + self.offset_mm


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

    def with_image_size(self, width: int, height: int) -> Rig:
        """The same rig with its image scaled to ``width`` x ``height`` pixels.

        Scales f, the principal point and the radii by the same factor (the width
        ratio); used by the simulator to make small test images of one rig.
        """
        s = width / self.camera.width
        cam = self.camera
        return Rig(
            camera=CameraIntrinsics(
                width=int(width),
                height=int(height),
                cx=(cam.cx + 0.5) * s - 0.5,
                cy=(cam.cy + 0.5) * s - 0.5,
                f=cam.f * s,
                pixel_pitch=None if cam.pixel_pitch is None else cam.pixel_pitch / s,
                radius_min=None if cam.radius_min is None else cam.radius_min * s,
                radius_max=None if cam.radius_max is None else cam.radius_max * s,
            ),
            mirror=self.mirror,
            laser=self.laser,
            model=_scaled_model(self.model, s),
        )

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


def _scaled_model(
    model: UnifiedParams | OcamParams | None, s: float
) -> UnifiedParams | OcamParams | None:
    """The model parameters of an image scaled by ``s`` (pixel lengths times s)."""
    if isinstance(model, UnifiedParams):
        return UnifiedParams(
            xi=model.xi, fx=model.fx * s, fy=model.fy * s, skew=model.skew * s,
            k1=model.k1, k2=model.k2, p1=model.p1, p2=model.p2,
        )
    if isinstance(model, OcamParams):
        # ray (xp, yp, P(r)) keeps its direction when xp, yp, r and P scale by s.
        poly = tuple(a * s ** (1 - i) for i, a in enumerate(model.polynomial))
        inv = None
        if model.inverse_polynomial is not None:
            inv = tuple(a * s for a in model.inverse_polynomial)
        return OcamParams(poly, inv, model.c, model.d, model.e)
    return model


def _section(
    data: dict[str, Any], name: str, source: str | None, prefix: str = ""
) -> dict[str, Any]:
    value = data.get(name)
    if value is None:
        raise ConfigError(prefix + name, "missing section", source)
    if not isinstance(value, dict):
        raise ConfigError(prefix + name, f"must be a mapping, got {type(value).__name__}", source)
    return value


def _number(
    section: dict[str, Any],
    prefix: str,
    key: str,
    source: str | None,
    *,
    required: bool = True,
    positive: bool = False,
    non_negative: bool = False,
) -> float | None:
    field = f"{prefix}.{key}"
    if key not in section or section[key] is None:
        if required:
            raise ConfigError(field, "missing", source)
        return None
    value = section[key]
    if isinstance(value, bool) or not isinstance(value, int | float):
        raise ConfigError(field, f"must be a number, got {value!r}", source)
    value = float(value)
    if not math.isfinite(value):
        raise ConfigError(field, f"must be finite, got {value}", source)
    if positive and value <= 0:
        raise ConfigError(field, f"must be > 0, got {value:g}", source)
    if non_negative and value < 0:
        raise ConfigError(field, f"must be >= 0, got {value:g}", source)
    return value


def _number_list(
    section: dict[str, Any], field: str, key: str, source: str | None, *, length: int | None = None
) -> list[float] | None:
    """An optional list of finite numbers ``section[key]`` (None when absent)."""
    value = section.get(key)
    if value is None:
        return None
    name = f"{field}.{key}"
    if not isinstance(value, list | tuple) or (length is not None and len(value) != length):
        what = f"{length} numbers" if length is not None else "numbers"
        raise ConfigError(name, f"must be a list of {what}, got {value!r}", source)
    out = []
    for i, v in enumerate(value):
        if isinstance(v, bool) or not isinstance(v, int | float) or not math.isfinite(v):
            raise ConfigError(f"{name}[{i}]", f"must be a finite number, got {v!r}", source)
        out.append(float(v))
    return out


def _unified_params(cam: dict[str, Any], source: str | None) -> UnifiedParams:
    block = _section(cam, "unified", source, prefix="camera.")
    xi = _number(block, "camera.unified", "xi", source, non_negative=True)
    fx = _number(block, "camera.unified", "fx", source, positive=True)
    fy = _number(block, "camera.unified", "fy", source, positive=True)
    skew = _number(block, "camera.unified", "skew", source, required=False) or 0.0
    dist = _number_list(block, "camera.unified", "distortion", source, length=4) or [0.0] * 4
    return UnifiedParams(xi, fx, fy, skew, *dist)  # type: ignore[arg-type]


def _ocam_params(cam: dict[str, Any], source: str | None) -> OcamParams:
    block = _section(cam, "ocam", source, prefix="camera.")
    poly = _number_list(block, "camera.ocam", "polynomial", source)
    if poly is None:
        raise ConfigError("camera.ocam.polynomial", "missing", source)
    if len(poly) < 2 or not poly[0] < 0.0:
        raise ConfigError(
            "camera.ocam.polynomial",
            "needs at least 2 coefficients a0, a1, ... with a0 < 0 (OCamCalib: the centre sees -z)",
            source,
        )
    inv = _number_list(block, "camera.ocam", "inverse_polynomial", source)
    affine = _number_list(block, "camera.ocam", "affine", source, length=3) or [1.0, 0.0, 0.0]
    c, d, e = affine
    if abs(c - d * e) < 1e-9:
        raise ConfigError("camera.ocam.affine", "matrix [[c, d], [e, 1]] is singular", source)
    return OcamParams(tuple(poly), None if inv is None else tuple(inv), c, d, e)


def rig_from_dict(data: Any, source: str | None = None) -> Rig:
    """Validate a rig.yaml mapping and build a :class:`Rig`.

    ``camera.model`` selects the camera model (``hyperboloid`` when absent: the
    contract's rig.yaml). A rig without a ``laser`` section loads with ``laser`` None
    (camera-only work: calibration, ``import-ocam``).

    Raises:
        ConfigError: naming the first missing or invalid field.
    """
    if not isinstance(data, dict):
        raise ConfigError("rig", "the file must hold a mapping with camera, mirror, laser", source)
    cam = _section(data, "camera", source)
    model_name = cam.get("model", "hyperboloid")
    if not isinstance(model_name, str) or model_name.lower() not in CAMERA_MODELS:
        raise ConfigError(
            "camera.model", f"must be one of {', '.join(CAMERA_MODELS)}, got {model_name!r}", source
        )
    model_name = model_name.lower()
    width = _number(cam, "camera", "width", source, positive=True)
    height = _number(cam, "camera", "height", source, positive=True)
    for key, value in (("width", width), ("height", height)):
        if value is not None and value != int(value):
            raise ConfigError(
                f"camera.{key}", f"must be a whole number of pixels, got {value}", source
            )
    params: UnifiedParams | OcamParams | None = None
    if model_name == "unified":
        params = _unified_params(cam, source)
        f_value = 0.5 * (params.fx + params.fy)
    elif model_name == "ocam":
        params = _ocam_params(cam, source)
        f_value = abs(params.polynomial[0])
    else:
        f_value = _number(cam, "camera", "f", source, positive=True)  # type: ignore[assignment]
    camera = CameraIntrinsics(
        width=int(width),  # type: ignore[arg-type]
        height=int(height),  # type: ignore[arg-type]
        cx=_number(cam, "camera", "cx", source),  # type: ignore[arg-type]
        cy=_number(cam, "camera", "cy", source),  # type: ignore[arg-type]
        f=float(f_value),
        pixel_pitch=_number(cam, "camera", "pixel_pitch", source, required=False, positive=True),
        radius_min=_number(cam, "camera", "radius_min", source, required=False, non_negative=True),
        radius_max=_number(cam, "camera", "radius_max", source, required=False, positive=True),
    )
    if (
        camera.radius_min is not None
        and camera.radius_max is not None
        and camera.radius_min >= camera.radius_max
    ):
        raise ConfigError(
            "camera.radius_min",
            f"must be < camera.radius_max ({camera.radius_min:g} >= {camera.radius_max:g})",
            source,
        )
    mirror: Mirror | None = None
    if model_name == "hyperboloid" or data.get("mirror") is not None:
        mir = _section(data, "mirror", source)
        mirror = Mirror(
            a=_number(mir, "mirror", "a", source, positive=True),  # type: ignore[arg-type]
            b=_number(mir, "mirror", "b", source, positive=True),  # type: ignore[arg-type]
        )
    if data.get("laser") is None:
        return Rig(camera=camera, mirror=mirror, laser=None, model=params)
    las = _section(data, "laser", source)
    plane = las.get("plane")
    if plane is None:
        raise ConfigError("laser.plane", "missing", source)
    if not isinstance(plane, list | tuple) or len(plane) != 4:
        raise ConfigError(
            "laser.plane", f"must be a list of 4 numbers k1 k2 k3 k4, got {plane!r}", source
        )
    k = []
    for i, value in enumerate(plane):
        if (
            isinstance(value, bool)
            or not isinstance(value, int | float)
            or not math.isfinite(value)
        ):
            raise ConfigError(
                f"laser.plane[{i}]", f"must be a finite number, got {value!r}", source
            )
        k.append(float(value))
    norm = math.hypot(*k[:3])
    if not norm > 1e-12 or not math.isfinite(norm):
        raise ConfigError("laser.plane", "normal (k1, k2, k3) must not be zero", source)
    distance = abs(k[3]) / norm
    if not distance >= MIN_LASER_DISTANCE_MM:
        raise ConfigError(
            "laser.plane",
            f"passes {distance:.3g} mm from the mirror focus; a laser plane must lie at least "
            f"{MIN_LASER_DISTANCE_MM:g} mm from it (k4 / |k1 k2 k3| is that distance)",
            source,
        )
    channel = las.get("channel", "red")
    if not isinstance(channel, str) or channel.lower() not in LASER_CHANNELS:
        raise ConfigError(
            "laser.channel", f"must be one of {', '.join(LASER_CHANNELS)}, got {channel!r}", source
        )
    offset_sigma = las.get("offset_sigma_mm", 0.0)
    if (
        isinstance(offset_sigma, bool)
        or not isinstance(offset_sigma, int | float)
        or not math.isfinite(offset_sigma)
        or offset_sigma < 0
    ):
        raise ConfigError(
            "laser.offset_sigma_mm", f"must be a finite number >= 0 (mm), got {offset_sigma!r}", source
        )
    laser = LaserPlane(
        k=(k[0], k[1], k[2], k[3]), channel=channel.lower(), offset_sigma_mm=float(offset_sigma)
    )
    check_ring_visible(camera, mirror, laser, source, model=params)
    return Rig(camera=camera, mirror=mirror, laser=laser, model=params)


def check_ring_visible(
    camera: CameraIntrinsics,
    mirror: Mirror | None,
    laser: LaserPlane,
    source: str | None = None,
    *,
    model: UnifiedParams | OcamParams | None = None,
) -> None:
    """Refuse a laser plane whose ring the mirror can never see whole.

    The rule. On a pipe wall of radius R coaxial with the mirror, a plane that crosses
    the mirror axis at z0 with its normal tilted by theta from the axis draws the ring
    z(phi) = z0 - R tan(theta) cos(phi - phi0), seen from the focus at elevation
    atan(z0 / R - tan(theta) cos(phi - phi0)). The camera sees a full ring between the
    elevations e_lo (blind centre, ``radius_min``) and e_hi (the largest circle about
    the principal point inside both the mirror rim and the image). The plane is
    accepted when some pipe wider than the mirror itself (R above the mirror's radius
    at the outer edge of that band) shows the whole ring in that band:
    tan(theta) <= min((t_hi - t_lo) / 2, t_hi - z0/R_min, -t_lo) for z0 < 0 (and the
    mirror image of it for z0 > 0), t = tan(e). A plane parallel to the axis
    (k3 = 0, e.g. ``[1, 0, 0, 82]``) never is: its "ring" runs along the pipe without end.
    For the paper's rig this allows a tilt of up to about 48 degrees. Without a
    hyperboloid (``unified``/``ocam`` models and no ``mirror`` section) the mirror's
    size is unknown and the z0 / R_min term is left out.

    Raises:
        ConfigError: ``laser.plane``, with the tilt, where it crosses the axis and the
            largest tilt this rig allows.
    """
    from omnipipe.camera.factory import camera_from_parts

    k = np.asarray(laser.k, dtype=float)
    n = k[:3] / np.linalg.norm(k[:3])
    tilt = math.degrees(math.acos(min(1.0, abs(float(n[2])))))
    cam = camera_from_parts(camera, mirror, model)
    r_full = min(
        cam.radius_max,
        camera.cx + 0.5,
        camera.width - 0.5 - camera.cx,
        camera.cy + 0.5,
        camera.height - 0.5 - camera.cy,
    )
    if not r_full > cam.radius_min:
        raise ConfigError(
            "camera",
            f"no full circle of the mirror image fits between radius_min ({cam.radius_min:g} px) "
            f"and the image border or radius_max ({r_full:g} px)",
            source,
        )
    rays = cam.unproject(
        np.array(
            [[camera.cx + max(cam.radius_min, 1e-6), camera.cy], [camera.cx + r_full, camera.cy]]
        )
    )
    if not np.isfinite(rays).all():
        raise ConfigError("camera.radius_max", "lies beyond the mirror's asymptote", source)
    t_lo, t_hi = (float(r[2] / math.hypot(r[0], r[1])) if r[0] > 0 else -math.inf for r in rays)
    if model is None and mirror is not None:
        # Mirror radius at the outer edge of the full ring: the ray meets the mirror
        # sheet (X^2+Y^2)/a^2 - (Z+c)^2/b^2 = -1 at t d, t = a^2 / (b - c d_z).
        rim = rays[1]
        a, b, c = mirror.a, mirror.b, mirror.c
        t_rim = a * a / (b - c * float(rim[2]))
        r_mirror = t_rim * math.hypot(rim[0], rim[1])
    else:
        r_mirror = math.inf
    if abs(n[2]) < 1e-12:
        tan_max, z0 = -1.0, math.nan
    else:
        z0 = -float(k[3] / k[2])
        ratio = z0 / r_mirror  # z0 / R at the narrowest pipe the robot fits in
        if z0 < 0:
            tan_max = min((t_hi - t_lo) / 2.0, t_hi - ratio, -t_lo)
        else:
            tan_max = min((t_hi - t_lo) / 2.0, ratio - t_lo, t_hi)
    tan_tilt = math.tan(math.radians(tilt)) if tilt < 90.0 else math.inf
    if tan_tilt <= tan_max:
        return
    band = (
        f"elevations {math.degrees(math.atan(t_lo)):.1f} to {math.degrees(math.atan(t_hi)):.1f} deg"
    )
    if tan_max < 0:
        where = (
            "parallel to the mirror axis"
            if math.isnan(z0)
            else f"crossing the axis at z = {z0:g} mm"
        )
        raise ConfigError(
            "laser.plane",
            f"the mirror can never see this laser's ring ({where}; the mirror sees {band})",
            source,
        )
    raise ConfigError(
        "laser.plane",
        f"tilted {tilt:.1f} deg from the mirror axis: its ring on a pipe wider than the mirror "
        f"(radius > {r_mirror:.0f} mm) never lies whole within the mirror's view ({band}); "
        f"this rig allows at most {math.degrees(math.atan(tan_max)):.1f} deg",
        source,
    )


def load_rig(path: str | Path) -> Rig:
    """Read and validate a rig.yaml file.

    The file is parsed by :func:`omnipipe.safe_yaml.load_yaml_file` (bounded size and
    alias expansion), then validated by :func:`rig_from_dict`.

    Raises:
        ConfigError: the file is missing, not YAML, too large, or a field is invalid.
    """
    path = Path(path)
    return rig_from_dict(load_yaml_file(path, "rig"), str(path))


def save_rig(rig: Rig, path: str | Path) -> None:
    """Write ``rig`` as a contract rig.yaml."""
    text = yaml.safe_dump(rig.to_dict(), sort_keys=False, default_flow_style=None)
    Path(path).write_text(text, encoding="utf-8")
