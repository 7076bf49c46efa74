"""A second, independent scale for every step, and the decision which length to trust.

The laser's template matching along the epipolar curve (Eq. 17) measures a step's
length from the wall's appearance. On a periodic wall (brick courses, tiles, joints)
the next course looks like the right one, and the best-scoring length can be a whole
course off. This module gives each step a second length from other evidence and
decides, step by step, what the trajectory may use:

* **Feature depth scale**: the light section measures the wall (a cylinder around the
  rig, from the ring points of the earlier keyframe; in a bend a torus section whose
  curvature is the step's axis turn per length). Every matched feature ray of
  that keyframe meets the wall at a metric depth; triangulating the same match with
  a unit-length translation gives its depth in step units. Their ratio, over all
  matches (median), is the step length in mm, without any template matching. A
  feature matched to the wrong course lands off the wall and gives another ratio, so
  the per-match ratios also tell which matches to keep.
* **Laser consensus peaks**: every length at which the laser points' patches agree
  (:func:`omnipipe.sfm.laser_scale.consensus_peaks`), not only the best one.

A step is trusted when the two agree. When the laser's best peak disagrees but
another of its peaks agrees with the feature scale, that peak is chosen (the step is
resolved and says so). When nothing agrees, or one source is missing and the other is
ambiguous, the step is unreliable: the trajectory keeps a pose but the report marks
the stretch.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, replace

import numpy as np
from scipy.optimize import least_squares

from omnipipe.config import bounded
from omnipipe.geometry import make_transform
from omnipipe.sfm.geometry import triangulate_pairs

#: Confidence levels of a step, best first.
CONFIDENCE = ("high", "resolved", "low", "none")
#: How the reason of a step measured by its feature depths alone begins (the laser's
#: consensus peaks ambiguous); the window of steps around it may confirm it
#: (:func:`omnipipe.sfm.step_window.confirm_by_gait`).
FEATURE_ONLY = "feature depth scale alone:"
# How a step's reason says that only the robot's odometry confirmed the length the bundle
# adjustment moved it to (omnipipe.sfm.adjusted_steps): its own sources missed it, so it
# adds nothing to the run's scale (StepCheck.measures_scale).
ODOMETRY_WITNESS = "; the odometry confirms it:"
#: How the reason of a step resolved to another laser consensus peak begins.
PEAK_CHOSEN = "laser peak "


@dataclass(frozen=True)
class ScaleCheckConfig:
    """When two scale estimates agree, and when a laser answer is ambiguous.

    Attributes:
        agree_log: largest |log(s1 / s2)| for two lengths to agree (0.12: 12 %).
        ambiguous_ratio: the laser is ambiguous when its second consensus peak
            reaches this fraction of the best.
        alternative_min_ratio: a non-best laser peak may be chosen (because the
            features agree with it) only if it reaches this fraction of the best.
        min_feature_matches: fewest usable matches for a feature depth scale.
        min_parallax_deg: matches whose rays meet at less are not triangulated.
        max_feature_spread_log: the feature scale is unusable when its per-match log
            ratios scatter more than this (MAD, robust sigma) around the median.
        keep_match_log: matches whose own depth ratio is further than this from the
            chosen length are dropped from the tracks (a wrong course, a mismatch).
        adjusted_agree_log: after bundle adjustment a keyframe step must stay this
            close to its checked length, or it is flagged.
        max_source_offset_log: a run-wide laser / feature-depth ratio up to this is
            treated as a bias of one source and removed before the per-step check;
            beyond it (a course or more: every step aliased alike) it is not, and the
            steps are judged as measured.
        max_bias_log: a run-wide offset beyond this (5 %) means the laser's template
            lengths are biased on this rig and pipe: the metric anchors of the bundle
            adjustment are then features placed on the light-section wall instead.
        adjusted_agree_mm: ... or further than this (mm) from every source's length
            (the run-wide offsets removed): a frame step off by more than 1 mm is wrong
            (bench_robustness), whatever its share of a long keyframe step.
        feature_only_min_matches: fewest feature-depth matches for a step whose laser
            peaks are ambiguous to be measured by its feature depths alone (still
            unreliable until its neighbours confirm it).
        anchor_agree_log: a ``high`` step whose two lengths differ by more than this
            (offset removed) takes the feature-depth length, and its laser matches do
            not anchor the bundle adjustment (a partial wrong-course laser match).
    """

    agree_log: float = bounded(0.12, gt=0)
    ambiguous_ratio: float = bounded(0.8, gt=0, le=1)
    alternative_min_ratio: float = bounded(0.5, gt=0, le=1)
    min_feature_matches: int = bounded(12, ge=1)
    min_parallax_deg: float = bounded(1.0, ge=0, lt=180)
    max_feature_spread_log: float = bounded(0.35, gt=0)
    keep_match_log: float = bounded(0.25, gt=0)
    adjusted_agree_log: float = bounded(0.1, gt=0)
    max_source_offset_log: float = bounded(0.25, gt=0)
    adjusted_agree_mm: float = bounded(0.75, gt=0)
    feature_only_min_matches: int = bounded(30, ge=1)
    max_bias_log: float = bounded(0.05, gt=0)
    anchor_agree_log: float = bounded(0.05, gt=0)


@dataclass(frozen=True)
class WallCylinder:
    """The wall around a keyframe, in its rig frame: a tube, straight or bent.

    Straight (``curvature_xy`` None): a cylinder parallel to rig z through the ring's
    circle centre. Bent (:func:`bent_wall`): a torus section whose centreline is
    tangent to rig z at the rig (z = 0; the rig follows the axis) and turns towards
    ``curvature_xy``, fitted to the ring points. In a bend the straight cylinder is off
    the wall by about curvature * (z_ring**2 - z**2) / 2 at rig z (R 300 mm, ring
    78 mm from the features: 10 mm).

    Attributes:
        centre_xy: (2,) axis position in the rig's x-y plane (mm): straight, anywhere
            along it; bent, at the rig (z = 0).
        radius_mm: wall (tube) radius (mm).
        ring_z_mm: the ring plane's rig z (mm).
        curvature_xy: (2,) the axis' curvature vector (1/mm) in the rig's x-y plane,
            pointing to the bend's centre; None: straight.
        ring_points: (N, 3) the ring points it was fitted to (mm, rig frame).
    """

    centre_xy: np.ndarray
    radius_mm: float
    ring_z_mm: float = 0.0
    curvature_xy: np.ndarray | None = None
    ring_points: np.ndarray | None = None


@dataclass(frozen=True)
class StepCheck:
    """The evidence behind one keyframe step and what was decided.

    Attributes:
        first_frame, last_frame: frame indices of the two keyframes.
        laser_scale_mm: the laser's best length (NaN: no laser match).
        laser_ambiguity: second laser consensus peak over the best (0..1).
        feature_scale_mm: the feature depth scale (NaN: not measurable).
        feature_matches: matches behind it.
        scale_mm: the length used (NaN: none could be trusted).
        confidence: one of :data:`CONFIDENCE`.
        reason: why the step is not ``high`` (empty when it is).
        laser_peaks_mm: up to three laser consensus peaks (mm), best first.
        bridged_mm: for a step vision could not measure, the length it was given
            (mm; NaN: measured, or nothing to bridge it with).
        bridged_sigma_mm: that length's 1-sigma (mm; NaN: not bridged).
        bridged_from: where it came from: ``"odometry"``, ``"gait"`` (the nearest
            trusted steps) or ``""`` (not bridged).
    """

    first_frame: int
    last_frame: int
    laser_scale_mm: float
    laser_ambiguity: float
    feature_scale_mm: float
    feature_matches: int
    scale_mm: float
    confidence: str
    reason: str = ""
    laser_peaks_mm: tuple[float, ...] = ()
    bridged_mm: float = math.nan
    bridged_sigma_mm: float = math.nan
    bridged_from: str = ""

    @property
    def reliable(self) -> bool:
        """True when the step's length rests on agreeing evidence."""
        return self.confidence in ("high", "resolved")

    @property
    def measures_scale(self) -> bool:
        """True when the step's own sources may speak for the run's scale: reliable, not
        bridged, and not trusted on the odometry's word alone (:data:`ODOMETRY_WITNESS`)."""
        return self.reliable and not self.bridged_from and ODOMETRY_WITNESS not in self.reason

    def to_dict(self) -> dict:
        """JSON-ready form (lengths rounded to 0.01 mm)."""

        def r(x: float, nd: int = 2) -> float | None:
            return None if not math.isfinite(x) else round(float(x), nd)

        return {
            "first_frame": int(self.first_frame),
            "last_frame": int(self.last_frame),
            "confidence": self.confidence,
            "laser_scale_mm": r(self.laser_scale_mm),
            "laser_ambiguity": r(self.laser_ambiguity, 3),
            "feature_scale_mm": r(self.feature_scale_mm),
            "feature_matches": int(self.feature_matches),
            "scale_mm": r(self.scale_mm),
            "laser_peaks_mm": [r(p) for p in self.laser_peaks_mm],
            "reason": self.reason,
            **(
                {
                    "bridged_mm": r(self.bridged_mm),
                    "bridged_sigma_mm": r(self.bridged_sigma_mm),
                    "bridged_from": self.bridged_from,
                }
                if self.bridged_from
                else {}
            ),
        }


