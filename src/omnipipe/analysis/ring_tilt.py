"""Rings tilted against the centreline: an oblique cut, or a centreline drawn off the pipe.

Each laser ring lies in a plane (the rig's light section). Where the fitted centreline
runs at an angle e to that plane's normal, one of two things is true:

* the ring really is oblique to the pipe (the rig leans in it, or its laser ring lies
  ahead of the rig in a bend): in its own plane the ring is the pipe's section stretched
  by 1 / cos e along the tilt; projected across the centreline it is the section itself.
  The stations measure the pipe.
* the ring is square to the pipe and the centreline is off it: the camera motion drifts
  sideways, so the ring centres run obliquely through a straight pipe (random-features
  seed 32: 5 mm sideways over a 32 mm run, e 6-8 deg). In its own plane the ring is the
  section; projected across the centreline its extent along the tilt shrinks by cos e:
  an extra ovality 1 - cos e with the minor axis along the tilt, the mean diameter
  D (1 + cos e) / 2, too small by D (1 - cos e) / 2.

A round pipe tells them apart from the rings: the stations' ovality (magnitude and
direction) either is that extra ovality or is not. :func:`tilt_check` compares the two
explanations station by station over a few neighbours; a station neither explanation
decides (an oval pipe, noise as large as the tilt's signal) takes its nearest decided
station's, and half the correction goes into its sigma and the headline's, so the stated
sigma covers either truth. An oval pipe whose ovality across the centreline happens to
equal the extra ovality in size and axis is taken for square rings.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, replace

import numpy as np

from omnipipe.analysis.feature_types import Ovality, Stretch
from omnipipe.analysis.stations import Station

DECISIVE_CHI2 = 9.0
"""One explanation wins when its chi-square over a station's neighbourhood's ovality
vectors is this much below the other's (a likelihood ratio of 90: 3 sigma)."""

FIT_RESIDUAL_SIGMA = 3.0
"""The winning explanation must leave the neighbourhood's ovality vectors within this
many sigma (their median): otherwise the pipe itself is oval there and the tilt is not
decided."""

OVALITY_FLOOR = 0.002
"""The smallest sigma (a fraction) of a station's ovality vector in the test: the ring
shapes' scatter that no fit sigma holds (random-features seed 1's round stretch read
through rings 7 deg oblique: 0.0-0.5 % against fit sigmas of 0.05 %)."""

NEIGHBOURS = 2
"""The test pools each station with this many stations either side (the camera motion's
drift changes along the run: seed 1's rings are oblique cuts over one stretch, square to
the pipe under a drifting centreline over the next)."""


TANGENT_SIGMA_RAD = math.radians(2.0)
"""1-sigma of the centreline's direction at a station against the pipe's axis, as a
model: the tangents' own scatter (0.0-0.1 deg on the random-features runs) holds none
of the camera motion's rotation error nor a section centre's pull. A ring oblique by e
to the tangent, measured about an axis off the pipe's by d in the tilt's plane, reads an
ovality of tan(e) d + d^2 / 2 (a round pipe, 270 deg of wall: 0.6-0.9 % at e = 8 deg,
d = 3 deg). The 2 deg and its coverage on the features bench: benchmarks/RESULTS.md
(ana27)."""


@dataclass(frozen=True)
class TiltCheck:
    """The rings' tilt against the centreline and which explanation holds at each station.

    Attributes:
        tilt_rad: (S,) per station the angle between its ring's plane normal and the
            centreline's tangent.
        direction_rad: (S,) the tilt's direction around the axis (the station angle
            convention: from the centreline's normal towards its binormal).
        square_weight: (S,) 1: the ring is square to the pipe (the centreline is off
            it); 0: an oblique cut (the station stands). A station the test does not
            decide takes its nearest decided station's (the cause changes smoothly along
            the run: a drifting motion, a rig leaning through a bend), 0.5 when the run
            decides none.
        undecided: (S,) the stations the test did not decide themselves.
    """

    tilt_rad: np.ndarray
    direction_rad: np.ndarray
    square_weight: np.ndarray
    undecided: np.ndarray

    def shrink_mm(self, diameters: np.ndarray) -> np.ndarray:
        """(S,) the mean diameter (mm) a ring square to the pipe loses across the
        centreline: D (1 - cos e) / (1 + cos e) of the measured D."""
        c = np.cos(self.tilt_rad)
        return np.asarray(diameters, float) * (1.0 - c) / (1.0 + c)

    def ambiguity_mm(self, diameters: np.ndarray) -> float:
        """The run's diameter sigma (mm) from the undecided stations: the stations' mean
        of half their shrink where not decided (0 where decided); shared by neighbours,
        so it does not average down."""
        s = self.shrink_mm(diameters)
        return float(np.mean(np.where(self.undecided, 0.5 * s, 0.0))) if len(s) else 0.0


