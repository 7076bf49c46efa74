"""The run's metric scale after the bundle adjustment, and its relative 1-sigma
(paper Sec. V-D).

:func:`run_length`: the adjusted run's lengths against the laser's decided ones
(:func:`decided_log`) and the wall-placed features'
(:func:`omnipipe.sfm.scale_check.wall_scale_correction`), combined by inverse variance
(:func:`combine_scales`); the sigma from the anchors' spread and the sources' gap
(:func:`scale_sigma`) plus the part both sources share (:data:`SHARED_SCALE_SIGMA`)
and, where the wall placed lengths, its radius change along the run
(:func:`with_radius_change`).

Conventions: log ratios natural; sigmas relative.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from omnipipe.sfm.scale_check import (
    WALL_SCALE_SIGMA_FLOOR,
    StepCheck,
    median_with_sigma,
    wall_radius_change,
    wall_scale_correction,
)
from omnipipe.sfm.shift_scale import ShiftScale, shift_scale
from omnipipe.sfm.step_chain import ChainedSteps
from omnipipe.sfm.step_decide import RunScale
from omnipipe.sfm.types import Anchor, Keyframes, SfmContext
from omnipipe.spill import dropping_pages

# Relative 1-sigma both scale sources share, added to every run's: the laser (Eq. 17)
# and the wall-placed features both rest on the light-section ring and the relative
# motion, and on random rigs runs whose two sources agreed still came out 0.35-0.54 %
# off (bench_robustness seeds 15, 24, 25 at 800x600; cause not found). On the 40
# random-wide renders at 640x480 (--full at 62672fb) the 13 runs stated below 0.5 %
# were off by 0.39 % RMS, seeds 22 (mosaic) and 23 (photo) by 0.62 and 0.60 % at 0.30
# and 0.29 % stated: their laser, feature depths and wall's shift all long on every step
# (22: +0.4, +0.5 and +0.45 % median), the bench's whole-trajectory fit and the
# keyframes' own steps alike (scale34). 0.35 % (was 0.25) makes the +-2 sigma interval
# cover every run with at most 10 % of its steps flagged (worst 1.6 sigma).
SHARED_SCALE_SIGMA = 0.0035

# The wall's own shift overrules the laser and wall-placed features' correction as their
# disagreement grows: its weight rises from 0 at this many sigmas of the gap to 1 at
# :data:`SHIFT_OVERRULES_SIGMAS`'s second value (linear in the gap's sigmas; the hard
# switch at 3 sigma it replaces flipped on 0.1 % input changes). On the random-wide runs
# where the laser and feature depths ran short together (tiles, seeds 32 and 35: their
# step lengths' medians 5-6 % and 2-5 % short) the shift's steps' median was within
# 0.7 % of the truth on every seed read (benchmarks/RESULTS.md, scale32).
SHIFT_OVERRULES_SIGMAS = (2.0, 4.0)

# Relative 1-sigma of a bias the laser and the wall-placed features share, which their
# agreement and spread do not show, when a third source can see it: on the random-wide
# renders at 640x480 the feature depths' step lengths ran a median 0.6-6.2 % short on all
# six seeds read (0, 8, 18, 21, 32, 35; RMS 3.4 %), the laser's -6 to +0.4 % (RMS 3.3 %),
# and the wall-set correction of seed 35 stated +-0.11 % for a 1.9 % error
# (benchmarks/RESULTS.md, scale32). At 1 % the combination kept 1.2-1.3 % of their bias
# on seeds 0, 8, 18, 35 where the wall's shift read within 0.3-0.8 % (scale33).
SOURCES_BIAS_SIGMA = 0.03
# The weight of the shared bias above grows linearly with the chi-square of the gap
# between the run's scale and the wall shift's (over their own variances) from 0 at the
# first value to 1 at the second (a gap well within their sigmas shows none; on full-size
# clean runs the laser's 0.25 % would otherwise weigh as little as the shift's 1 %:
# bend's scale error 0.04 -> 0.18 %). Chosen over (0.5, 1.5) and (0, 1) on bench_robustness
# replays (two RANSAC seeds; benchmarks/RESULTS.md, ransac17).
BIAS_SHOWN_CHI2 = (0.25, 1.25)

# The laser's decided lengths replace the adjusted run as its reading of the laser in
# proportion to how many of the laser's sigmas they differ by: not at all within the
# first value, fully beyond the second, linearly between (within its sigma the
# adjustment's pixel-weighted fit of the laser points reads them as well as their
# lengths' median: measured on bench_robustness, benchmarks/RESULTS.md, depth5). The
# laser's sigma in this test is at least :data:`DECIDED_SIGMA_FLOOR`: a laser whose
# matches agree within 0.1-0.5 % still reads the run's length no better than about 1 %
# (random-wide seeds 9 and 31 at 640x480: decided corrections of 0.36 and 1.8 % at 2.8
# and 3.7 of their sigmas made the scale error 0.04 -> 0.17 % and 0.22 -> 0.71 %;
# benchmarks/RESULTS.md, ransac16).
DECIDED_SIGMAS = (1.0, 3.0)
DECIDED_SIGMA_FLOOR = 0.01

# Relative 1-sigma a run's feature depths share, in proportion to the share of its length
# anchored by features placed on the light-section wall rather than laser matches
# (:func:`feature_share`): the per-step floor of a feature-depth length
# (:data:`omnipipe.sfm.scale_check.FEATURE_DEPTH_SIGMA_FLOOR`, the wall model and the
# relative motion's direction) is one bias over the run's steps, which their matches'
# spread does not show. Added to the stated sigma only, after the combination, not to its
# weights (why: benchmarks/RESULTS.md, feat21).
FEATURE_ANCHOR_SIGMA = 0.01

# The keyframe rings' own scatter of radius in a straight cylinder (half the relative
# range; the ring's tilt, its fit on a partial ring), taken off the wall's radius change
# in quadrature: on the 40 random-wide renders at 640x480 (cylinders) it reached 0.53 %
# (seed 7), and with it in the sigma seed 7's rose 0.68 -> 0.86 %; random-features
# seeds 30 and 19 (reducers) read 10.8 and 5.1 %.
RADIUS_CHANGE_FLOOR = 0.01
# The widening (the change beyond the floor) from which it is also a warning.
RADIUS_CHANGE_WARN = 0.01


@dataclass(frozen=True)
class RunLength:
    """The run's metric scale after the bundle adjustment.

    Attributes:
        correction_log: log of the factor to apply to every length (NaN: none).
        sigma_rel: relative 1-sigma of lengths along the run (shared part included;
            NaN: unknown).
        wall_log: log of the factor by which the wall's lengths exceed the adjusted
            run's (NaN: too few reliable steps to tell).
        source: where the scale comes from (:attr:`omnipipe.sfm.types.SfmResult.scale_source`).
    """

    correction_log: float
    sigma_rel: float
    wall_log: float
    source: str


RUN_LENGTH_DROP_S = 0.02
"""Seconds between two page drops (:func:`omnipipe.spill.dropping_pages`) within
:func:`run_length`: its passes read every keyframe's features and ring from the scratch
within a second or two."""


@dropping_pages(RUN_LENGTH_DROP_S)  # the scratch's pages dropped while it reads (the same result)
def run_length(
    ctx: SfmContext,
    world_from_kf: np.ndarray,
    chain: ChainedSteps,
    kf: Keyframes,
    scale: RunScale,
    readings: dict[int, tuple[float, float]] | None = None,
) -> RunLength:
    """The run's scale after the adjustment (``world_from_kf``, (K, 4, 4) mm; ``chain``
    with the checks of :func:`check_adjusted`): the anchors' spread and the sources' gap give its
    sigma; with ``scale_from_wall`` it is combined with the features placed on the
    light-section wall (:func:`combine_scales`) and the wall's own shift
    (:func:`combine_shift`; ``readings``: steps already read off the wall on these poses,
    :class:`omnipipe.sfm.step_priors.WallPriors`). Where the wall placed lengths, the
    sigma carries the wall's radius change along the run (:func:`with_radius_change`)."""
    config = ctx.config
    wall = wall_scale_correction(
        world_from_kf,
        [(p.a, p.b, p.matches) for p in chain.pair_matches],
        [f.rays_in_rig for f in kf.features],
        kf.ring_points,
        chain.checks,
        config.scale_check,
    )
    source = "feature depths on the light-section wall" if scale.wall_anchored else "laser (Eq. 17)"
    sigma = scale_sigma(chain.anchors, chain.scales_mm, scale.offset_log, scale.wall_anchored)
    applied = math.nan
    if config.scale_from_wall and wall is not None:
        # The laser's say is its decided lengths against the adjusted ones. (Without the
        # wall's, too few steps, the adjusted run is kept: a run whose one step the
        # adjustment had right would lose it; benchmarks/RESULTS.md, depth5.)
        decided = decided_log(
            chain.checks, chain.scales_mm, world_from_kf, config.scale_check.adjusted_agree_log
        )
        laser_log, laser_sigma = laser_say(decided, sigma)
        applied, sigma = combine_scales(
            wall[0], math.hypot(wall[1], WALL_SCALE_SIGMA_FLOOR), laser_sigma, scale.wall_anchored,
            laser_log,
        )
        if scale.wall_anchored:
            sigma = math.hypot(sigma, abs(scale.offset_log) / 2)  # as scale_sigma's
        if not scale.wall_anchored:
            source = "laser (Eq. 17), combined with feature depths on the light-section wall"
    if config.scale_from_wall:
        shift = shift_scale(ctx, kf, world_from_kf, chain.checks, readings)
        if shift is not None:
            applied, sigma = combine_shift(applied, sigma, shift)
            source = f"{source}, and the wall's own shift ({shift.steps} steps)"
    wall_log = math.nan if wall is None else wall[0]
    sigma = math.hypot(sigma, SHARED_SCALE_SIGMA)
    share = feature_share(chain.anchors, chain.scales_mm)
    if not scale.wall_anchored:  # (a wall-anchored run's sigma carries half the sources' gap)
        sigma = math.hypot(sigma, FEATURE_ANCHOR_SIGMA * share)
    if scale.wall_anchored or share > 0 or math.isfinite(applied):  # lengths the wall placed
        sigma = with_radius_change(sigma, wall_radius_change(kf.ring_points), ctx.warnings)
    sigma = with_bridged(sigma, chain.checks, chain.scales_mm)
    return RunLength(applied, sigma, wall_log, source)