@dataclass(frozen=True)
class UnreliableStretch:
    """Frames whose motion could not be trusted (DATA_CONTRACT ``trajectory_quality``).

    Attributes:
        first_frame, last_frame: 0-based frame indices, inclusive.
        reason: why, in words.
    """

    first_frame: int
    last_frame: int
    reason: str

    def to_dict(self) -> dict:
        """The contract's form."""
        return {
            "first_frame": int(self.first_frame),
            "last_frame": int(self.last_frame),
            "reason": self.reason,
        }


def merge_stretches(stretches: list[UnreliableStretch]) -> list[UnreliableStretch]:
    """Sorted stretches, overlapping or touching ones merged (reasons joined once each)."""
    out: list[UnreliableStretch] = []
    for s in sorted(stretches, key=lambda s: (s.first_frame, s.last_frame)):
        if out and s.first_frame <= out[-1].last_frame:
            last = out[-1]
            reasons = last.reason.split("; ")
            reason = last.reason if s.reason in reasons else f"{last.reason}; {s.reason}"
            out[-1] = UnreliableStretch(
                last.first_frame, max(last.last_frame, s.last_frame), reason
            )
        else:
            out.append(s)
    return out


def steps_checked(checks: list[StepCheck], stationary: np.ndarray) -> int:
    """Frame-to-frame steps whose motion was verified: standstills (frames found
    identical to their predecessor) and steps inside keyframe steps whose length two
    sources confirmed."""
    ok = np.asarray(stationary, bool)[1:].copy()
    for c in checks:
        if c.reliable:
            ok[c.first_frame : c.last_frame] = True
    return int(ok.sum())


