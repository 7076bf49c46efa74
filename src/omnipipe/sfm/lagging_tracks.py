"""A run whose tracks lag behind the wall, estimated again on the views' local contrast.

The tracker's two finest flow levels read the perspective views after CLAHE
(:class:`~omnipipe.sfm.features.FeatureConfig`, ``flow_plain`` off). CLAHE's tiles are
fixed in the view and, like the rig's own light, hold a broad pattern (a corrugation's
shading, wide tiles) back: every track falls a few per cent short of the wall's true
flow. Two things follow on such a wall, and only there:

- every feature depth length is short by that much, so the laser's template lengths
  (Eq. 17), which no flow enters, run longer than the feature depths throughout the
  run; beyond ``scale_check.max_bias_log`` the run is anchored on the wall-placed
  features (:func:`omnipipe.sfm.step_decide.run_scale`) and its scale rests on the
  wall's own shift to undo the lag;
- the lag is not the same in every part of the view, so each step's direction is bent
  by a fraction of a degree, always the same way, which no scale source sees.

On the views' local contrast (``flow_plain``) the tracks follow the wall: the same
run's feature depths agree with the laser and its directions lose the bend. That
mode is not the default (on every run it lost as many bench runs as it won:
benchmarks/RESULTS.md, feat23, feat24), so it is used where the lag shows:
:func:`lags` (the laser longer than the feature depths beyond the bias bar: a lag
shortens feature depths, never lengthens them) on a wall with texture for it
(:func:`plain_config`, the texture floor). The run is then estimated again and the
second estimate kept when its two sources agree within the bar, its feature depths
lengthened by at least :data:`LAG_SHARE` of the first's offset (:func:`feature_gain`:
the lag was the cause, not a laser that ran long on its own) and it leaves no frame
more unreliable (:func:`kept`); else the first. Measured: benchmarks/RESULTS.md (mot28).
"""

from __future__ import annotations

import math
from dataclasses import replace

import numpy as np

from omnipipe.sfm.types import SfmConfig, SfmResult

# Least share of the first estimate's offset (log) by which the second's feature depths
# must have lengthened (:func:`feature_gain`) for the lag to be what the second undid;
# a laser that ran long on its own comes nearer the feature depths with a better motion
# but barely lengthens them (benchmarks/RESULTS.md, mot28).
LAG_SHARE = 0.5


def lags(config: SfmConfig, result: SfmResult) -> bool:
    """Whether ``result`` was estimated on the CLAHE'd views and its laser lengths run
    longer than its feature depths by more than ``scale_check.max_bias_log`` throughout
    the run (:attr:`SfmResult.laser_offset`: it is then anchored on the wall)."""
    if config.features.flow_plain or not config.tracking.enabled or config.trajectory_from:
        return False
    offset = result.laser_offset
    return math.isfinite(offset) and offset > -1.0 and math.log1p(offset) > config.scale_check.max_bias_log


def plain_config(config: SfmConfig) -> SfmConfig:
    """``config`` with the tracker's fine levels on the views' local contrast
    (``features.flow_plain``)."""
    return replace(config, features=replace(config.features, flow_plain=True))


def feature_gain(first: SfmResult, second: SfmResult) -> float:
    """log of how much longer ``second``'s feature depth lengths are than ``first``'s,
    both measured against ``first``'s poses: per estimate, the sum of its steps' feature
    depth lengths over the sum of ``first``'s distances between the same two frames
    (steps with a feature length whose frames ``first`` registered). NaN when either has
    none. A lag undone lengthens them by about the first's offset; a laser that ran
    long on its own (and moved with the better motion) leaves them as they were."""
    positions = np.asarray(first.world_from_rig)[:, :3, 3]

    def rate(result: SfmResult) -> float:
        feature, travel = 0.0, 0.0
        for c in result.step_checks:
            a, b = c.first_frame, c.last_frame
            if not (math.isfinite(c.feature_scale_mm) and c.feature_scale_mm > 0):
                continue
            if max(a, b) >= len(positions) or not (first.registered[a] and first.registered[b]):
                continue
            feature += c.feature_scale_mm
            travel += float(np.linalg.norm(positions[b] - positions[a]))
        return feature / travel if travel > 0 and feature > 0 else math.nan

    return math.log(rate(second) / rate(first))


def kept(config: SfmConfig, first: SfmResult, second: SfmResult) -> SfmResult:
    """The estimate to keep: ``second`` (on the local contrast) when its laser and feature
    depths agree within ``scale_check.max_bias_log``, its feature depths lengthened by at
    least :data:`LAG_SHARE` of ``first``'s offset (:func:`feature_gain`) and it leaves no
    more frames unregistered and no more stretches unreliable; else ``first``, as it was
    (its own warning already says how far its sources differ). A kept second estimate's
    warnings say why."""
    offset = second.laser_offset
    agree = math.isfinite(offset) and offset > -1.0 and abs(math.log1p(offset)) <= config.scale_check.max_bias_log
    gain = feature_gain(first, second)
    undone = gain >= LAG_SHARE * math.log1p(first.laser_offset)  # False for NaN
    no_worse = (
        int(second.registered.sum()) >= int(first.registered.sum())
        and len(second.unreliable) <= len(first.unreliable)
    )
    if not (agree and undone and no_worse):
        return first
    second.warnings.append(
        f"laser template lengths ran {100.0 * first.laser_offset:+.0f} % over the feature depths "
        "throughout the run: the tracks lagged behind the wall (a broad pattern held back by the "
        "views' contrast), so the motion was estimated again with the tracks on the views' local "
        f"contrast, where the two agree ({100.0 * offset:+.1f} %) and the feature depths are "
        f"{100.0 * gain:+.1f} % longer: that estimate is kept"
    )
    return second
