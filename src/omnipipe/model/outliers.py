"""Robust rejection of stray wall points (a false laser peak: a reflection, a speck).

A stray laser peak triangulates to a point far off the wall (tens of mm). One such
point inflates the wall's RMS, pulls the fitted cylinder and leaves a hole in the mesh
(the triangles to it have edges much longer than the rest and are dropped). The
points are therefore checked per ring (one station's laser ring, in the rig frame)
before they are integrated, analysed, meshed or exported.

**Rule.** Each ring's samples are ordered by their scan angle around the principal
point (the angle around the pipe axis). The local robust wall is the running median of
the samples' radius ``hypot(x, y)`` (distance from the rig's z axis, mm) over
``window`` neighbouring samples (cyclic). A sample's residual is its radius minus that
median; the ring's noise is ``1.4826 x MAD`` of the residuals. A sample *departs* when
``|residual| > max(k_mad x noise, floor_mm)``. A departure is an outlier only if it is
**isolated**:

* along the ring: its run of consecutive departing samples of the same sign is at most
  ``max_run`` samples long (with 720 scan lines that is 2 x 0.5 deg, about 1.8 mm of
  arc in a 200 mm pipe), and
* across the rings: neither neighbouring station's ring departs with the same sign
  within ``support_deg`` of its angle.

A real defect is a surface: the paper's 5 mm bulge spans about 6 samples of every ring
over its 100 mm length, so each of its departures is supported on both counts (the
running median over 41 samples, about 18 mm of arc, follows the wall, not the bulge;
where a wider defect fills half the window the median follows the defect and its
samples no longer depart at all). Both conditions must fail to remove a point: a
narrow defect present in one ring alone and narrower than ``max_run + 1`` samples
cannot be told from a stray peak and is removed (below the detection limit anyway).
"""

from __future__ import annotations

from dataclasses import dataclass, replace
from typing import TYPE_CHECKING

import numpy as np
from scipy.ndimage import median_filter

from omnipipe.config import bounded
from omnipipe.errors import ConfigError

if TYPE_CHECKING:
    from omnipipe.laser.extract import LaserRing


@dataclass(frozen=True)
class OutlierConfig:
    """Settings of the stray-point rule (module docstring).

    Attributes:
        window: samples of the running median (the local robust wall), odd.
        k_mad: a departure exceeds this many robust sigmas of the ring's residuals...
        floor_mm: ...and at least this (mm): never noise, never a defect's ramp.
        max_run: departures in runs of at most this many consecutive samples may be
            outliers (longer runs are a surface: kept).
        support_deg: a departure of the same sign in a neighbouring ring within this
            angle supports it (kept).
    """

    window: int = bounded(41, ge=3)
    k_mad: float = bounded(6.0, gt=0)
    floor_mm: float = bounded(1.0, gt=0)
    max_run: int = bounded(2, ge=1)
    support_deg: float = bounded(1.5, gt=0)

    def __post_init__(self) -> None:
        if self.window < 3 or self.window % 2 == 0:
            raise ConfigError("model.outliers.window", f"must be an odd number >= 3, got {self.window}")


def ring_departures(
    points_in_rig: np.ndarray, angle_rad: np.ndarray, config: OutlierConfig
) -> tuple[np.ndarray, np.ndarray]:
    """Residual (mm) and departure sign (-1, 0, +1) of each sample of one ring.

    Args:
        points_in_rig: (N, 3) the ring's points, mm.
        angle_rad: (N,) their scan angles.

    Returns:
        residual: (N,) radius minus the running median of the ring, mm (input order).
        sign: (N,) int8: +1 / -1 where the sample departs outwards / inwards, else 0.
    """
    n = len(points_in_rig)
    residual = np.zeros(n)
    sign = np.zeros(n, np.int8)
    if n < 5:
        return residual, sign
    order = np.argsort(angle_rad, kind="stable")
    radius = np.hypot(points_in_rig[order, 0], points_in_rig[order, 1])
    window = min(config.window, n - 1 + n % 2)  # odd, at most the ring
    res = radius - median_filter(radius, size=window, mode="wrap")
    noise = 1.4826 * float(np.median(np.abs(res - np.median(res))))
    limit = max(config.k_mad * noise, config.floor_mm)
    residual[order] = res
    sign[order] = np.where(res > limit, 1, np.where(res < -limit, -1, 0))
    return residual, sign