def wall_cylinder(points_in_rig: np.ndarray) -> WallCylinder | None:
    """Least-squares circle (Kasa) of the ring points' x-y: the wall around the rig.

    Args:
        points_in_rig: (N, 3) metric ring points (mm) of one frame.

    Returns:
        The cylinder, or None with fewer than 20 points or a degenerate fit.
    """
    p = np.asarray(points_in_rig, float)
    if len(p) < 20:
        return None
    x, y = p[:, 0], p[:, 1]
    A = np.column_stack([2 * x, 2 * y, np.ones(len(x))])
    sol, *_ = np.linalg.lstsq(A, x * x + y * y, rcond=None)
    cx, cy, c = sol
    r2 = c + cx * cx + cy * cy
    if not np.isfinite(r2) or r2 <= 0:
        return None
    return WallCylinder(np.array([cx, cy]), float(math.sqrt(r2)), float(np.median(p[:, 2])), None, p)


# Below this axis turn per keyframe step (rad) a wall stays straight: a torus from
# one step's turn estimate only adds error there (keyframe steps of paper-small and
# bend-small turn 0.15-0.27 deg; the full `bend`, R = 4 D, about 1 deg a step, where
# the bent wall took the run's ATE from 0.107 to 0.249 mm; elbow-small's R = 1.5 D
# 3.3-4.0 deg, where it is needed).
MIN_BEND_TURN_RAD = math.radians(2.0)