def ring_tilts(
    points: np.ndarray, rings: list[np.ndarray], tangent: np.ndarray, normal: np.ndarray, binormal: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """Each ring's plane tilt against the centreline (radians) and its direction.

    Args:
        points: (N, 3) ring points, world frame, mm.
        rings: per station the indices of its ring's points (at least 3).
        tangent, normal, binormal: (S, 3) the centreline's frame at each station.

    Returns:
        ((S,) tilt in [0, pi/2], (S,) direction from ``normal`` towards ``binormal``).
    """
    tilt, direction = np.zeros(len(rings)), np.zeros(len(rings))
    for j, on in enumerate(rings):
        q = points[on]
        _, _, vt = np.linalg.svd(q - q.mean(axis=0), full_matrices=False)
        n = vt[2] if float(vt[2] @ tangent[j]) >= 0.0 else -vt[2]
        tilt[j] = math.acos(min(1.0, float(n @ tangent[j])))
        direction[j] = math.atan2(float(n @ binormal[j]), float(n @ normal[j]))
    return tilt, direction


def _vectors(stations: list[Station]) -> tuple[np.ndarray, np.ndarray]:
    """(S, 2) the stations' ovality vectors ov (cos 2a, sin 2a) and (S,) their sigmas
    (NaN rows where a station has no ovality)."""
    ov = np.array([s.ovality for s in stations], float)
    a = np.radians(np.array([s.ovality_angle_deg for s in stations], float))
    sig = np.array([s.ovality_sigma for s in stations], float)
    return ov[:, None] * np.column_stack([np.cos(2 * a), np.sin(2 * a)]), sig


def tilt_vectors(tilt: np.ndarray, direction: np.ndarray) -> np.ndarray:
    """(S, 2) the ovality vectors a ring square to the pipe shows across a centreline
    tilted ``tilt`` to it: 1 - cos e, major axis across the tilt's ``direction``."""
    mag = 1.0 - np.cos(tilt)
    return -mag[:, None] * np.column_stack([np.cos(2 * direction), np.sin(2 * direction)])


def tilt_check(
    stations: list[Station], tilt: np.ndarray, direction: np.ndarray, shared_ovality: float = 0.0
) -> TiltCheck:
    """Decide, station by station, whether the rings are square to the pipe or oblique cuts.

    Args:
        stations: the measured stations (ovality, its angle and sigma across the
            centreline), in order along the run.
        tilt, direction: (S,) :func:`ring_tilts` of their rings.
        shared_ovality: the ring-shape error every station shares (a fraction), added
            to each station's ovality sigma (with :data:`OVALITY_FLOOR`).

    Each station with its :data:`NEIGHBOURS` either side that have an ovality gives
    chi-squares of their ovality vectors against zero (oblique cuts of a round pipe) and
    against :func:`tilt_vectors` (square rings); one wins by :data:`DECISIVE_CHI2` when
    its residuals stay within :data:`FIT_RESIDUAL_SIGMA` (median); otherwise (an oval
    pipe, or no signal) the station is undecided and takes its nearest decided
    station's weight (0.5 when none is decided).
    """
    m, sig = _vectors(stations)
    ok = np.isfinite(m).all(axis=1) & np.isfinite(sig)
    s = np.hypot(np.hypot(np.where(ok, sig, 1.0), shared_ovality), OVALITY_FLOOR)
    square = np.linalg.norm(m - tilt_vectors(tilt, direction), axis=1) / s
    oblique = np.linalg.norm(m, axis=1) / s
    w = np.full(len(stations), 0.5)
    for j in range(len(stations)):
        near = np.zeros(len(stations), bool)
        near[max(0, j - NEIGHBOURS) : j + NEIGHBOURS + 1] = True
        near &= ok
        if near.sum() < 3:
            continue
        chi_sq, chi_ob = float(np.sum(square[near] ** 2)), float(np.sum(oblique[near] ** 2))
        if chi_sq + DECISIVE_CHI2 <= chi_ob and np.median(square[near]) <= FIT_RESIDUAL_SIGMA:
            w[j] = 1.0
        elif chi_ob + DECISIVE_CHI2 <= chi_sq and np.median(oblique[near]) <= FIT_RESIDUAL_SIGMA:
            w[j] = 0.0
    undecided = w == 0.5
    decided = np.flatnonzero(~undecided)
    if len(decided):
        nearest = decided[np.argmin(np.abs(np.arange(len(w))[:, None] - decided[None, :]), axis=1)]
        w = w[nearest]
    return TiltCheck(tilt, direction, w, undecided)


def with_tilt(stations: list[Station], check: TiltCheck) -> list[Station]:
    """The stations measured as the check decided: square rings (weight 1) gain their
    shrink and lose the tilt's ovality, oblique cuts (0) stand, 0.5 gain half the
    shrink; undecided stations hold half the shrink in their diameter sigma and half the
    tilt's ovality in their ovality sigma."""
    d = np.array([s.diameter_mm for s in stations], float)
    shrink = check.shrink_mm(d)
    extra = tilt_vectors(check.tilt_rad, check.direction_rad)
    m, _ = _vectors(stations)
    out = []
    rows = zip(stations, shrink, extra, m, check.square_weight, check.undecided, strict=True)
    for st, ds, p, mv, w, open_ in rows:
        new = replace(
            st,
            diameter_mm=st.diameter_mm + w * ds,
            diameter_sigma_mm=math.hypot(st.diameter_sigma_mm, 0.5 * ds if open_ else 0.0),
            diameter_min_mm=st.diameter_min_mm + w * ds,
            diameter_max_mm=st.diameter_max_mm + w * ds,
        )
        out.append(_ovality_less(new, mv, p, w, open_) if np.isfinite(mv).all() else new)
    return out


def _ovality_less(st: Station, m: np.ndarray, p: np.ndarray, w: float, undecided: bool) -> Station:
    """``st`` with the tilt's ovality vector ``p`` taken out of its own ``m`` when square
    (w 1); its ovality sigma widened by half |p| when ``undecided``."""
    if undecided:
        st = replace(st, ovality_sigma=math.hypot(st.ovality_sigma, 0.5 * float(np.linalg.norm(p))))
    if w < 1.0:
        return st
    v = m - p
    ov = float(np.linalg.norm(v))
    half = 0.5 * ov * st.diameter_mm
    return replace(
        st,
        ovality=ov,
        ovality_angle_deg=math.degrees(0.5 * math.atan2(float(v[1]), float(v[0]))) % 180.0,
        diameter_min_mm=st.diameter_mm - half,
        diameter_max_mm=st.diameter_mm + half,
    )


def with_tangent_sigma(stations: list[Station], tilt_rad: np.ndarray) -> list[Station]:
    """The stations with the centreline direction's uncertainty in their ovality sigma:
    tan(e) x :data:`TANGENT_SIGMA_RAD` for a ring tilted e (radians, (S,)) to the
    centreline (a fraction; stations without an ovality as they are)."""
    return [
        replace(st, ovality_sigma=math.hypot(st.ovality_sigma, math.tan(min(float(e), 1.4)) * TANGENT_SIGMA_RAD))
        if math.isfinite(st.ovality) else st
        for st, e in zip(stations, tilt_rad, strict=True)
    ]


ALONG_TILT_SIGMAS = 2.0
"""An ovality stretch's stations' component along their rings' tilt axis counts only
beyond this many of each station's ovality sigmas (:func:`ovality_beyond_tilt`)."""


def along_tilt_lower_bound(stations: list[Station], direction_rad: np.ndarray) -> np.ndarray:
    """(S,) each station's ovality (a fraction) with its component along its ring's tilt
    axis shrunk by :data:`ALONG_TILT_SIGMAS` of its ovality sigma (not below zero); NaN
    where a station has no ovality.

    A ring tilted to the centreline reads, besides the pipe's ovality, terms whose major
    axis lies along or across the tilt's ``direction_rad`` (S,) only: the oblique cut
    itself (1 - cos e, or the pipe's section stretched by 1 / cos e), the centreline's
    direction error (tan(e) d), and the sections a long ring mixes (a taper's end or a
    joint's step cut by a ring that spans them along the axis: a function of the angle
    to the tilt alone). Their sizes are what the stations' sigmas state; the component
    across the tilt axis (45 degrees to it) holds none of them."""
    m, sig = _vectors(stations)
    d = np.asarray(direction_rad, float)
    along = m[:, 0] * np.cos(2 * d) + m[:, 1] * np.sin(2 * d)
    across = -m[:, 0] * np.sin(2 * d) + m[:, 1] * np.cos(2 * d)
    return np.hypot(np.maximum(np.abs(along) - ALONG_TILT_SIGMAS * sig, 0.0), across)


def ovality_beyond_tilt(
    features: list[Stretch], stations: list[Station], direction_rad: np.ndarray, min_pct: float
) -> tuple[list[Stretch], list[str]]:
    """The section features without the ovality stretches that their rings' tilt could
    make up, and a warning for each: a stretch is kept when the median over its stations
    of :func:`along_tilt_lower_bound` reaches ``min_pct`` (percent; the stretches'
    threshold). ``stations`` carry their final ovality sigmas (fit, shared ring shape,
    scatter, the centreline's direction, the sections each ring mixes)."""
    if len(direction_rad) != len(stations):
        return features, []
    low = along_tilt_lower_bound(stations, direction_rad)
    axial = np.array([s.axial_mm for s in stations])
    tilt_axis = np.degrees(np.asarray(direction_rad, float)) % 180.0
    kept, warnings = [], []
    for f in features:
        inside = (axial >= f.axial_from_mm) & (axial <= f.axial_to_mm) & np.isfinite(low)
        if not isinstance(f, Ovality) or not inside.any() or 100.0 * float(np.median(low[inside])) >= min_pct:
            kept.append(f)
            continue
        warnings.append(
            f"an ovality of {f.percent:.1f} % at {f.axial_from_mm:.0f}..{f.axial_to_mm:.0f} mm lies along the "
            f"rings' tilt axis ({float(np.median(tilt_axis[inside])):.0f} deg): under {min_pct:g} % once the "
            "rings' oblique cut, the centreline's direction and the sections a ring mixes are allowed for, "
            "so it is not reported"
        )
    return kept, warnings
