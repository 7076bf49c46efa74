"""Bundle-adjusted keyframe steps that the wall and the gait confirm.

:func:`check_adjusted` flags a step the bundle adjustment moved away from the length it
was decided on. In a run whose scale the wall anchors (the
laser runs off the feature depths throughout, :class:`omnipipe.sfm.step_decide.RunScale`)
the decided length is often the laser's wrong peak: the adjustment, held by the feature
tracks over several keyframes and by the wall-placed features, moves the step to its
feature depths' length. Those feature depths are then no independent witness (they are
the anchors), so such a step is judged as a step measured by its feature depths alone
is (:func:`omnipipe.sfm.step_resolve.confirm_by_gait`): it is trusted when its adjusted
length is its feature depths' and its pace agrees with the trusted steps around it
(:func:`omnipipe.sfm.step_window.gait_agrees`); otherwise it stays flagged.

Conventions: lengths in mm, in the chain's units (a wall-anchored chain: feature-depth
units).
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import replace

import numpy as np

from omnipipe.sfm.robot_sensors import OdometrySteps
from omnipipe.sfm.scale_check import ODOMETRY_WITNESS, ScaleCheckConfig, StepCheck
from omnipipe.sfm.step_window import gait_agrees

# The reason check_adjusted gives a step it flagged.
MOVED = "bundle adjustment moved the step"


def confirm_adjusted(
    checks: list[StepCheck],
    world_from_kf: np.ndarray,
    counts: np.ndarray,
    config: ScaleCheckConfig,
    warnings: list[str] | None = None,
) -> list[StepCheck]:
    """``checks`` with the steps flagged for the adjustment's move (:data:`MOVED`)
    ``resolved`` where the adjusted length is the step's feature depths' (within
    ``anchor_agree_log`` and ``adjusted_agree_mm``, from at least
    ``feature_only_min_matches`` matches) and its pace agrees with the trusted steps
    around it. For a wall-anchored run only (its chain is in feature-depth units).

    Args:
        checks: (K-1,) the steps' checks after ``check_adjusted``.
        world_from_kf: (K, 4, 4) the adjusted keyframe poses, mm.
        counts: (K-1,) moving frames each step spans
            (:func:`omnipipe.sfm.step_window.moving_counts`).
        warnings: receives one line per confirmed step.
    """
    lengths = np.linalg.norm(np.diff(world_from_kf[:, :3, 3], axis=0), axis=1)
    n = min(len(checks), len(lengths), len(counts))
    trusted = np.array([c.reliable for c in checks[:n]], bool)
    out = list(checks)
    for k in range(n):
        c, length = checks[k], float(lengths[k])
        if c.reliable or not c.reason.startswith(MOVED) or not _features_agree(c, length, config):
            continue
        why = gait_agrees(k, length, lengths[:n], trusted, np.asarray(counts[:n]))
        if not why:
            continue
        reason = (
            f"{c.reason}; its feature depths ({c.feature_scale_mm:.1f} mm) and the gait "
            f"confirm the adjusted length: {why}"
        )
        if warnings is not None:
            warnings.append(f"frames {c.first_frame}->{c.last_frame}: {reason}")
        out[k] = replace(c, confidence="resolved", reason=reason)
    return out


def _features_agree(check: StepCheck, length: float, config: ScaleCheckConfig) -> bool:
    """Whether the step's feature-depth length is ``length`` (mm, same units)."""
    f = check.feature_scale_mm
    if f is None or not (math.isfinite(f) and f > 0 and length > 0):
        return False
    return (
        abs(math.log(length / f)) <= config.anchor_agree_log
        and abs(length - f) <= config.adjusted_agree_mm
        and check.feature_matches >= config.feature_only_min_matches
    )


# Fewest reliable steps for check_adjusted to remove a source's run-wide ratio: with 3
# (random-wide seed 21, 32 frames) the adjustment's own +8 % drift of two of them was
# taken for the laser's bias and no step was flagged.
ADJUSTED_OFFSET_MIN_STEPS = 5


