"""Whether the mirror can see a laser plane's ring whole: the rig's load-time check."""

from __future__ import annotations

import math

import numpy as np

from omnipipe.camera.factory import camera_from_parts
from omnipipe.errors import ConfigError
from omnipipe.rig import CameraIntrinsics, LaserPlane, Mirror, OcamParams, UnifiedParams


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
    k = np.asarray(laser.k, dtype=float)
    n = k[:3] / np.linalg.norm(k[:3])
    tilt = math.degrees(math.acos(min(1.0, abs(float(n[2])))))
    t_lo, t_hi, r_mirror = _full_ring_band(camera, mirror, model, source)
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
    _refuse_plane(tilt, z0, tan_max, (t_lo, t_hi), r_mirror, source)


def _full_ring_band(
    camera: CameraIntrinsics,
    mirror: Mirror | None,
    model: UnifiedParams | OcamParams | None,
    source: str | None,
) -> tuple[float, float, float]:
    """(t_lo, t_hi, r_mirror): tangents of the elevations bounding the band of full rings
    the camera sees, and the mirror's radius (mm) at its outer edge (inf without a
    hyperboloid).

    Raises:
        ConfigError: no full circle fits (``camera``) or ``radius_max`` is past the asymptote.
    """
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
    return t_lo, t_hi, r_mirror


def _refuse_plane(
    tilt: float,
    z0: float,
    tan_max: float,
    band_t: tuple[float, float],
    r_mirror: float,
    source: str | None,
) -> None:
    """Raise the ``laser.plane`` ConfigError: never visible (``tan_max`` < 0) or tilted too far.

    ``tilt`` in degrees, ``z0`` where the plane crosses the axis (mm, nan: parallel)."""
    t_lo, t_hi = band_t
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
