"""The run's scale bounded by the robot's odometry where vision cannot bound it.

:func:`omnipipe.sfm.run_length.run_length` decides the run's scale from vision alone
(laser, wall-placed features, the wall's own shift) with a relative 1-sigma; the
odometry only checked it (:func:`omnipipe.sfm.robot_sensors.odometry_disagreement`) and
bridged the steps vision lost. Where vision's sigma is as large as the odometry's own
(a reducer breaking the feature depths' cylinder, both sources short, a few steps), its
scale stayed vision's whatever the odometry said. Here the odometry's travel over the
steps vision measured is a second reading of the run's scale, mixed in by inverse
variance (:func:`omnipipe.sfm.run_length.mix`: the gap between the two in the sigma),
with a weight that is 0 while vision's sigma is under half the odometry's and reaches
the inverse-variance weight where vision's is the odometry's or more
(:data:`VISION_BOUNDS_RATIO`): the odometry never overrides good vision.

Conventions: log ratios natural; sigmas relative; lengths mm.
"""

from __future__ import annotations

import math
from dataclasses import replace

import numpy as np

from omnipipe.sfm.robot_sensors import OdometrySteps
from omnipipe.sfm.run_length import RunLength, mix, ramp
from omnipipe.sfm.scale_check import StepCheck

# Vision's relative sigma over the odometry's at which the odometry starts to count
# (first value) and counts with its full inverse-variance weight (second). Under the
# first, vision bounds the run's scale better than the odometry can (its slip, 1-3 %
# on real robots, would only pull a good run off: random-wide with sensors, whose
# vision sigmas are 0.4-1.5 %).
VISION_BOUNDS_RATIO = (0.5, 1.0)

# Least odometry travel over the steps vision measured, in multiples of its resolution.
MIN_TRAVEL_FLOORS = 20.0
# Fewest steps vision measured for the odometry's reading: over 1-3 steps its timing at
# the keyframes (the interpolation at stops) reads 2-5 % beyond its slip (random-wide
# 30s: +4.2 % over 3 steps with a 2.1 % slip; random-features 13, 24: 1 step each).
MIN_READING_STEPS = 4


def odometry_reading(
    world_from_kf: np.ndarray, checks: list[StepCheck], odometry: OdometrySteps
) -> tuple[float, float, int] | None:
    """The odometry's reading of the run's scale: log(odometry travel / vision's
    adjusted length) summed over the steps whose own sources measured them
    (:attr:`StepCheck.measures_scale`) and which the odometry covers, its relative
    1-sigma and the number of steps; None without enough travel or fewer than
    :data:`MIN_READING_STEPS` steps. The sigma: the steps'
    stated relative parts (the slip, one bias over the run) summed, their noise
    (:attr:`OdometrySteps.noise_mm`: walk, resolution, interpolation) in quadrature."""
    pos = np.asarray(world_from_kf, float)[:, :3, 3]
    vision = travel = shared = noise2 = 0.0
    n = 0
    for k, c in enumerate(checks):
        d = float(odometry.length_mm[k])
        if not (c.measures_scale and math.isfinite(d) and d > 4 * odometry.floor_mm):
            continue
        if not math.isfinite(float(odometry.sigma_mm[k])):
            continue
        vision += float(np.linalg.norm(pos[k + 1] - pos[k]))
        travel += d
        noise = 0.0 if odometry.noise_mm is None else float(odometry.noise_mm[k])
        shared += math.sqrt(max(float(odometry.sigma_mm[k]) ** 2 - noise**2, 0.0))
        noise2 += noise**2
        n += 1
    if n < MIN_READING_STEPS or vision <= 0 or travel < MIN_TRAVEL_FLOORS * odometry.floor_mm:
        return None
    return math.log(travel / vision), math.hypot(shared, math.sqrt(noise2)) / travel, n


def with_odometry_scale(
    length: RunLength,
    world_from_kf: np.ndarray,
    checks: list[StepCheck],
    odometry: OdometrySteps | None,
    warnings: list[str],
) -> RunLength:
    """``length`` (vision's scale of the adjusted keyframes ``world_from_kf`` (K, 4, 4)
    mm, ``checks`` (K-1,) their steps) with the ``odometry``'s reading mixed in
    (module docstring); unchanged without odometry, a finite vision sigma or enough
    travel, or where vision bounds the scale (weight 0). A warning says what was
    combined."""
    if odometry is None or not (math.isfinite(length.sigma_rel) and length.sigma_rel > 0):
        return length
    reading = odometry_reading(world_from_kf, checks, odometry)
    if reading is None:
        return length
    odo_log, odo_sigma, n = reading
    if not odo_sigma > 0:
        return length
    sv = length.sigma_rel
    weight = ramp(sv / odo_sigma, *VISION_BOUNDS_RATIO) * sv**2 / (sv**2 + odo_sigma**2)
    if weight <= 0:
        return length
    vision_log = 0.0 if math.isnan(length.correction_log) else length.correction_log
    applied, sigma = mix(weight, (vision_log, sv), (odo_log, odo_sigma))
    warnings.append(
        f"run's scale combined with the odometry's: vision {100 * (math.exp(vision_log) - 1):+.2f} "
        f"+- {100 * sv:.2f} %, odometry {100 * (math.exp(odo_log) - 1):+.2f} +- {100 * odo_sigma:.2f} % "
        f"over {n} steps (weight {weight:.2f}): {100 * (math.exp(applied) - 1):+.2f} +- {100 * sigma:.2f} %"
    )
    return replace(
        length,
        correction_log=applied,
        sigma_rel=sigma,
        source=f"{length.source}, bounded by the odometry (weight {weight:.2f})",
    )
