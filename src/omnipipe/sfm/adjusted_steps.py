"""Bundle-adjusted keyframe steps that the wall and the gait confirm.

:func:`omnipipe.sfm.step_scale.check_adjusted` flags a step the bundle adjustment moved
away from the length it was decided on. In a run whose scale the wall anchors (the
laser runs off the feature depths throughout, :class:`omnipipe.sfm.step_scale.RunScale`)
the decided length is often the laser's wrong peak: the adjustment, held by the feature
tracks over several keyframes and by the wall-placed features, moves the step to its
feature depths' length. Those feature depths are then no independent witness (they are
the anchors), so such a step is judged as a step measured by its feature depths alone
is (:func:`omnipipe.sfm.step_scale.confirm_by_gait`): it is trusted when its adjusted
length is its feature depths' and its pace agrees with the trusted steps around it
(:func:`omnipipe.sfm.step_window.gait_agrees`); otherwise it stays flagged.

Conventions: lengths in mm, in the chain's units (a wall-anchored chain: feature-depth
units).
"""

from __future__ import annotations

import math
from dataclasses import replace

import numpy as np

from omnipipe.sfm.scale_check import ScaleCheckConfig, StepCheck
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