def ramp(x: float, lo: float, hi: float) -> float:
    """0 at ``x <= lo``, 1 at ``x >= hi``, linear between (continuous in ``x``)."""
    return min(1.0, max(0.0, (x - lo) / (hi - lo)))


def mix(p: float, a: tuple[float, float], b: tuple[float, float]) -> tuple[float, float]:
    """Two readings (log, relative 1-sigma) mixed with weight ``p`` on ``b``: the mean
    ``(1 - p) a + p b`` and the mixture's sigma (both variances weighted, plus the
    spread ``p (1 - p) (b - a)^2`` between the two): the combination's own uncertainty
    is carried into the sigma rather than hidden."""
    mean = (1.0 - p) * a[0] + p * b[0]
    var = (1.0 - p) * a[1] ** 2 + p * b[1] ** 2 + p * (1.0 - p) * (b[0] - a[0]) ** 2
    return mean, math.sqrt(var)


def laser_say(decided_log: float, sigma: float) -> tuple[float, float]:
    """The laser's correction of the adjusted run and its relative 1-sigma: the decided
    lengths' log correction ``decided_log`` (:func:`decided_log`) weighted by its
    significance against the laser's ``sigma`` (:data:`DECIDED_SIGMAS`, a ramp), the
    rest the adjusted run's own (0); the two mixed (:func:`mix`). A non-finite
    ``sigma``: (0, sigma)."""
    if not (math.isfinite(sigma) and sigma > 0):
        return 0.0, sigma
    z = abs(decided_log) / max(sigma, DECIDED_SIGMA_FLOOR)
    return mix(ramp(z, *DECIDED_SIGMAS), (0.0, sigma), (decided_log, sigma))