def _short_runs(sign_sorted: np.ndarray, max_run: int) -> np.ndarray:
    """(N,) bool: samples (in angle order, cyclic) in a run of equal nonzero sign of at
    most ``max_run`` samples."""
    n = len(sign_sorted)
    out = np.zeros(n, bool)
    calm = np.flatnonzero(sign_sorted == 0)
    if not len(calm):  # every sample departs: a surface, not stray points
        return out
    shift = int(calm[0])  # start the cycle on a calm sample: no run wraps around
    s = np.roll(sign_sorted, -shift)
    change = np.flatnonzero(np.diff(s) != 0) + 1
    starts = np.concatenate([[0], change])
    ends = np.concatenate([change, [n]])
    for a, b in zip(starts.tolist(), ends.tolist(), strict=True):
        if s[a] != 0 and b - a <= max_run:
            out[a:b] = True
    return np.roll(out, shift)


def _supported(angles: np.ndarray, signs: np.ndarray, other: tuple[np.ndarray, np.ndarray], tol: float) -> np.ndarray:
    """(n,) bool: a departure of ``other`` ((m,) angles, (m,) signs) of the same sign lies
    within ``tol`` rad (cyclic) of each of the (n,) departures."""
    o_ang, o_sign = other
    out = np.zeros(len(angles), bool)
    for s in (-1, 1):
        mine = signs == s
        theirs = np.sort(o_ang[o_sign == s])
        if not mine.any() or not len(theirs):
            continue
        a = angles[mine]
        i = np.searchsorted(theirs, a)
        near = np.minimum(
            np.abs(a - theirs[i % len(theirs)]), np.abs(a - theirs[(i - 1) % len(theirs)])
        )
        near = np.minimum(near, 2 * np.pi - near)
        out[mine] = near <= tol
    return out


def reject_outliers(
    points_in_rig: list[np.ndarray], angle_rad: list[np.ndarray], config: OutlierConfig
) -> list[np.ndarray]:
    """Per ring, the (N_k,) bool mask of the samples kept (module docstring).

    Args:
        points_in_rig: K rings' (N_k, 3) points, mm, in the order of the stations along
            the pipe (neighbours support each other).
        angle_rad: K (N_k,) scan angles of their samples.
    """
    signs = []
    for pts, ang in zip(points_in_rig, angle_rad, strict=True):
        signs.append(ring_departures(np.asarray(pts, float), np.asarray(ang, float), config)[1])
    departures = [
        (np.asarray(ang, float)[s != 0] % (2 * np.pi), s[s != 0])
        for ang, s in zip(angle_rad, signs, strict=True)
    ]
    tol = np.radians(config.support_deg)
    keep = []
    for k, (ang, s) in enumerate(zip(angle_rad, signs, strict=True)):
        mask = np.ones(len(s), bool)
        if np.any(s != 0):
            ang = np.asarray(ang, float)
            order = np.argsort(ang, kind="stable")
            short = np.zeros(len(s), bool)
            short[order] = _short_runs(s[order], config.max_run)
            cand = np.flatnonzero(short)
            a, sc = ang[cand] % (2 * np.pi), s[cand]
            support = np.zeros(len(cand), bool)
            for j in (k - 1, k + 1):
                if 0 <= j < len(signs):
                    support |= _supported(a, sc, departures[j], tol)
            mask[cand[~support]] = False
        keep.append(mask)
    return keep


def reject_ring_outliers(
    rings: list[LaserRing], config: OutlierConfig | None = None
) -> tuple[list[LaserRing], int]:
    """The stations' rings (in order along the pipe) without their stray samples, and
    how many samples were removed. Every per-sample array of a ring is masked alike."""
    cfg = config or OutlierConfig()
    keep = reject_outliers([r.points_in_rig for r in rings], [r.angle_rad for r in rings], cfg)
    out, removed = [], 0
    for ring, mask in zip(rings, keep, strict=True):
        if mask.all():
            out.append(ring)
            continue
        removed += int(np.count_nonzero(~mask))
        n = len(mask)
        fields = {
            name: getattr(ring, name)[mask]
            for name in ("pixels", "angle_rad", "confidence", "radius_sigma_px", "peak_width_px",
                         "points_in_rig", "sigma_mm")
            if len(getattr(ring, name)) == n
        }
        out.append(replace(ring, **fields))
    return out, removed
