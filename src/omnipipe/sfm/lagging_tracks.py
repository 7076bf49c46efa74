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
second estimate kept when its two sources agree within the bar (:func:`kept`), else the
first. Measured: benchmarks/RESULTS.md (mot28).
"""

from __future__ import annotations

import math
from dataclasses import replace

from omnipipe.sfm.types import SfmConfig, SfmResult


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


def kept(config: SfmConfig, first: SfmResult, second: SfmResult) -> SfmResult:
    """The estimate to keep: ``second`` (on the local contrast) when its laser and feature
    depths agree within ``scale_check.max_bias_log`` and it leaves no more frames
    unregistered and no more stretches unreliable than ``first``; else ``first``. The
    kept one's warnings say what was done."""
    before = 100.0 * first.laser_offset
    offset = second.laser_offset
    agree = math.isfinite(offset) and offset > -1.0 and abs(math.log1p(offset)) <= config.scale_check.max_bias_log
    no_worse = (
        int(second.registered.sum()) >= int(first.registered.sum())
        and len(second.unreliable) <= len(first.unreliable)
    )
    what = (
        f"laser template lengths ran {before:+.0f} % over the feature depths throughout the run: "
        "the tracks lagged behind the wall (a broad pattern held back by the views' contrast), "
        "so the motion was estimated again with the tracks on the views' local contrast"
    )
    if agree and no_worse:
        second.warnings.append(f"{what}, where the two agree ({100.0 * offset:+.1f} %): that estimate is kept")
        return second
    why = (
        f"the two still differ by {100.0 * offset:+.1f} %" if not agree else "it left more frames unreliable"
    )
    first.warnings.append(f"{what}, but {why}: the first estimate is kept")
    return first
