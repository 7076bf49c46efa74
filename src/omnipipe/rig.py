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
    """

    k: tuple[float, float, float, float]
    channel: str = "red"

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


@dataclass(frozen=True)
class Rig:
    """A calibrated omni-directional rangefinder: camera, mirror and laser plane."""

    camera: CameraIntrinsics
    mirror: Mirror
    laser: LaserPlane

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
        )

    def to_dict(self) -> dict[str, Any]:
        """The rig as the contract's rig.yaml mapping (optional keys only when set)."""
        cam = self.camera
        camera: dict[str, Any] = {
            "width": cam.width,
            "height": cam.height,
            "cx": float(cam.cx),
            "cy": float(cam.cy),
            "f": float(cam.f),
        }
        for key in ("pixel_pitch", "radius_min", "radius_max"):
            value = getattr(cam, key)
            if value is not None:
                camera[key] = float(value)
        return {
            "camera": camera,
            "mirror": {"a": float(self.mirror.a), "b": float(self.mirror.b)},
            "laser": {
                "plane": [float(v) for v in self.laser.k],
                "channel": self.laser.channel,
            },
        }


def _section(data: dict[str, Any], name: str, source: str | None) -> dict[str, Any]:
    value = data.get(name)
    if value is None:
        raise ConfigError(name, "missing section", source)
    if not isinstance(value, dict):
        raise ConfigError(name, f"must be a mapping, got {type(value).__name__}", source)
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


def rig_from_dict(data: Any, source: str | None = None) -> Rig:
    """Validate a rig.yaml mapping and build a :class:`Rig`.

    Raises:
        ConfigError: naming the first missing or invalid field.
    """
    if not isinstance(data, dict):
        raise ConfigError("rig", "the file must hold a mapping with camera, mirror, laser", source)
    cam = _section(data, "camera", source)
    width = _number(cam, "camera", "width", source, positive=True)
    height = _number(cam, "camera", "height", source, positive=True)
    for key, value in (("width", width), ("height", height)):
        if value is not None and value != int(value):
            raise ConfigError(
                f"camera.{key}", f"must be a whole number of pixels, got {value}", source
            )
    camera = CameraIntrinsics(
        width=int(width),  # type: ignore[arg-type]
        height=int(height),  # type: ignore[arg-type]
        cx=_number(cam, "camera", "cx", source),  # type: ignore[arg-type]
        cy=_number(cam, "camera", "cy", source),  # type: ignore[arg-type]
        f=_number(cam, "camera", "f", source, positive=True),  # type: ignore[arg-type]
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
    mir = _section(data, "mirror", source)
    mirror = Mirror(
        a=_number(mir, "mirror", "a", source, positive=True),  # type: ignore[arg-type]
        b=_number(mir, "mirror", "b", source, positive=True),  # type: ignore[arg-type]
    )
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
    laser = LaserPlane(k=(k[0], k[1], k[2], k[3]), channel=channel.lower())
    check_ring_visible(camera, mirror, laser, source)
    return Rig(camera=camera, mirror=mirror, laser=laser)


def check_ring_visible(
    camera: CameraIntrinsics, mirror: Mirror, laser: LaserPlane, source: str | None = None
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
    For the paper's rig this allows a tilt of up to about 48 degrees.

    Raises:
        ConfigError: ``laser.plane``, with the tilt, where it crosses the axis and the
            largest tilt this rig allows.
    """
    from omnipipe.camera.hyperboloid import OmniCamera

    k = np.asarray(laser.k, dtype=float)
    n = k[:3] / np.linalg.norm(k[:3])
    tilt = math.degrees(math.acos(min(1.0, abs(float(n[2])))))
    cam = OmniCamera(camera, mirror)
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
    # Mirror radius at the outer edge of the full ring: the ray meets the mirror sheet
    # (X^2+Y^2)/a^2 - (Z+c)^2/b^2 = -1 at t d, t = a^2 / (b - c d_z).
    rim = rays[1]
    a, b, c = mirror.a, mirror.b, mirror.c
    t_rim = a * a / (b - c * float(rim[2]))
    r_mirror = t_rim * math.hypot(rim[0], rim[1])
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