def combine_shift(applied_log: float, sigma: float, shift: ShiftScale) -> tuple[float, float]:
    """The run's log correction ``applied_log`` (NaN: none, the adjusted run as it is)
    with relative 1-sigma ``sigma`` (laser and wall-placed features) combined with the
    wall's own shift (:func:`omnipipe.sfm.shift_scale.shift_scale`): two combinations,
    ``sigma`` as it is and widened by :data:`SOURCES_BIAS_SIGMA` (their shared bias),
    mixed (:func:`mix`) with the bias's weight growing with the gap's chi-square
    (:data:`BIAS_SHOWN_CHI2`). Each is :func:`_with_shift`. Without a finite ``sigma``
    the shift alone. Continuous in every input.

    Returns:
        (log correction to apply to every length, relative 1-sigma).
    """
    if not (math.isfinite(sigma) and sigma > 0):
        return shift.log, shift.sigma
    base = 0.0 if math.isnan(applied_log) else applied_log
    chi2 = (base - shift.log) ** 2 / (sigma**2 + shift.sigma**2)
    q = ramp(chi2, *BIAS_SHOWN_CHI2)
    return mix(
        q, _with_shift(base, sigma, shift), _with_shift(base, math.hypot(sigma, SOURCES_BIAS_SIGMA), shift)
    )


