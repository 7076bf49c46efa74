"""The contract's ``rig.yaml`` (DATA_CONTRACT.md section 2): read, validated, written.

Every field is checked at load time with an error naming it; the laser plane also by
:func:`omnipipe.camera.visibility.check_ring_visible` (the mirror must be able to see
its ring whole), which needs the camera model, hence this module sits above
:mod:`omnipipe.camera` while the data classes (:mod:`omnipipe.rig`) sit below it.
"""

from __future__ import annotations

import math
from pathlib import Path
from typing import Any

import yaml

from omnipipe.camera.visibility import check_ring_visible
from omnipipe.errors import ConfigError
from omnipipe.rig import (
    CAMERA_MODELS,
    LASER_CHANNELS,
    MIN_LASER_DISTANCE_MM,
    CameraIntrinsics,
    LaserPlane,
    Mirror,
    OcamParams,
    Rig,
    UnifiedParams,
)
from omnipipe.safe_yaml import load_yaml_file


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
    model_name = _camera_model_name(cam, source)
    camera, params = _camera_from_dict(cam, model_name, source)
    mirror: Mirror | None = None
    if model_name == "hyperboloid" or data.get("mirror") is not None:
        mir = _section(data, "mirror", source)
        mirror = Mirror(
            a=_number(mir, "mirror", "a", source, positive=True),  # type: ignore[arg-type]
            b=_number(mir, "mirror", "b", source, positive=True),  # type: ignore[arg-type]
        )
    if data.get("laser") is None:
        return Rig(camera=camera, mirror=mirror, laser=None, model=params)
    laser = _laser_from_dict(_section(data, "laser", source), source)
    check_ring_visible(camera, mirror, laser, source, model=params)
    return Rig(camera=camera, mirror=mirror, laser=laser, model=params)


def _camera_model_name(cam: dict[str, Any], source: str | None) -> str:
    """``camera.model`` in lower case (``hyperboloid`` when absent), checked against CAMERA_MODELS."""
    model_name = cam.get("model", "hyperboloid")
    if not isinstance(model_name, str) or model_name.lower() not in CAMERA_MODELS:
        raise ConfigError(
            "camera.model", f"must be one of {', '.join(CAMERA_MODELS)}, got {model_name!r}", source
        )
    return model_name.lower()


def _camera_from_dict(
    cam: dict[str, Any], model_name: str, source: str | None
) -> tuple[CameraIntrinsics, UnifiedParams | OcamParams | None]:
    """The ``camera`` section: intrinsics (px) and the unified / OCam parameters (None: hyperboloid)."""
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
    return camera, params


def _laser_plane_k(las: dict[str, Any], source: str | None) -> list[float]:
    """``laser.plane`` (k1, k2, k3, k4): four finite numbers, a non-zero normal, far enough from the focus."""
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
    return k


def _laser_from_dict(las: dict[str, Any], source: str | None) -> LaserPlane:
    """The ``laser`` section: plane, channel and offset sigma (mm), validated."""
    k = _laser_plane_k(las, source)
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
    return LaserPlane(
        k=(k[0], k[1], k[2], k[3]), channel=channel.lower(), offset_sigma_mm=float(offset_sigma)
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