def check_adjusted(
    checks: list[StepCheck],
    world_from_kf: np.ndarray,
    config: ScaleCheckConfig,
    decided_unit: float = 1.0,
    feature_unit: float | None = None,
    wall_mm: dict[int, tuple[float, float]] | None = None,
    odometry: OdometrySteps | None = None,
) -> list[StepCheck]:
    """Flag keyframe steps whose adjusted length left what their sources measured.

    The sources are the length the step was decided on (``scale_mm``: the laser's,
    re-matched, or the feature depths') and its feature-depth length; each is compared
    after removing its run-wide ratio to the adjusted lengths (a consistent bias is
    not a jump). A step is flagged when it left the decided length by more than
    ``adjusted_agree_log``, or every source by more than ``adjusted_agree_mm``. (The
    laser's best peak is not a source here: on a resolved step it is the wrong course.)

    ``decided_unit``: the decided lengths' unit in the chain's (the run-wide laser /
    feature-depth gain when the wall anchors the scale: the decided lengths are in
    laser units, the chain in feature-depth units). Without it a run with fewer than
    :data:`ADJUSTED_OFFSET_MIN_STEPS` steps would flag every step by the gain itself.

    A step whose adjusted length is its feature depths' (within ``anchor_agree_log`` and
    ``adjusted_agree_mm``, from at least ``feature_only_min_matches`` matches) is not
    flagged: the adjustment corrected a wrong decided length. Only when the feature
    depths are an independent measurement in the chain's units: ``feature_unit``, their
    unit in the chain's (a laser-anchored run: the run-wide laser / feature-depth gain),
    is given (None: a wall-anchored run, whose anchors are those feature depths, or an
    unknown unit); their run-wide ratio to the adjusted lengths replaces it when
    measured (at least :data:`ADJUSTED_OFFSET_MIN_STEPS` steps).

    ``wall_mm``: step k -> (length, 1-sigma) mm the wall's own shift read, where the
    adjustment was held to it (:func:`omnipipe.sfm.step_priors.wall_priors`): a third
    measured length; a step within :data:`WALL_CONFIRM_SIGMAS` of it, the reading
    itself within :data:`WALL_SOURCE_LOG` of one of the other sources, is not flagged.

    ``odometry``: the robot's travel per step, a witness (:func:`_odometry_confirms`): a
    step it confirms, unless :func:`confirm_adjusted` may, is ``resolved`` (not for the scale).
    """
    lengths = np.linalg.norm(np.diff(world_from_kf[:, :3, 3], axis=0), axis=1)
    ok = [
        k
        for k, c in enumerate(checks)
        if k < len(lengths) and c.reliable and lengths[k] > 1e-9 and math.isfinite(c.scale_mm)
    ]

    def offsets(values: list[float]) -> tuple[np.ndarray, float]:
        v = np.array(values, float)
        with np.errstate(invalid="ignore", divide="ignore"):
            r = np.log(lengths[ok] / v) if ok else np.zeros(0)
        good = r[np.isfinite(r)]
        return r, float(np.median(good)) if len(good) >= ADJUSTED_OFFSET_MIN_STEPS else 0.0

    r_dec, m_dec = offsets([checks[k].scale_mm / decided_unit for k in ok])
    r_feat, m_feat = offsets([checks[k].feature_scale_mm for k in ok])
    odo = _odometry_witness(odometry, len(lengths), ok, offsets)
    # log(chain / feature-depth length) run-wide for the confirmation: measured, or the unit's
    m_unit = m_feat
    if feature_unit is not None and np.isfinite(r_feat).sum() < ADJUSTED_OFFSET_MIN_STEPS:
        m_unit = math.log(feature_unit)
    out = list(checks)
    for j, k in enumerate(ok):
        c, length = checks[k], float(lengths[k])
        devs = [
            (name, float(r - m))
            for name, r, m in (("decided", r_dec[j], m_dec), ("feature depth", r_feat[j], m_feat))
            if np.isfinite(r)
        ]
        if feature_unit is not None and _feature_confirms(r_feat[j] - m_unit, c, length, config):
            continue
        reason = _moved(devs, length, config)
        if not reason or _wall_confirms((wall_mm or {}).get(k), length, [length * math.exp(-d) for _, d in devs]):
            continue
        reason = f"{MOVED} to {length:.1f} mm, {reason}"
        later = feature_unit is None and _features_agree(c, length, config)  # confirm_adjusted's
        if odo is not None and not later and _odometry_confirms(odo[0][j], odo[1][k], length, config):
            reason += f"{ODOMETRY_WITNESS} {length * math.exp(-odo[0][j]):.1f} mm"
        out[k] = replace(c, confidence="resolved" if ODOMETRY_WITNESS in reason else "none", reason=reason)
    return out