def _with_shift(base: float, sigma: float, shift: ShiftScale) -> tuple[float, float]:
    """``base`` +- ``sigma`` (relative) and the wall's shift: the inverse-variance mean,
    its sigma scaled by sqrt(chi-square) when the two disagree beyond their sigmas (as
    :func:`combine_scales`), mixed (:func:`mix`) with the shift alone (half the gap added
    to its sigma: the other value stays within 2 sigma) by a weight rising with the gap's
    sigmas (:data:`SHIFT_OVERRULES_SIGMAS`)."""
    gap2 = (base - shift.log) ** 2
    chi2 = gap2 / (sigma**2 + shift.sigma**2)
    w_base, w_shift = 1.0 / sigma**2, 1.0 / shift.sigma**2
    mean = (w_base * base + w_shift * shift.log) / (w_base + w_shift)
    both = (mean, math.sqrt(max(chi2, 1.0) / (w_base + w_shift)))
    alone = (shift.log, math.sqrt(shift.sigma**2 + gap2 / 4))
    return mix(ramp(math.sqrt(chi2), *SHIFT_OVERRULES_SIGMAS), both, alone)


def decided_log(
    checks: list[StepCheck], scales_mm: list[float], world_from_kf: np.ndarray, max_log: float
) -> float:
    """log of the factor by which the reliable steps' chained lengths (``scales_mm``,
    (K-1,) mm: the decided ones, in the chain's units) exceed their adjusted lengths
    (``world_from_kf``, (K, 4, 4) mm), length-weighted; 0 when no step can say. Steps
    further off than ``max_log`` (flagged by :func:`check_adjusted`) do not count.

    The bundle adjustment does not keep the anchors' run length: on random-wide seeds 0
    and 21 (640x480) it shortened the run by 1.9 % and 0.2 % against the laser lengths
    it was anchored on (both sources agreed within 0.2 % and 1.3 %)."""
    lengths = np.linalg.norm(np.diff(np.asarray(world_from_kf)[:, :3, 3], axis=0), axis=1)
    logs, weights = [], []
    for k, c in enumerate(checks):
        if k >= min(len(lengths), len(scales_mm)) or not c.measures_scale:
            continue
        if not (scales_mm[k] > 0) or lengths[k] <= 1e-9:
            continue
        r = math.log(scales_mm[k] / lengths[k])
        if abs(r) <= max_log:
            logs.append(r)
            weights.append(lengths[k])
    return float(np.average(logs, weights=weights)) if logs else 0.0


