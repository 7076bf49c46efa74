"""What the user is told about the camera motion: report.json's ``trajectory_quality``.

DATA_CONTRACT defines ``steps_checked`` and ``unreliable`` (first/last frame, reason).
omnipipe adds, compatibly: per unreliable stretch its extent along the pipe
(``axial_start_mm``, ``axial_end_mm``, the defects' axial convention) so that
report.html can mark it on the unrolled wall, and ``keyframe_steps``: every keyframe
step's evidence (laser length and consensus peaks, feature depth length, confidence).
Defects whose axial extent touches an unreliable stretch, and features in one, get
``"motion_unreliable": true`` and a warning: their length and position rest on untrusted
motion. The records
are :class:`~omnipipe.contract.TrajectoryQuality` and :class:`~omnipipe.contract.Defect`,
changed by ``dataclasses.replace`` only.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass, replace

import numpy as np

from omnipipe.analysis.feature_types import Bend, Feature, PointFeature, Stretch
from omnipipe.analysis.ring_spans import RingSpans
from omnipipe.contract import Defect, RotationCheck, TrajectoryQuality, UnreliableSpan
from omnipipe.errors import ReconstructionError
from omnipipe.sfm import SfmResult
from omnipipe.sfm.scale_check import TRACKED_MIN_MATCHES, StepCheck, steps_checked
from omnipipe.sfm.types import ODOMETRY_ONLY


def station_axial_mm(
    point_axial_mm: np.ndarray, point_station: np.ndarray, n_stations: int
) -> np.ndarray:
    """(K,) axial position (mm) of each station: the median of its ring points' positions
    (each station's points read on their own: :class:`omnipipe.analysis.ring_spans.RingSpans`)."""
    out = np.full(n_stations, np.nan)
    if len(point_station) == 0:
        return out
    spans = RingSpans(point_station)
    for i, k in enumerate(spans.rings):
        out[int(k)] = float(np.median(spans.values(i, point_axial_mm)))
    return out


def trajectory_quality(
    motion: SfmResult, station_frames: np.ndarray, station_axial: np.ndarray
) -> TrajectoryQuality:
    """report.json's ``trajectory_quality``.

    Args:
        motion: the camera-motion result.
        station_frames: (K,) first frame of each station that fed the model, increasing.
        station_axial: (K,) their axial positions (mm; NaN unknown).
    """
    unreliable = []
    for u in motion.unreliable:
        span = UnreliableSpan(int(u.first_frame), int(u.last_frame), u.reason)
        if len(station_frames):
            k = np.clip(
                np.searchsorted(station_frames, [u.first_frame, u.last_frame], side="right") - 1,
                0,
                len(station_frames) - 1,
            )
            ax = station_axial[k]
            if np.all(np.isfinite(ax)):
                span = replace(
                    span,
                    axial_start_mm=round(float(ax.min()), 1),
                    axial_end_mm=round(float(ax.max()), 1),
                )
        unreliable.append(span)
    return TrajectoryQuality(
        steps_checked=steps_checked(motion.step_checks, motion.stationary),
        unreliable=tuple(unreliable),
        scale_source=motion.scale_source,
        laser_offset_pct=round(100 * motion.laser_offset, 2),
        # After the adjustment: how far the wall's lengths were from the laser-anchored
        # run's, and the correction applied (both NaN -> null when not measured).
        wall_scale_gap_pct=_pct(motion.wall_scale_log),
        scale_correction_pct=_pct(motion.scale_correction_log),
        scale_sigma_pct=_pct(math.log1p(motion.scale_sigma_rel)),
        keyframe_steps=tuple(motion.step_checks),
        rotation_check=_rotation_check(motion, station_frames, station_axial),
    )


def _rotation_check(
    motion: SfmResult, station_frames: np.ndarray, station_axial: np.ndarray
) -> RotationCheck | None:
    """The camera motion's rotation against the gyro (None without one), with the
    stations' frames and axial positions to place a feature's ends."""
    check = motion.gyro_check
    if check is None:
        return None
    frame, gap, sig = check.worst()
    return RotationCheck(
        math.degrees(gap), frame, math.degrees(sig), check,
        np.asarray(station_frames, int), np.asarray(station_axial, float),
    )


def bend_with_rotation(bend: Bend, rc: RotationCheck | None) -> Bend:
    """``bend`` with the camera motion's rotation error over its stretch in its turn's
    and radius' sigmas: the images' relative rotation between the stations at its two
    ends against the gyro's (:meth:`omnipipe.sfm.rotation_check.GyroCheck.between`), less
    the gyro's own sigma over that time in quadrature, added in quadrature
    (``turn_motion_sigma_deg`` says how much, 0 when the gyro's drift explains the
    departure; the radius (end - start) / turn by its relative share). Unchanged without
    a check or with the ends' stations unknown."""
    if rc is None or bend.turn_deg <= 0:
        return bend
    known = np.flatnonzero(np.isfinite(rc.station_axial_mm))
    if len(known) == 0:
        return bend
    ends = [
        int(rc.station_frames[known[np.argmin(np.abs(rc.station_axial_mm[known] - x))]])
        for x in (bend.axial_from_mm, bend.axial_to_mm)
    ]
    err, gyro_sigma = rc.gyro.between(*ends)
    # The images' error beyond what the gyro's own drift explains (a departure within it
    # tells nothing: the tight elbow's 1.0 deg over 20 s, its gyro's 1-sigma 1.15 deg,
    # for the images' true 0.1 deg).
    extra = math.sqrt(max(err**2 - gyro_sigma**2, 0.0))
    turn = math.radians(bend.turn_deg)
    return replace(
        bend,
        turn_sigma_deg=math.hypot(bend.turn_sigma_deg or 0.0, math.degrees(extra)),
        radius_sigma_mm=math.hypot(bend.radius_sigma_mm or 0.0, bend.radius_mm * extra / turn),
        turn_motion_sigma_deg=math.degrees(extra),
    )


def _pct(log_value: float) -> float | None:
    """A log factor as a rounded percentage, None when not finite (JSON null)."""
    return round(100 * math.expm1(log_value), 3) if math.isfinite(log_value) else None


def _overlaps_unreliable(start: float, end: float, quality: TrajectoryQuality) -> UnreliableSpan | None:
    """The first unreliable stretch overlapping ``[start, end]`` (mm along the pipe)."""
    for u in quality.unreliable:
        if u.axial_start_mm is None or u.axial_end_mm is None:
            continue
        if start <= u.axial_end_mm and end >= u.axial_start_mm:
            return u
    return None


def flag_features(
    features: Sequence[Feature], quality: TrajectoryQuality
) -> tuple[tuple[Feature, ...], list[str]]:
    """The pipe's features, those within 3 sigma of (point features) or overlapping
    (stretches) an unreliable stretch flagged ``motion_unreliable``; one warning per
    flagged feature. Their positions and axial sizes rest on untrusted motion. Bends'
    turns carry the motion's rotation error the gyro shows (:func:`bend_with_rotation`)."""
    out: list[Feature] = []
    warnings = []
    for f in features:
        if isinstance(f, Bend):
            f = bend_with_rotation(f, quality.rotation_check)
        if isinstance(f, Stretch):
            start, end = f.axial_from_mm, f.axial_to_mm
        elif isinstance(f, PointFeature):
            margin = 3.0 * (f.axial_sigma_mm or 0.0)
            start, end = f.axial_mm - margin, f.axial_mm + margin
        else:
            out.append(f)
            continue
        u = _overlaps_unreliable(start, end, quality)
        if u is not None:
            f = replace(f, motion_unreliable=True)
            warnings.append(
                f"{f.kind} at {f.position_mm:.0f} mm lies in frames {u.first_frame}-"
                f"{u.last_frame}, whose motion is unreliable: its position and axial sizes "
                "are not trustworthy"
            )
        out.append(f)
    return tuple(out), warnings


def flag_defects(
    defects: Sequence[Defect], quality: TrajectoryQuality
) -> tuple[list[Defect], list[str]]:
    """The defects, those lying across an unreliable stretch flagged
    ``motion_unreliable``; and one warning per flagged defect."""
    warnings = []
    out = []
    for k, d in enumerate(defects):
        start, end = d.axial_start_mm, d.axial_end_mm
        u = _overlaps_unreliable(start, end, quality)
        if u is not None:
            d = replace(d, motion_unreliable=True)
            warnings.append(
                f"defect {k + 1} ({d.kind}, at {start:.0f} mm) lies across frames "
                f"{u.first_frame}-{u.last_frame}, whose motion is unreliable: its "
                "length and position are not trustworthy"
            )
        out.append(d)
    return out, warnings


@dataclass(frozen=True)
class Widened:
    """What :func:`widen_for_unreliable` gives.

    Attributes:
        run_length_sigma_mm: the run length's 1-sigma with the unreliable stretches in it
            (None: the run length had none).
        run_length_unreliable_mm: the length of the run resting on unreliable motion.
        defects: the defects, their axial starts' sigmas widened by the stretches before.
        warnings: one line when some of the run is unreliable.
    """

    run_length_sigma_mm: float | None
    run_length_unreliable_mm: float
    defects: list[Defect]
    warnings: list[str]


def _reported_scale_mm(check: StepCheck) -> float | None:
    """A step's length as report.json's ``keyframe_steps`` states it (0.01 mm)."""
    return round(float(check.scale_mm), 2) if math.isfinite(check.scale_mm) else None


def widen_for_unreliable(
    run_length_sigma_mm: float | None, defects: Sequence[Defect], quality: TrajectoryQuality
) -> Widened:
    """Lengths along the pipe that pass through unreliable motion carry its length as sigma.

    An unreliable stretch keeps the run going with a placeholder length, and after the
    adjustment (nothing anchors a step without matches) it may even collapse: the run
    length and the axial position of everything beyond it rest on a length nobody
    measured. Each stretch counts with the larger of its extent in the output and its
    unreliable keyframe steps times the median trusted step (``keyframe_steps``), added
    in quadrature (100 %, 1 sigma) to ``run_length_sigma_mm`` and to each later defect's
    ``axial_start_sigma_mm``; ``run_length_unreliable_mm`` is their sum, and a warning
    says so. Defects lying across a stretch are flagged by :func:`flag_defects`.
    """
    steps = quality.keyframe_steps
    trusted = [
        scale
        for c in steps
        if c.confidence in ("high", "resolved") and (scale := _reported_scale_mm(c))
    ]
    typical = float(np.median(trusted)) if trusted else 0.0
    spans = []
    for u in quality.unreliable:
        if u.axial_start_mm is None or u.axial_end_mm is None:
            continue
        a, b = float(u.axial_start_mm), float(u.axial_end_mm)
        n_steps = sum(
            1 for c in steps
            if c.confidence not in ("high", "resolved")
            and c.first_frame < u.last_frame and c.last_frame > u.first_frame
        )
        spans.append((a, b, max(b - a, n_steps * typical)))
    total = sum(w for *_, w in spans)
    unchanged = Widened(run_length_sigma_mm, round(float(total), 1), list(defects), [])
    if not spans or total <= 0:
        return unchanged
    if run_length_sigma_mm is not None:
        run_length_sigma_mm = round(math.hypot(run_length_sigma_mm, total), 3)
    widened = []
    for d in defects:
        before = sum(w for _, b, w in spans if b <= d.axial_start_mm)
        if before > 0 and d.axial_start_sigma_mm is not None:
            d = replace(d, axial_start_sigma_mm=round(math.hypot(d.axial_start_sigma_mm, before), 4))
        widened.append(d)
    return Widened(
        run_length_sigma_mm,
        unchanged.run_length_unreliable_mm,
        widened,
        [
            f"about {total:.0f} mm of the run is unreliable motion ({len(spans)} stretches): its "
            "length is a placeholder, counted in run_length_sigma_mm and in the axial positions "
            "beyond it"
        ],
    )


# A ``low`` step's two sources agree when within this |log| of each other.
SOURCES_AGREE_LOG = 0.1


def _has_length(check: StepCheck) -> bool:
    """Whether a step's length rests on more than one unconfirmed source (the odometry
    is a measurement of its own: a plain wall with odometry is measured along the axis).

    A ``low`` step has one when its laser and feature depth lengths agree within
    :data:`SOURCES_AGREE_LOG` (offset alike throughout the run), or when its feature
    depths stand on a wall with measurable texture: at least
    :data:`~omnipipe.sfm.scale_check.TRACKED_MIN_MATCHES` matches (the bar a feature
    depth length alone is trusted at). A few dozen matches on a plain wall, against a
    laser that does not agree, are no length (random-wide seeds 10, 19, 25: smooth walls
    of contrast 0.05-0.3, 22-48 matches scattering 15-27 %, lengths 15-33 % off)."""
    if check.confidence in ("high", "resolved") or check.bridged_from == "odometry":
        return True
    if check.confidence != "low" or not math.isfinite(check.feature_scale_mm):
        return False
    laser, feature = check.laser_scale_mm, check.feature_scale_mm
    if math.isfinite(laser) and laser > 0 and feature > 0 and abs(math.log(laser / feature)) <= SOURCES_AGREE_LOG:
        return True
    return check.feature_matches >= TRACKED_MIN_MATCHES


def _unverified_plain_run(motion: SfmResult) -> bool:
    """True for a run without odometry none of whose keyframe steps had
    :data:`TRACKED_MIN_MATCHES` feature matches and some of whose frame steps lie in an
    unreliable stretch: the wall has no texture to measure the run by, and part of it
    could not be verified (random-wide seeds 19 and 25, smooth walls of low contrast: 7-42
    matches a step, every frame flagged by the stationary test's bound, scale 22-25 % off,
    28-37 mm per 300 mm; seed 25 with its creeps placed by the wall's shift: 12 frame
    steps still flagged, scale 7.3 % off at a stated 1.8 %; the joints walls of seeds 3
    and 24 had 196-797 matches: measured)."""
    checks = motion.step_checks
    stationary = getattr(motion, "stationary", None)
    if stationary is None or len(stationary) < 2 or any(c.bridged_from == "odometry" for c in checks):
        return False
    if max(c.feature_matches for c in checks) >= TRACKED_MIN_MATCHES:
        return False
    covered = np.zeros(len(stationary) - 1, bool)
    for u in getattr(motion, "unreliable", ()):
        covered[u.first_frame : max(u.last_frame, u.first_frame + 1)] = True
    return bool(covered.any())


def weak_texture_warnings(motion: SfmResult) -> list[str]:
    """One line for a run measured (not refused) without odometry on a wall none of whose
    keyframe steps had :data:`TRACKED_MIN_MATCHES` feature matches: its steps were checked
    along the pipe, but the rig's position across it rests on a few dozen features
    (random-wide seed 25, a smooth wall, 12-42 matches a step, nothing flagged: 0.9 mm
    off across the pipe over 42 mm of travel). Empty for any other run."""
    checks = motion.step_checks
    stationary = getattr(motion, "stationary", None)
    if not checks or stationary is None or any(c.bridged_from == "odometry" for c in checks):
        return []
    most = max(c.feature_matches for c in checks)
    if most >= TRACKED_MIN_MATCHES:
        return []
    return [
        f"the wall gave at most {most} feature matches a keyframe step (fewer than "
        f"{TRACKED_MIN_MATCHES}): the steps' lengths were checked, but the rig's position "
        "across the pipe rests on few features and may be off by a millimetre or more; "
        "odometry and an IMU (odometry.txt, imu.txt) would hold it"
    ]


def refuse_untrusted_motion(motion: SfmResult) -> None:
    """A run that moved but has no step with a usable length is refused.

    Steps of confidence ``low`` with both sources (offset throughout the run) are
    flagged in the report but still give the run its shape. A run whose every step is
    ``none`` (no relative motion, sources that contradict each other, an ambiguous laser
    without features) or ``low`` on one unconfirmed source has no scale anywhere (random
    seed 3, joints wall: 30 steps ``none`` and one laser length of 197 mm that no feature
    confirmed made every placeholder step 197 mm long, ATE 129 mm), nor does one whose
    every step is ``low`` on feature depths of a wall without measurable texture
    (:func:`_has_length`; random-wide seed 10, a smooth wall of contrast 0.1: one step
    from 48 matches, 7 % short, the laser 32 % off it, its frames 33 mm per 300 mm off).
    Nor is one with flagged frame steps on a wall without measurable texture
    (:func:`_unverified_plain_run`).

    A run that moved without a single keyframe step and with frames left unplaced is
    refused too, unless the odometry placed them along the axis (flagged:
    :data:`omnipipe.sfm.types.ODOMETRY_ONLY`; a plain wall whose moving frames made no
    keyframe step).

    Raises:
        ReconstructionError: one line with the most frequent reason.
    """
    checks = motion.step_checks
    moving = 0 if checks else int((~np.asarray(motion.stationary, bool)[1:]).sum())
    placed = getattr(motion, "scale_source", "") == ODOMETRY_ONLY
    if moving and motion.unreliable and not placed:
        # No keyframe step at all (seed 10 of random-wide, a plain wall: its 4 moving
        # frames had too little parallax to become keyframes and too few tracks to be
        # resected; every frame was left at frame 0's pose).
        raise ReconstructionError(
            f"camera motion could not be measured: the rig moved at {moving} frames but no "
            "two frames could be related: too little usable wall texture for features"
        )
    if checks and _unverified_plain_run(motion):
        most = max(c.feature_matches for c in checks)
        raise ReconstructionError(
            f"camera motion could not be verified (frame steps flagged; at most "
            f"{most} feature matches a step, fewer than {TRACKED_MIN_MATCHES}): too little usable "
            "wall texture for features"
        )
    if checks and not any(_has_length(c) for c in checks):
        reasons: dict[str, int] = {}
        for c in checks:
            key = c.reason.split(" (")[0] if c.reason else c.confidence
            key = key.split(" mm")[0].rstrip("0123456789. ") if "scale" in key else key
            reasons[key] = reasons.get(key, 0) + 1
        top = max(reasons, key=lambda k: reasons[k])
        most = max(c.feature_matches for c in checks)
        raise ReconstructionError(
            f"camera motion could not be trusted at any of the {len(checks)} steps "
            f"(most often: {top}; at most {most} feature matches a step): too little usable "
            "wall texture for features, or no laser ring to scale them"
        )