def _moved(devs: list[tuple[str, float]], length: float, config: ScaleCheckConfig) -> str:
    """How the adjusted ``length`` (mm) left the step's sources (``devs``: each one's log
    deviation from it, run-wide ratio removed, the decided length's first); "" if not."""
    # Each source's length in the adjusted run's units, and how far it lies (mm).
    gaps = [abs(length - length * math.exp(-d)) for _, d in devs]
    if devs and abs(devs[0][1]) > config.adjusted_agree_log:
        return f"{100 * devs[0][1]:+.0f} % from its measured length"
    if gaps and min(gaps) > config.adjusted_agree_mm:
        return f"{min(gaps):.1f} mm from the nearest of its measured lengths"
    return ""


# A step held to the wall's reading is confirmed by it within this many of the
# reading's sigmas, when the reading lies within WALL_SOURCE_LOG of one of the step's
# other sources (a periodic wall's wrong course lies further; random-wide seed 29,
# smooth: steps 9->14 and 14->19 held to the wall's 27.1 and 20.4 mm, true 27.03 and
# 20.44, their feature depths 7 and 9 % short, flagged "1.0 mm from the nearest of its
# measured lengths").
WALL_CONFIRM_SIGMAS = 2.0
WALL_SOURCE_LOG = 0.1


def _wall_confirms(wall: tuple[float, float] | None, length: float, sources_mm: list[float]) -> bool:
    """Whether the wall's reading ``wall`` (length, 1-sigma mm) confirms the adjusted
    ``length`` (mm) and itself agrees with one of ``sources_mm`` (the step's other
    sources in the adjusted run's units)."""
    if wall is None or not all(math.isfinite(v) and v > 0 for v in wall):
        return False
    mm, sigma = wall
    return abs(length - mm) <= WALL_CONFIRM_SIGMAS * sigma and any(
        math.isfinite(v) and v > 0 and abs(math.log(mm / v)) <= WALL_SOURCE_LOG for v in sources_mm
    )


def _feature_confirms(
    dev_log: float, check: StepCheck, length: float, config: ScaleCheckConfig
) -> bool:
    """Whether a step's feature depths (``dev_log``: the adjusted ``length`` (mm) over
    theirs in the chain's units, log; NaN: not measured) confirm it."""
    return (
        math.isfinite(dev_log)
        and abs(dev_log) <= config.anchor_agree_log
        and check.feature_matches >= config.feature_only_min_matches
        and abs(length - length * math.exp(-dev_log)) <= config.adjusted_agree_mm
    )


# A step the bundle adjustment moved is confirmed by the odometry within this many of
# its stated sigmas (and adjusted_agree_mm). Features bench at 73373dd (400x300, odometry
# with 1-3 % slip): of the 19 steps flagged for the adjustment's move, 8 lay within
# 0.75 mm of the raw odometry, all of them within 0.5 mm of the true step; the 11 others
# include every move that was wrong (1.1-13.9 mm off the truth).
ODOMETRY_CONFIRM_SIGMAS = 2.0


def _odometry_witness(
    odometry: OdometrySteps | None,
    n: int,
    ok: list[int],
    offsets: Callable[[list[float]], tuple[np.ndarray, float]],
) -> tuple[np.ndarray, np.ndarray] | None:
    """Per reliable step (``ok``) the log of its adjusted length over the odometry's,
    the run-wide ratio removed, and per step (``n``) the odometry's stated sigma in the
    adjusted lengths' units (mm); None without odometry or a measured ratio
    (``offsets``: :func:`check_adjusted`'s, on the odometry's lengths)."""
    if odometry is None or len(odometry.length_mm) < n:
        return None
    r, m = offsets([float(odometry.length_mm[k]) for k in ok])
    if np.isfinite(r).sum() < ADJUSTED_OFFSET_MIN_STEPS:
        return None
    return r - m, np.asarray(odometry.sigma_mm, float)[:n] * math.exp(m)


def _odometry_confirms(dev_log: float, sigma_mm: float, length: float, config: ScaleCheckConfig) -> bool:
    """Whether the odometry (``dev_log``: the adjusted ``length`` (mm) over its length in
    the same units, log, its run-wide ratio removed, measured over at least
    :data:`ADJUSTED_OFFSET_MIN_STEPS` steps; ``sigma_mm`` its stated 1-sigma there)
    confirms the step: within ``adjusted_agree_mm`` and :data:`ODOMETRY_CONFIRM_SIGMAS`."""
    if not (math.isfinite(dev_log) and math.isfinite(sigma_mm) and sigma_mm > 0):
        return False
    gap = abs(length - length * math.exp(-dev_log))
    return gap <= config.adjusted_agree_mm and gap <= ODOMETRY_CONFIRM_SIGMAS * sigma_mm