def combine_scales(
    wall_log: float,
    wall_sigma: float,
    laser_sigma: float,
    wall_anchored: bool,
    laser_log: float = 0.0,
) -> tuple[float, float]:
    """The run's scale from its two metric sources, after the bundle adjustment.

    The laser (Eq. 17) says the adjusted run's lengths need the log correction
    ``laser_log`` (:func:`decided_log`: its decided lengths over the adjusted ones; 0
    when the adjustment kept them) with relative sigma ``laser_sigma`` (its matches'
    spread and its run-wide gap to the feature depths); the wall
    (:func:`omnipipe.sfm.scale_check.wall_scale_correction`) says ``wall_log``
    with ``wall_sigma``. Inverse-variance weighted mean; when the two disagree by more
    than their sigmas explain (chi-square per degree of freedom > 1), the combined
    sigma is scaled by its square root (the Particle Data Group's scale factor), so a
    disagreement widens the stated uncertainty instead of hiding. A run already
    anchored on the wall (``wall_anchored``) takes the wall's value: the two are one
    source then.

    Measured (path-length error, laser alone -> combined, full-size datasets): paper
    -0.01 -> +0.05 %, bend +0.41 -> +0.07 % (docs/pipeline.md); bench_robustness
    seeds 0-29: median scale error 0.29 % (0.31 % before the stripe fix and this).

    Returns:
        (log correction to apply to every length, relative 1-sigma of the result).
    """
    if wall_anchored or not (math.isfinite(laser_sigma) and laser_sigma > 0):
        return wall_log, wall_sigma
    w_wall, w_laser = 1.0 / wall_sigma**2, 1.0 / laser_sigma**2
    mean = (w_wall * wall_log + w_laser * laser_log) / (w_wall + w_laser)
    sigma = 1.0 / math.sqrt(w_wall + w_laser)
    chi2 = (wall_log - laser_log) ** 2 / (wall_sigma**2 + laser_sigma**2)
    return mean, sigma * math.sqrt(max(chi2, 1.0))


def scale_sigma(
    anchors: list[Anchor], scales_mm: list[float], offset_log: float, wall_anchored: bool
) -> float:
    """Relative 1-sigma of lengths: the anchors' statistical part, plus the systematic
    part. With laser anchors, the run-wide gap to the feature depths (which source is
    right within it is unknown: measured bend 0.43 % scale error, gap 0.4 %; paper
    0.02 %, gap 0.1 %). With wall anchors, 0.1 % and half the gap: the feature depths
    are taken where the laser runs more than 5 % off them, mostly rightly (random-wide
    seeds 8, 11, 13, 20 at 640x480: laser 5-12 % short, feature depths within 0.8 %),
    but on seeds 12 and 18 (corrugated) the laser was right and the feature depths 4.5
    and 6 % short: +-2 sigma spans both sources."""
    stat = _scale_sigma_rel(anchors, scales_mm)
    if not math.isfinite(stat):
        return stat
    if wall_anchored:
        return math.hypot(stat, 0.001, abs(offset_log) / 2)
    return math.hypot(stat, abs(offset_log))