def bent_wall(
    wall: WallCylinder | None,
    b_from_a_rotation: np.ndarray,
    travel_b_from_a: np.ndarray,
    length_mm: float,
) -> WallCylinder | None:
    """The wall of keyframe a bent by the step's axis turn per length.

    The rig's z axis of keyframe b, seen in rig a, is ``R^T e_z``; its turn from rig
    a's z over the step's length ``length_mm`` is the pipe axis' curvature (the rig
    follows the axis). Straight when the turn is below :data:`MIN_BEND_TURN_RAD`, the
    length is not finite or the torus does not fit (:func:`fit_torus`).

    Args:
        wall: the ring's straight wall from :func:`wall_cylinder` (None passes
            through).
        b_from_a_rotation: (3, 3) rotation of rig_b_from_rig_a.
        travel_b_from_a: (3,) translation of rig_b_from_rig_a (any length; its
            direction tells which way the rig travels).
        length_mm: the step's length (mm).
    """
    if wall is None or not math.isfinite(length_mm) or length_mm <= 0:
        return wall
    R = np.asarray(b_from_a_rotation, float)
    z_b = R.T[:, 2]  # rig b's z in rig a
    turn = math.atan2(math.hypot(z_b[0], z_b[1]), z_b[2])
    if turn < MIN_BEND_TURN_RAD:
        return replace(wall, curvature_xy=None)
    # The axis' tangent along the travel turns towards the bend's centre: rig z's tilt
    # when the rig travels along +z, its opposite along -z.
    travel = -R.T @ np.asarray(travel_b_from_a, float)
    direction = math.copysign(1.0, travel[2]) * z_b[:2] / math.hypot(z_b[0], z_b[1])
    bent = fit_torus(wall, direction * (turn / length_mm))
    return bent if bent is not None else replace(wall, curvature_xy=None)


def fit_torus(wall: WallCylinder, curvature_xy: np.ndarray) -> WallCylinder | None:
    """The bent wall of curvature ``curvature_xy`` (2,) 1/mm through the ring points:
    its axis position at the rig and tube radius by least squares, from the straight
    cylinder's (the ring plane cuts a bent tube obliquely: not a circle). None when
    the ring is too far along the bend (beyond 0.9 of its radius) or the fit fails."""
    if wall.ring_points is None:
        return None
    bend_r = 1.0 / float(np.hypot(*curvature_xy))
    if abs(wall.ring_z_mm) >= 0.9 * bend_r:
        return None
    n = curvature_xy * bend_r
    sag = bend_r - math.sqrt(bend_r**2 - wall.ring_z_mm**2)
    x0 = np.array([*(wall.centre_xy - sag * n), wall.radius_mm])
    sol = least_squares(
        lambda x: _off_torus(wall.ring_points, x[:2], x[2], curvature_xy), x0, method="lm"
    )
    if not sol.success or not np.all(np.isfinite(sol.x)) or sol.x[2] <= 0:
        return None
    return replace(wall, centre_xy=sol.x[:2], radius_mm=float(sol.x[2]), curvature_xy=curvature_xy)


def _off_torus(
    points: np.ndarray, centre_xy: np.ndarray, radius_mm: float, curvature_xy: np.ndarray
) -> np.ndarray:
    """(N,) signed distance (mm) of (N, 3) points outside the bent wall whose axis is
    at ``centre_xy`` at z = 0, tangent to z, turning towards ``curvature_xy``."""
    bend_r = 1.0 / float(np.hypot(*curvature_xy))
    n = np.array([*(curvature_xy * bend_r), 0.0])
    centre = np.array([*centre_xy, 0.0]) + bend_r * n
    binormal = np.cross(n, [0.0, 0.0, 1.0])
    q = points - centre
    h = q @ binormal
    rho = np.linalg.norm(q - h[:, None] * binormal, axis=1)
    return np.hypot(rho - bend_r, h) - radius_mm


def wall_depth(rays_in_rig: np.ndarray, wall: WallCylinder) -> np.ndarray:
    """(N,) distance (mm) from the rig origin along each unit ray to the wall (NaN: misses).

    Straight: the ray-cylinder root. Bent: Newton's method on the distance to the
    torus centreline from the straight root (NaN where it does not converge).
    """
    r = np.asarray(rays_in_rig, float)
    cx, cy = wall.centre_xy
    a = r[:, 0] ** 2 + r[:, 1] ** 2
    b = -2.0 * (r[:, 0] * cx + r[:, 1] * cy)
    c = cx * cx + cy * cy - wall.radius_mm**2
    disc = b * b - 4 * a * c
    with np.errstate(invalid="ignore", divide="ignore"):
        t = (-b + np.sqrt(disc)) / (2 * a)
    t = np.where((disc > 0) & (a > 1e-6) & (t > 0), t, np.nan)
    if wall.curvature_xy is None:
        return t
    return _torus_depth(r, t, wall)