def with_radius_change(sigma: float, change: float, warnings: list[str]) -> float:
    """The run's relative 1-sigma ``sigma`` with the wall's radius change along the run
    (``change``, :func:`omnipipe.sfm.scale_check.wall_radius_change`, less the rings' own
    scatter :data:`RADIUS_CHANGE_FLOOR` in quadrature) in quadrature: the feature depths
    and the wall's own shift take the ring's radius for the features' wall, so a reducer
    between them biases every length they give by up to that much (a warning says so
    from :data:`RADIUS_CHANGE_WARN` on)."""
    beyond = math.sqrt(max(change**2 - RADIUS_CHANGE_FLOOR**2, 0.0))
    if not (math.isfinite(sigma) and beyond > 0):
        return sigma
    widened = math.hypot(sigma, beyond)
    if beyond >= RADIUS_CHANGE_WARN:
        warnings.append(
            f"the wall's radius changes by +-{100 * change:.1f} % along the run (a reducer or an "
            "offset): the feature depths and the wall's own shift take the ring's radius for the "
            f"features' wall, so the scale sigma carries it: {100 * sigma:.2f} -> {100 * widened:.2f} %"
        )
    return widened


def feature_share(anchors: list[Anchor], scales_mm: list[float]) -> float:
    """The share (0-1) of the anchored steps' length (``scales_mm``, (K-1,) mm) whose
    anchors are features placed on the light-section wall, not laser matches (a step
    whose laser did not confirm its feature depths closely, :func:`omnipipe.sfm.step_decide.decide_step`)."""
    steps = {a.a for a in anchors if a.b == a.a + 1 and 0 <= a.a < len(scales_mm) and scales_mm[a.a] > 0}
    laser = {a.a for a in anchors if a.b == a.a + 1 and a.epipolar}
    total = sum(scales_mm[k] for k in steps)
    return sum(scales_mm[k] for k in steps - laser) / total if total > 0 else 0.0


def with_bridged(sigma: float, checks: list[StepCheck], scales_mm: list[float]) -> float:
    """The run's relative 1-sigma ``sigma`` (of its measured steps; NaN: none stated)
    with its bridged steps' (odometry, gait: :attr:`StepCheck.bridged_sigma_mm`) over the
    whole run's length: their sigmas add linearly (an odometry's slip, a gait's pace is
    one bias over the run), the measured part's in quadrature with them. A run of
    bridged steps only (a plain wall with odometry) states its bridges' sigma, not the
    analysis' assumed fallback. NaN when neither is known."""
    bridged = [(c.bridged_mm, c.bridged_sigma_mm) for c in checks if c.bridged_from]
    bridged = [(b, s) for b, s in bridged if math.isfinite(b) and b > 0 and math.isfinite(s)]
    if not bridged:
        return sigma
    measured = sum(
        float(scales_mm[k]) for k, c in enumerate(checks)
        if not c.bridged_from and k < len(scales_mm) and math.isfinite(scales_mm[k]) and scales_mm[k] > 0
    )
    if measured > 0 and not math.isfinite(sigma):
        return sigma
    length_b, sigma_b = sum(b for b, _ in bridged), sum(s for _, s in bridged)
    part = sigma * measured if measured > 0 else 0.0
    return math.hypot(part, sigma_b) / (measured + length_b)


def _scale_sigma_rel(anchors: list[Anchor], scales_mm: list[float]) -> float:
    """Relative 1-sigma of lengths along the run from the spread of the anchors' per-point
    lengths (``anchor.log_lengths``; the step's length ``scales_mm[anchor.a]``).

    Each step's length is the median of its points' log lengths: sigma_k from their
    robust spread over sqrt(n); independent steps add in quadrature.
    """
    var, total = 0.0, 0.0
    for anchor in anchors:
        length, logs = scales_mm[anchor.a], anchor.log_lengths
        if len(logs) < 3 or length <= 0:
            continue
        _, sig = median_with_sigma(logs)
        var += (length * sig) ** 2
        total += length
    return math.sqrt(var) / total if total > 0 else math.nan