def _torus_depth(rays: np.ndarray, t0: np.ndarray, wall: WallCylinder) -> np.ndarray:
    """(N,) depths (mm) along unit ``rays`` to the bent wall, Newton from ``t0``."""

    def off_wall(t: np.ndarray) -> np.ndarray:
        return _off_torus(rays * t[:, None], wall.centre_xy, wall.radius_mm, wall.curvature_xy)

    t = t0.copy()
    with np.errstate(invalid="ignore"):
        for _ in range(8):
            f = off_wall(t)
            slope = (off_wall(t + 1e-3) - f) / 1e-3
            t = t - f / np.where(np.abs(slope) > 1e-3, slope, np.nan)
        ok = (np.abs(off_wall(t)) < 1e-3) & (t > 0)
    return np.where(ok, t, np.nan)


def unit_depths(
    rays_a: np.ndarray, rays_b: np.ndarray, b_from_a_rotation: np.ndarray, direction: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """Depth along each ray of frame a for a translation of length 1 (midpoint method).

    Args:
        rays_a, rays_b: (N, 3) matched unit rays in rig a and rig b.
        b_from_a_rotation: (3, 3) rotation of rig_b_from_rig_a.
        direction: (3,) unit translation of rig_b_from_rig_a (p_b = R p_a + s d).

    Returns:
        (N,) depths in units of the step length (NaN behind either camera) and (N,)
        parallax angles (rad) between the rays.
    """
    R = np.asarray(b_from_a_rotation, float)
    u = np.asarray(rays_a, float) @ R.T  # ray a expressed in rig b
    v = np.asarray(rays_b, float)
    _, depth = triangulate_pairs(
        np.asarray(rays_a, float), v, make_transform(R, np.asarray(direction, float))
    )
    uv = np.sum(u * v, axis=1)
    parallax = np.arccos(np.clip(uv / np.sqrt(np.sum(u * u, axis=1) * np.sum(v * v, axis=1)), -1.0, 1.0))
    with np.errstate(invalid="ignore"):
        t = np.where((depth[:, 0] > 0) & (depth[:, 1] > 0), depth[:, 0], np.nan)
    return t, parallax


# Passes of feature_log_scales after the straight one: the length sets the curvature.
BEND_ITERATIONS = 2


def feature_log_scales(
    rays_a: np.ndarray,
    rays_b: np.ndarray,
    b_from_a_rotation: np.ndarray,
    direction: np.ndarray,
    wall: WallCylinder | None,
    config: ScaleCheckConfig,
    bend: bool = True,
) -> np.ndarray:
    """(N,) log of each match's implied step length (mm): wall depth / unit depth.

    NaN where the match cannot say (no wall, too little parallax, behind a camera).
    With ``bend`` a straight ``wall`` is bent by the step's axis turn per length
    (:func:`bent_wall`), the length taken from the previous pass.
    """
    n = len(rays_a)
    if wall is None or n == 0:
        return np.full(n, np.nan)
    t_unit, parallax = unit_depths(rays_a, rays_b, b_from_a_rotation, direction)
    usable = np.isfinite(t_unit) & (parallax >= math.radians(config.min_parallax_deg))
    ls = np.full(n, np.nan)
    model = wall
    for it in range(1 + BEND_ITERATIONS):
        with np.errstate(invalid="ignore", divide="ignore"):
            ls = np.where(usable, np.log(wall_depth(rays_a, model) / t_unit), np.nan)
        if not bend or it == BEND_ITERATIONS or not np.isfinite(ls).any():
            break
        # The bend's curvature is the axis turn per mm: the length from this pass
        # bends the wall of the next (the bend's effect is second order in the length).
        bent = bent_wall(wall, b_from_a_rotation, direction, math.exp(float(np.nanmedian(ls))))
        if bent is None or (bent.curvature_xy is None and model.curvature_xy is None):
            break
        model = bent
    return ls


def feature_scale(log_scales: np.ndarray, config: ScaleCheckConfig) -> tuple[float, int]:
    """Robust step length (mm) from per-match log lengths, and the matches behind it.

    NaN when too few matches or when they scatter too much to mean anything.
    """
    ls = log_scales[np.isfinite(log_scales)]
    if len(ls) < config.min_feature_matches:
        return math.nan, len(ls)
    med = float(np.median(ls))
    spread = 1.4826 * float(np.median(np.abs(ls - med)))
    inl = np.abs(ls - med) < max(3 * spread, 0.05)
    if spread > config.max_feature_spread_log or inl.sum() < config.min_feature_matches:
        return math.nan, int(inl.sum())
    return float(math.exp(np.median(ls[inl]))), int(inl.sum())


# A step's feature-depth length is trusted on its own only from a textured wall's
# tracked matches: at least this many ...
TRACKED_MIN_MATCHES = 100
# ... whose per-match log lengths scatter at most this much (robust sigma). On the 40
# random-wide renders (640x480) the 135 steps with both were within 2.2 % of the truth
# (95 % within 1.3 %); with fewer matches or more scatter steps were 5-24 % off (plain
# walls, corrugation, a short step's small parallax).
TRACKED_MAX_SPREAD_LOG = 0.04
# Relative 1-sigma floor of a feature-depth length: the wall model and the relative
# motion's direction, which the matches' spread does not show (those 135 steps: with
# 1.0 % 2 sigma covers 134, 3 sigma all; the spread over sqrt(n) alone covered a third).
FEATURE_DEPTH_SIGMA_FLOOR = 0.01


def feature_depth_spread(log_scales: np.ndarray) -> tuple[float, float, int]:
    """The robust spread (1.4826 MAD, log) of a step's per-match log lengths (N,) within
    :func:`feature_scale`'s inlier band, its length's relative 1-sigma (the median's,
    with :data:`FEATURE_DEPTH_SIGMA_FLOOR`) and the matches behind it (NaN, NaN, n with
    fewer than 3)."""
    ls = np.asarray(log_scales, float)
    ls = ls[np.isfinite(ls)]
    if len(ls) < 3:
        return math.nan, math.nan, len(ls)
    med = float(np.median(ls))
    spread = 1.4826 * float(np.median(np.abs(ls - med)))
    ls = ls[np.abs(ls - med) < max(3 * spread, 0.05)]
    _, sigma = median_with_sigma(ls)
    return sigma * math.sqrt(len(ls)) / 1.2533, math.hypot(sigma, FEATURE_DEPTH_SIGMA_FLOOR), len(ls)


def decide(
    first_frame: int,
    last_frame: int,
    laser_scale_mm: float,
    peak_scales_mm: np.ndarray,
    peak_scores: np.ndarray,
    feature_scale_mm: float,
    feature_matches: int,
    config: ScaleCheckConfig,
    feature_gain: float = 1.0,
) -> StepCheck:
    """Which length a step may use, from the laser's peaks and the feature scale.

    ``feature_gain`` is the run's systematic laser / feature-depth ratio: the feature
    length is compared with the laser's after multiplying by it.

    Returns:
        A :class:`StepCheck`. ``scale_mm`` is a consensus peak's length when one was
        chosen (the caller re-matches the laser around it for precision); NaN when no
        length could be trusted.
    """
    amb = (
        float(peak_scores[1] / peak_scores[0])
        if len(peak_scores) >= 2 and peak_scores[0] > 0
        else 0.0
    )
    has_laser = math.isfinite(laser_scale_mm) and laser_scale_mm > 0
    has_feat = math.isfinite(feature_scale_mm)

    def check(scale: float, confidence: str, reason: str = "") -> StepCheck:
        return StepCheck(
            first_frame, last_frame, laser_scale_mm, amb, feature_scale_mm, feature_matches,
            scale, confidence, reason, tuple(float(p) for p in peak_scales_mm[:3]),
        )

    expected = feature_scale_mm * feature_gain  # the feature length in laser units
    if has_laser and has_feat:
        if abs(math.log(laser_scale_mm / expected)) <= config.agree_log:
            return check(laser_scale_mm, "high")
        # Another consensus peak may be the right course; so may the best peak itself
        # when the points' median (``laser_scale_mm``) left it (seen on corrugation:
        # best peak 19.5 mm, median 30.8 mm, features 18.3 mm, truth 18.4 mm).
        for s, c in zip(peak_scales_mm, peak_scores, strict=True):
            if (
                c >= config.alternative_min_ratio * peak_scores[0]
                and abs(math.log(s / expected)) <= config.agree_log
            ):
                return check(
                    float(s), "resolved",
                    f"{PEAK_CHOSEN}{s:.1f} mm chosen over {laser_scale_mm:.1f} mm: it agrees with "
                    f"the feature depth scale {feature_scale_mm:.1f} mm",
                )
        if amb >= config.ambiguous_ratio and feature_matches >= config.feature_only_min_matches:
            # A periodic wall: every course scores alike. The features' depths, many
            # and agreeing, are a length of their own; the window (gait) confirms it.
            return check(
                expected, "low",
                f"{FEATURE_ONLY} {feature_scale_mm:.1f} mm ({feature_matches} matches); the "
                f"laser's peaks ({', '.join(f'{s:.1f}' for s in peak_scales_mm[:3])} mm) "
                "are ambiguous",
            )
        return check(
            math.nan, "none",
            f"laser scale {laser_scale_mm:.1f} mm and feature depth scale "
            f"{feature_scale_mm:.1f} mm disagree",
        )
    if has_laser:
        if amb >= config.ambiguous_ratio:
            return check(
                math.nan, "none",
                f"ambiguous laser scale (peaks at {', '.join(f'{s:.1f}' for s in peak_scales_mm[:3])} mm) "
                "and no feature depth scale to decide",
            )
        return check(laser_scale_mm, "low", "laser scale not confirmed by feature depths")
    if has_feat:
        return check(expected, "low", "laser points not found again; feature depth scale used")
    return check(math.nan, "none", "no laser scale and no feature depth scale")


# Relative 1-sigma floor of a wall-set scale: what the statistics of the steps cannot
# see (the wall model's approximation, e.g. a cylinder parallel to the rig axis in a
# bend). The wall-scaled bench_robustness runs' errors were 0.02-0.28 %.
WALL_SCALE_SIGMA_FLOOR = 0.001
# Fewest reliable keyframe steps for the wall to set the run's scale.
WALL_SCALE_MIN_STEPS = 5


def wall_scale_correction(
    world_from_kf: np.ndarray,
    pair_matches: list[tuple[int, int, np.ndarray]],
    rays_in_rig: list[np.ndarray],
    ring_points: list[np.ndarray],
    checks: list[StepCheck],
    config: ScaleCheckConfig,
) -> tuple[float, float] | None:
    """The run's scale correction from the light-section wall, after adjustment.

    For every reliable keyframe step k -> k+1 with matches: its adjusted motion gives
    each match a depth per unit step; the wall cylinder of keyframe k's ring gives the
    metric depth along the same ray; their robust ratio is the step's length as the
    wall measures it. The log ratio to the adjusted length, medianed over the steps,
    is the correction. The wall is bent (:func:`bent_wall`) only when the run turns
    steadily (:func:`steady_turn`): one step's turn cannot tell a bend from the rig's
    tilt in a straight pipe (a wobble of 0.6 deg a 6 mm step would bend it to
    R 340 mm), and the run's scale must not take that error.

    Args:
        world_from_kf: (K, 4, 4) adjusted keyframe poses (mm).
        pair_matches: (k, k + 1, (M, 2) match indices) per keyframe step.
        rays_in_rig: per keyframe, (F, 3) unit rays of its features (match indices
            point into these).
        ring_points: per keyframe, (N, 3) metric ring points in its rig frame (mm).
        checks: per keyframe step, its check (only reliable steps count).
        config: the feature-depth settings.

    Returns:
        (log gain, its 1-sigma) to multiply every length by exp(gain), or None with
        fewer than ``WALL_SCALE_MIN_STEPS`` usable steps.
    """
    logs = []
    bend = steady_turn(world_from_kf)
    for k, k1, inl in pair_matches:
        if k >= len(checks) or not checks[k].measures_scale or inl is None or len(inl) == 0:
            continue
        b_from_a = np.linalg.inv(world_from_kf[k1]) @ world_from_kf[k]
        length = float(np.linalg.norm(b_from_a[:3, 3]))
        if length <= 1e-6:
            continue
        log_s = feature_log_scales(
            rays_in_rig[k][inl[:, 0]], rays_in_rig[k1][inl[:, 1]],
            b_from_a[:3, :3], b_from_a[:3, 3] / length, wall_cylinder(ring_points[k]), config,
            bend=bend,
        )
        s_feat, _ = feature_scale(log_s, config)
        if math.isfinite(s_feat) and s_feat > 0:
            logs.append(math.log(s_feat / length))
    if len(logs) < WALL_SCALE_MIN_STEPS:
        return None
    return median_with_sigma(np.array(logs))


def steady_turn(world_from_kf: np.ndarray) -> bool:
    """True when the (K, 4, 4) keyframe poses' z axes turn one way: the run's mean
    turn per step (world frame) is more than three of its standard errors (a bend
    turns alike step after step; the tilt noise of a straight pipe does not)."""
    z = np.asarray(world_from_kf, float)[:, :3, 2]
    if len(z) < WALL_SCALE_MIN_STEPS:
        return False
    d = np.diff(z, axis=0)
    mean = d.mean(axis=0)
    se = d.std(axis=0, ddof=1) / math.sqrt(len(d))
    return bool(np.linalg.norm(mean) > 3.0 * max(float(np.linalg.norm(se)), 1e-12))


def median_with_sigma(values: np.ndarray) -> tuple[float, float]:
    """Median of (N,) values and its 1-sigma: the robust spread (1.4826 MAD) times the
    median's efficiency factor 1.2533, over sqrt(N)."""
    med = float(np.median(values))
    spread = 1.4826 * float(np.median(np.abs(values - med)))
    return med, 1.2533 * spread / math.sqrt(len(values))


# The wall's radius per ring for :func:`wall_radius_change`: the circle refitted this many
# times, first on the nearer half of its points, then without those further from it than
# RING_CLIP_MADS robust sigmas (at least RING_CLIP_FLOOR_MM): a joint's groove, a lateral's branch wall or stray peaks pulled
# the plain fit's radius by up to 61 % on the random-features rings (seed 6; 0.15 % without).
RING_PASSES = 4
RING_CLIP_MADS = 3.0
RING_CLIP_FLOOR_MM = 0.5


def ring_radius(points_in_rig: np.ndarray) -> float:
    """The wall's radius (mm) at one ring ((N, 3) metric points in the rig frame): the
    circle of :func:`wall_cylinder` refitted without outlying points
    (:data:`RING_PASSES`); NaN when no circle fits."""
    p = np.asarray(points_in_rig, float)
    wall = wall_cylinder(p)
    if wall is None:
        return math.nan
    for k in range(RING_PASSES):
        res = np.linalg.norm(p[:, :2] - wall.centre_xy, axis=1) - wall.radius_mm
        off = np.abs(res - float(np.median(res)))
        # The first refit keeps the nearer half (an outlying sector pulls the plain fit's
        # centre: its own points then scatter as widely as the outliers).
        clip = float(np.median(off)) if k == 0 else RING_CLIP_MADS * 1.4826 * float(np.median(off))
        refit = wall_cylinder(p[off <= max(clip, RING_CLIP_FLOOR_MM)])
        if refit is None:
            break
        wall = refit
    return wall.radius_mm


def wall_radius_change(ring_points: list[np.ndarray]) -> float:
    """Half the relative range of the wall's radius along the run: (max - min) / (max +
    min) of the keyframes' ring radii (:func:`ring_radius`; rings too short for one left
    out), each the median of three neighbours (one odd ring is no change); 0
    with fewer than two.

    The feature depths and the wall's own shift place the features on the ring's
    cylinder; the features lie up to a ring's distance from it along the pipe. Where the
    wall's radius changes along the run (a reducer, an offset joint) the features' wall
    differs from the ring's by up to this much, and so do those lengths (one bias over
    the steps that cross the change, which their spread does not show).

    Args:
        ring_points: per keyframe, (N_k, 3) metric ring points in its rig frame (mm).
    """
    radii = np.array([r for r in map(ring_radius, ring_points) if math.isfinite(r)])
    if len(radii) < 2:
        return 0.0
    starts = np.clip(np.arange(len(radii)) - 1, 0, max(len(radii) - 3, 0))
    smooth = [float(np.median(radii[i:i + 3])) for i in starts]
    lo, hi = min(smooth), max(smooth)
    return (hi - lo) / (hi + lo)
