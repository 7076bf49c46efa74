"""The robot's own sensors in camera motion (contract section 1: odometry.txt, imu.txt).

- Bridged steps: a keyframe step whose length vision could not measure (no relative
  motion, sources that contradict each other) gets an estimate, never a zero: the
  odometry's length of the step scaled by the run-wide odometry/vision ratio
  (:func:`odometry_steps`, :func:`calibrate_odometry`), else the gait (the median of
  the trusted steps), each with an honest 1-sigma; the step stays flagged.
- Contradiction: a trusted vision length further than :data:`CONTRADICT_SIGMAS` from
  the calibrated odometry is no longer trusted (:func:`odometry_contradicts`): both
  vision sources can take the same wrong course of a periodic wall. The step is
  flagged and bridged from the odometry.
- Weights: the odometry never replaces a trusted vision length it agrees with. Its
  per-step sigma (:func:`odometry_steps`) is the stated sigma split into slip, random
  walk and resolution (:func:`stated_error_model`) with the readings' interpolation
  around each keyframe's time (its lag at stops, :func:`odometry_noise`); calibrated
  on the trusted vision steps, the slip is replaced by the run-wide ratio's own
  uncertainty and the rest inflated by what the trusted steps' residuals show
  (:func:`calibrate_odometry`).
- Disagreement: the run-wide ratio and the trusted steps further than
  :data:`AGREE_SIGMAS` sigma from the odometry are reported as warnings
  (:func:`odometry_disagreement`).
- Gravity: the IMU's gravity direction (rig frame, :func:`omnipipe.inputs.sensors.gravity_at`)
  turned into the world frame by each registered frame's rotation and averaged
  (:func:`gravity_world`), over the frames linked to frame 0 by trusted steps only
  (:func:`rotation_linked`): the world is frame 0's rig frame, and an untrusted step's
  rotation may be wrong by degrees.

Conventions: lengths in mm, angles in radians; rig z is the direction of travel.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, replace

import numpy as np
from scipy.optimize import nnls

from omnipipe.inputs.sensors import DEFAULT_SIGMA_REL, Imu, Odometry, gravity_at, odometry_at

# A trusted step further than this many sigma from the calibrated odometry is reported.
AGREE_SIGMAS = 3.0
# Fewest trusted steps for a run-wide odometry/vision ratio.
MIN_CALIBRATION_STEPS = 5
# Relative 1-sigma floor of a gait-bridged length (the robot's strokes vary).
GAIT_SIGMA_FLOOR_REL = 0.15
# ... of one bridged by the pace (a step's share of a stroke varies, see gait_estimate).
GAIT_PACE_SIGMA_FLOOR_REL = 0.25


# Least travel (mm) by which the odometry alone makes a frame a moving one (where the
# images could not tell: a plain wall); also at least 3 of its resolution sigmas.
MOVED_MIN_MM = 1.0


def odometry_moved(odometry: Odometry, timestamps: np.ndarray) -> np.ndarray:
    """(N,) True for the frames (times ``timestamps``, s) by which the odometry counted
    more than :data:`MOVED_MIN_MM` (and 3 sqrt(2) resolution sigmas) since the last
    such frame; frame 0 and frames outside its span False."""
    d, _ = odometry_at(odometry, np.asarray(timestamps, float))
    threshold = max(MOVED_MIN_MM, 3 * math.sqrt(2) * float(np.min(odometry.sigma_mm)))
    out = np.zeros(len(d), bool)
    ref = d[0] if len(d) else math.nan
    for i in range(1, len(d)):
        if not math.isfinite(ref):
            ref = d[i]
        elif math.isfinite(d[i]) and d[i] - ref > threshold:
            out[i] = True
            ref = d[i]
    return out


# A frame taken for standing (by the images and by MOVED_MIN_MM) whose odometry counted
# more than this (mm) and CREEP_SIGMAS of its noise (:func:`odometry_noise`: walk,
# resolution, the interpolation around both frames' times, i.e. its lag at stops) since
# its station's first frame may have crept: its step is flagged. Over the 40
# random-wide renders this finds 129 of the 134 creeps under 1 mm and marks 1 of 258
# truly standing frames (still7's offline count); seed 3s (joints, 757 mm: the robot
# never stands, 0.5 mm creeps a fraction of a pixel) had 6 silent-strict steps there.
CREEP_MIN_MM = 0.25
CREEP_SIGMAS = 3.0


def odometry_creeps(odometry: Odometry, timestamps: np.ndarray, moved: np.ndarray) -> list[tuple[int, int, float]]:
    """(first, last, travel mm) of every station (``moved`` (N,): True where one starts)
    one of whose stationary frames the odometry counted beyond :data:`CREEP_MIN_MM` and
    :data:`CREEP_SIGMAS` of its noise from the station's first frame: from that frame
    to the next moving frame (or the run's last frame). Its frames share the station's
    pose; a creep lands in the step after it."""
    t = np.asarray(timestamps, float)
    m = np.asarray(moved, bool)
    d, _ = odometry_at(odometry, t)
    _, walk, floor = stated_error_model(odometry)
    starts = np.flatnonzero(m)
    if len(starts) == 0 or starts[0] != 0:
        starts = np.concatenate([[0], starts[starts > 0]])
    out = []
    for j, f in enumerate(starts):
        end = int(starts[j + 1]) if j + 1 < len(starts) else len(m) - 1
        worst = 0.0
        for i in range(f + 1, end + (j + 1 == len(starts))):
            if not (math.isfinite(d[i]) and math.isfinite(d[f])):
                continue
            noise = float(odometry_noise(odometry, t[[f, i]], walk, floor)[0])
            travel = abs(float(d[i] - d[f]))
            if travel > max(CREEP_MIN_MM, CREEP_SIGMAS * noise):
                worst = max(worst, travel)
        if worst > 0:
            out.append((int(f), end, worst))
    return out


@dataclass(frozen=True)
class OdometrySteps:
    """The odometry's length of every keyframe step.

    Attributes:
        length_mm: (K-1,) travel between consecutive keyframes (mm; NaN: not covered).
        sigma_mm: (K-1,) its 1-sigma before calibration against vision (mm; inf: none):
            the stated slip times the step (+) ``noise_mm``.
        floor_mm: the readings' smallest stated sigma (resolution, mm).
        ratio_log: log(vision / odometry) over the trusted steps (0: not calibrated).
        spread_log: per-step 1-sigma of that log ratio (NaN: not calibrated).
        noise_mm: (K-1,) the part of each step's 1-sigma a run-wide ratio does not remove
            (mm): the count's random walk over the step, the resolution at both ends and
            the interpolation between the readings around each keyframe's time
            (:func:`odometry_noise`); None: ``sigma_mm`` alone.
        ratio_sigma_log: 1-sigma of the calibrated ``ratio_log`` itself.
        inflation: factor (>= 1) by which the trusted steps' residuals to the calibrated
            odometry exceed ``noise_mm`` (the data's own word on the stated noise).
    """

    length_mm: np.ndarray
    sigma_mm: np.ndarray
    floor_mm: float
    ratio_log: float = 0.0
    spread_log: float = math.nan
    noise_mm: np.ndarray | None = None
    ratio_sigma_log: float = 0.0
    inflation: float = 1.0

    @property
    def calibrated(self) -> bool:
        return math.isfinite(self.spread_log)

    def estimate(self, k: int) -> tuple[float, float]:
        """Step k's length (mm) and 1-sigma (mm) in the run's units (NaN, inf: none).

        Calibrated: the step times the run-wide ratio, 1-sigma the ratio's own
        uncertainty times the length (+) the step's noise times the inflation, at
        least the spread of the trusted steps' ratios times the length when the noise
        is not known."""
        d = float(self.length_mm[k])
        if not math.isfinite(d):
            return math.nan, math.inf
        if not self.calibrated:
            return d, float(self.sigma_mm[k])
        length = d * math.exp(self.ratio_log)
        if self.noise_mm is None:
            return length, math.hypot(abs(length) * self.spread_log, math.sqrt(2) * self.floor_mm)
        noise = self.inflation * float(self.noise_mm[k]) * math.exp(self.ratio_log)
        return length, math.hypot(abs(length) * self.ratio_sigma_log, noise)


def stated_error_model(odometry: Odometry) -> tuple[float, float, float]:
    """The stated sigmas split as sigma^2 = (rel d)^2 + walk^2 |d| + floor^2 over the
    readings (non-negative least squares): the relative part (slip, a run-wide bias),
    the random walk's mm^2 per mm travelled and the resolution (mm), each >= 0.

    A source that states a sigma proportional to the travel gets walk 0; one without
    enough distinct readings its relative part at the median and floor at the minimum."""
    d = np.abs(np.asarray(odometry.distance_mm, float))
    s2 = np.asarray(odometry.sigma_mm, float) ** 2
    floor = float(np.min(odometry.sigma_mm))
    if len(np.unique(np.round(d, 6))) < 3:
        far = d > 20 * floor
        rel = float(np.median(np.sqrt(s2[far]) / d[far])) if far.sum() >= 3 else DEFAULT_SIGMA_REL
        return rel, 0.0, floor
    design = np.stack([d**2, d, np.ones_like(d)], axis=1)
    scale = np.maximum(s2, 1e-12)  # relative residuals: every reading counts alike
    coef, _ = nnls(design / scale[:, None], s2 / scale)
    return math.sqrt(coef[0]), float(coef[1]), max(math.sqrt(coef[2]), 1e-6)


def odometry_noise(odometry: Odometry, times_s: np.ndarray, walk_mm2_per_mm: float, floor_mm: float) -> np.ndarray:
    """(M-1,) 1-sigma (mm) of the odometry's travel between consecutive ``times_s`` apart
    from its run-wide slip: the random walk over the travel, the resolution at both
    ends, and at each end the linear interpolation between the readings around it,
    2 sqrt(f (1 - f)) x their increment / sqrt(12) (f: the time's fraction of their
    interval; 0 on a reading). The interpolation term is the odometry's lag at stops:
    a robot that stops at a frame was still moving during the reading interval around
    it (random-wide, 40 seeds: standing frames read up to 0.58 mm of travel)."""
    t = np.asarray(times_s, float)
    ts, dist = odometry.timestamps, odometry.distance_mm
    j = np.clip(np.searchsorted(ts, t, side="right") - 1, 0, max(len(ts) - 2, 0))
    if len(ts) >= 2:
        f = np.clip((t - ts[j]) / (ts[j + 1] - ts[j]), 0.0, 1.0)
        inc = np.abs(dist[j + 1] - dist[j])
        interp = 2.0 * np.sqrt(f * (1.0 - f)) * inc / math.sqrt(12.0)
    else:
        interp = np.zeros(len(t))
    d, _ = odometry_at(odometry, t)
    travel = np.abs(np.diff(d))
    return np.sqrt(walk_mm2_per_mm * travel + 2.0 * floor_mm**2 + interp[:-1] ** 2 + interp[1:] ** 2)


def odometry_steps(odometry: Odometry, timestamps: np.ndarray, frames: list[int]) -> OdometrySteps:
    """The odometry's travel between consecutive keyframes ``frames`` (frame indices into
    ``timestamps``, seconds), 1-sigma the stated relative part (slip) times the step
    (+) the step's noise (:func:`stated_error_model`, :func:`odometry_noise`).

    The relative part alone (the former model) left 25 % of the random-wide seeds'
    frame steps beyond 2 sigma of the truth (max 14 sigma, standing frames next to a
    stop); with the walk and the interpolation 0.2 % of 40 seeds' 1240 (none beyond
    3), of their 1000 2- and 3-frame steps 1.8 % (none beyond 3)."""
    times = np.asarray(timestamps, float)[frames]
    d, _ = odometry_at(odometry, times)
    rel, walk, floor = stated_error_model(odometry)
    length = np.diff(d)
    noise = odometry_noise(odometry, times, walk, floor)
    sigma = np.hypot(rel * np.abs(length), noise)
    sigma[~np.isfinite(length)] = np.inf
    return OdometrySteps(length, sigma, float(np.min(odometry.sigma_mm)), noise_mm=noise)


def calibrate_odometry(odo: OdometrySteps, lengths: np.ndarray, trusted: np.ndarray) -> OdometrySteps:
    """``odo`` with its run-wide ratio to the trusted vision ``lengths`` (K-1,) mm (the
    slip is a run-wide bias) and the per-step spread of that ratio (1.4826 MAD), both
    over the steps of the ratios' :func:`consensus` (within 3 stated relative sigmas),
    or unchanged with fewer than :data:`MIN_CALIBRATION_STEPS` usable steps.

    With the steps' noise known (:func:`odometry_steps`), the data's word on it: the
    inflation is the robust RMS (1.4826 MAD) of the residuals over their noise, at
    least 1, over every usable step that is no wrong course (the
    :func:`odometry_contradicts` rule; the consensus alone would keep only the steps
    that agree); vision's own noise is in it too, which errs on the safe side. The
    ratio is then the consensus steps' weighted mean (weights 1 / their inflated log
    noise^2: a 0.5 mm step's log ratio is mostly walk; the consensus half-width times
    the inflation), its 1-sigma that mean's, at least :data:`RATIO_SIGMA_FLOOR_LOG`."""
    v = np.asarray(lengths, float)
    use = trusted & np.isfinite(v) & (v > 0) & np.isfinite(odo.length_mm) & (odo.length_mm > 4 * odo.floor_mm)
    if use.sum() < MIN_CALIBRATION_STEPS:
        return odo
    logs = np.log(v[use] / odo.length_mm[use])
    tol = max(3 * float(np.median(odo.sigma_mm[use] / odo.length_mm[use])), CONSENSUS_MIN_LOG)
    r = consensus(logs, tol)
    if len(r) < MIN_CALIBRATION_STEPS:
        return odo
    mid = float(np.median(r))
    spread = max(1.4826 * float(np.median(np.abs(r - mid))), 0.01)
    if odo.noise_mm is None:
        return replace(odo, ratio_log=mid, spread_log=spread)
    idx = np.flatnonzero(use)
    length, noise = odo.length_mm[idx], odo.noise_mm[idx]
    gap = np.abs(v[idx] - length * math.exp(mid))
    course = (gap > np.maximum(CONTRADICT_SIGMAS * odo.sigma_mm[idx] * math.exp(mid), CONTRADICT_MIN_MM)) & (
        np.abs(logs - mid) > CONTRADICT_MIN_LOG
    )
    z = gap[~course] / np.maximum(noise[~course] * math.exp(mid), 1e-9)
    inflation = max(1.0, 1.4826 * float(np.median(z)))
    near = np.abs(logs - mid) <= tol * inflation
    w = (length[near] / (inflation * noise[near])) ** 2
    mid = float((w * logs[near]).sum() / w.sum())
    ratio_sigma = max(1.0 / math.sqrt(float(w.sum())), RATIO_SIGMA_FLOOR_LOG)
    return replace(
        odo, ratio_log=mid, spread_log=spread, ratio_sigma_log=ratio_sigma, inflation=inflation
    )


# Least 1-sigma of the calibrated odometry/vision ratio (log): vision's own scale
# has this much bias left (the run's scale error, bench_robustness median ~0.6 %).
RATIO_SIGMA_FLOOR_LOG = 0.005


# Smallest half-width (log) of the odometry/vision ratio's consensus.
CONSENSUS_MIN_LOG = 0.05


def consensus(log_ratios: np.ndarray, tol_log: float) -> np.ndarray:
    """The largest subset of (N,) log ratios within ``tol_log`` of one of them (ties:
    the one nearest 0, an unbiased odometry).

    The median alone is not robust enough: on a periodic wall half the trusted steps
    may share one wrong course (random-wide seed 22: 5 of 10 steps a course or more
    short, median ratio 1.44, the true one 1.00)."""
    r = np.asarray(log_ratios, float)
    best, best_key = r, (-1, math.inf)
    for x in r:
        inl = r[np.abs(r - x) <= tol_log]
        key = (-len(inl), abs(float(np.median(inl))))
        if key < best_key:
            best, best_key = inl, key
    return best


def gait_estimate(
    k: int, lengths: np.ndarray, trusted: np.ndarray, counts: np.ndarray | None = None
) -> tuple[float, float]:
    """Step k's length from the gait, and its 1-sigma (mm). (NaN, inf) with fewer than 3
    trusted moving steps in the run.

    With ``counts`` ((K-1,) moving frames per step, :func:`omnipipe.sfm.step_window.moving_counts`):
    the median pace (mm per moving frame) of the run's trusted steps times the step's
    moving frames; 1-sigma the paces' relative spread (1.4826 MAD), at least
    :data:`GAIT_PACE_SIGMA_FLOOR_REL`: a keyframe step may cover a stroke's fast middle
    or its slow ends (random-wide seed 21: a 2-frame step of a 3-frame stroke is 0.75 of
    it, a trusted one 0.5). Without: the median of the trusted steps, 1-sigma their
    spread, at least :data:`GAIT_SIGMA_FLOOR_REL`.

    The run's median, not the nearest steps': on bench_robustness seed 5 (random-wide,
    48 frames, 640x480) the nearest steps' median put 9 lost steps 2-6 mm long (ATE
    3.5 -> 8.7 mm). The median length alone put seed 21's (32 frames) five lost 29-35 mm
    steps at 18.6 +- 2.8 mm; by pace at 20.4 or 30.6 +- 25 %."""
    v = np.asarray(lengths, float)
    ok = np.flatnonzero(trusted & np.isfinite(v) & (v > 0))
    if len(ok) < 3:
        return math.nan, math.inf
    if counts is not None:
        pace = v[ok] / np.asarray(counts, float)[ok]
        mid = float(np.median(pace))
        rel = 1.4826 * float(np.median(np.abs(pace - mid))) / mid
        est = mid * float(counts[k])
        return est, est * max(rel, GAIT_PACE_SIGMA_FLOOR_REL)
    est = float(np.median(v[ok]))
    spread = 1.4826 * float(np.median(np.abs(v[ok] - est)))
    return est, max(spread, GAIT_SIGMA_FLOOR_REL * est)


def bridge_estimate(
    k: int,
    lengths: np.ndarray,
    trusted: np.ndarray,
    odo: OdometrySteps | None,
    counts: np.ndarray | None = None,
) -> tuple[float, float, str]:
    """Step k's length (mm), 1-sigma (mm) and source (``"odometry"``, ``"gait"``, or
    ``""`` with NaN, inf when neither can tell) for a step vision could not measure
    (``counts``: moving frames per step, for the gait's pace)."""
    if odo is not None:
        length, sigma = odo.estimate(k)
        if math.isfinite(length) and math.isfinite(sigma):
            return max(length, 0.0), sigma, "odometry"
    length, sigma = gait_estimate(k, lengths, trusted, counts)
    if math.isfinite(length):
        return length, sigma, "gait"
    return math.nan, math.inf, ""


# A trusted vision step further than this many sigma (the odometry's stated sigma or
# its calibrated spread, whichever is larger), :data:`CONTRADICT_MIN_MM` and
# :data:`CONTRADICT_MIN_LOG` from the calibrated odometry is not trusted: on a periodic wall both vision sources can take
# the same wrong course (random-wide seed 22, mosaic tiles 7.7 mm apart at 8.4 mm per
# frame: laser and feature depths agreed on 10.1 mm for a 33.2 mm step).
# ... and by more than this part of the step (|log|): a course is a large part of a
# step, the odometry's own excursions are not (seed 4, brick: 9.4 +- 0.3 mm against
# vision's right 7.9 mm, truth 8.5: 5 sigma but 17 %).
CONTRADICT_SIGMAS = 4.0
CONTRADICT_MIN_MM = 1.0
CONTRADICT_MIN_LOG = 0.25


# A step whose relative motion rests on fewer than scale_check.TRACKED_MIN_MATCHES
# feature matches (a plain wall) is "weak": the odometry contradicts it beyond this many
# sigma and WEAK_CONTRADICT_MIN_MM, whatever the part of the step. Random-wide seed 25s
# (smooth, 218 mm): step 16->23 trusted at 9.4 mm (laser peak chosen by the feature
# depths of 21 matches) for 10.3 true, the odometry 10.8 +- 0.5 mm (2.8 sigma); the
# frames resected inside it were 37-60 % off (3 strict steps). Bridged, they follow
# the travel.
WEAK_CONTRADICT_SIGMAS = 2.0
WEAK_CONTRADICT_MIN_MM = 0.5


def odometry_contradicts(odo: OdometrySteps, k: int, length_mm: float, weak: bool = False) -> str:
    """Why the calibrated odometry contradicts vision's ``length_mm`` for step k ("" when
    it does not, or cannot tell): beyond :data:`CONTRADICT_SIGMAS`,
    :data:`CONTRADICT_MIN_MM` and :data:`CONTRADICT_MIN_LOG` (a wrong course), or for a
    ``weak`` step (few feature matches) beyond :data:`WEAK_CONTRADICT_SIGMAS` and
    :data:`WEAK_CONTRADICT_MIN_MM`."""
    est, sig = odo.estimate(k)
    stated = float(odo.sigma_mm[k]) if k < len(odo.sigma_mm) else math.inf
    if not (math.isfinite(est) and math.isfinite(stated) and math.isfinite(length_mm)):
        return ""
    sigma = max(sig, stated)
    gap = abs(length_mm - est)
    if weak and gap > max(WEAK_CONTRADICT_SIGMAS * sigma, WEAK_CONTRADICT_MIN_MM):
        return (
            f"vision's {length_mm:.1f} mm (few feature matches) contradicts the odometry's "
            f"{est:.1f} +- {sigma:.1f} mm ({gap / sigma:.1f} sigma)"
        )
    if gap <= max(CONTRADICT_SIGMAS * sigma, CONTRADICT_MIN_MM) or not (
        length_mm > 0 and est > 0 and abs(math.log(length_mm / est)) > CONTRADICT_MIN_LOG
    ):
        return ""
    return (
        f"vision's {length_mm:.1f} mm contradicts the odometry's {est:.1f} +- {sigma:.1f} mm "
        f"({gap / sigma:.0f} sigma): a wrong course of a periodic wall"
    )


def odometry_disagreement(
    odo: OdometrySteps, lengths: np.ndarray, trusted: np.ndarray, frames: list[int]
) -> list[str]:
    """Warnings where the odometry and the trusted vision ``lengths`` (K-1,) disagree:
    the run-wide ratio beyond the stated slip, and each trusted step beyond
    :data:`AGREE_SIGMAS` sigma of the calibrated odometry. Uncalibrated (too few trusted
    steps) the ratio over the trusted steps is still said, against the odometry's stated
    sigma (:func:`uncalibrated_disagreement`)."""
    if not odo.calibrated:
        return uncalibrated_disagreement(odo, lengths, trusted)
    out = [
        f"odometry/vision length ratio {math.exp(-odo.ratio_log):.4f} over the trusted steps "
        f"(per-step spread {100 * odo.spread_log:.1f} %)"
    ]
    fin = np.isfinite(odo.sigma_mm) & (np.abs(odo.length_mm) > 4 * odo.floor_mm)
    rel = float(np.median(odo.sigma_mm[fin] / np.abs(odo.length_mm[fin]))) if fin.any() else 0.03
    if abs(odo.ratio_log) > AGREE_SIGMAS * max(rel, 0.01):
        out.append(
            f"odometry runs {100 * (math.exp(-odo.ratio_log) - 1):+.1f} % off vision over the run, "
            f"more than its stated slip ({100 * rel:.1f} %)"
        )
    off = []
    for k in np.flatnonzero(trusted):
        est, sig = odo.estimate(int(k))
        if math.isfinite(est) and abs(lengths[k] - est) > AGREE_SIGMAS * sig:
            off.append(f"{frames[k]}->{frames[k + 1]} ({lengths[k]:.1f} vs {est:.1f} mm)")
    if off:
        out.append(
            f"odometry disagrees with vision beyond {AGREE_SIGMAS:g} sigma at {len(off)} steps: "
            + ", ".join(off[:5])
            + (" ..." if len(off) > 5 else "")
        )
    return out


def uncalibrated_disagreement(odo: OdometrySteps, lengths: np.ndarray, trusted: np.ndarray) -> list[str]:
    """The odometry/vision length ratio over the trusted steps of a run too short to
    calibrate the odometry (fewer than :data:`MIN_CALIBRATION_STEPS`), against the
    odometry's stated relative sigma over them (the steps' stated sigmas added: a slip
    is one bias over the run); a second line when beyond :data:`AGREE_SIGMAS` of it.
    Nothing decides on it: vision's steps keep their lengths."""
    v = np.asarray(lengths, float)
    use = (
        np.asarray(trusted, bool) & np.isfinite(v) & (v > 0) & np.isfinite(odo.length_mm)
        & (odo.length_mm > 4 * odo.floor_mm) & np.isfinite(odo.sigma_mm)
    )
    if not use.any():
        return []
    total, vision = float(odo.length_mm[use].sum()), float(v[use].sum())
    rel = float(odo.sigma_mm[use].sum()) / total
    ratio = total / vision
    out = [
        f"odometry/vision length ratio {ratio:.4f} over {int(use.sum())} trusted steps (too few "
        f"to calibrate the odometry; its stated sigma over them {100 * rel:.1f} %)"
    ]
    if abs(math.log(ratio)) > AGREE_SIGMAS * rel:
        out.append(
            f"odometry runs {100 * (ratio - 1):+.1f} % off vision over the trusted steps, more than "
            f"{AGREE_SIGMAS:g} times its stated sigma ({100 * rel:.1f} %)"
        )
    return out


def rotation_linked(station: np.ndarray, untrusted_from: list[int]) -> np.ndarray:
    """(N,) True for the frames whose rotation reaches frame 0 through trusted steps only:
    the stations up to the one of the first frame where an untrusted stretch begins
    (``untrusted_from``: the first frames of the untrusted keyframe steps and of the
    frames that could not be resected; empty: every frame).

    A step vision could not measure keeps its keyframe's rotation (the rig's roll in
    between is lost), and one measured from a few matches can turn by degrees
    (random-wide seed 31 with sensors: a 1-frame step from 18 matches turned the
    gravity of every later frame 4-5 degrees around the axis; the run's mean was off
    1.6 degrees, frame 0's alone 0.2)."""
    station = np.asarray(station)
    if not untrusted_from:
        return np.ones(len(station), bool)
    return station <= station[min(untrusted_from)]


# Rotation drift (rad, 1 sigma) a keyframe step adds to a frame's rotation from frame 0
# in the gravity average (:func:`gravity_world`): random-wide seed 31 (108 mm, 6-9 mm
# frame steps, every step trusted) had two steps whose roll was about 1 degree off;
# averaged alike over every frame, the clock was 1.1 degrees off, frame 0's own 0.2.
ROTATION_STEP_SIGMA_RAD = math.radians(0.5)


def gravity_world(
    imu: Imu,
    timestamps: np.ndarray,
    world_from_rig: np.ndarray,
    registered: np.ndarray,
    steps_from_first: np.ndarray | None = None,
) -> tuple[np.ndarray, float] | None:
    """The gravity direction in the world frame: each registered frame's gravity in its
    rig (accelerometer averaged around its time) turned by its rotation, averaged with
    weights 1 / (its sigma^2 + (k x :data:`ROTATION_STEP_SIGMA_RAD`)^2), k its keyframe
    steps from frame 0 (``steps_from_first``; None: 0 for all): the world is frame 0's
    rig frame, and every step a frame's rotation is chained through may have turned it.

    Args:
        imu: the readings.
        timestamps: (N,) frame times, s.
        world_from_rig: (N, 4, 4) poses.
        registered: (N,) frames whose pose is valid.
        steps_from_first: (N,) keyframe steps between frame 0 and each frame.

    Returns:
        (unit (3,) vector pointing down in the world frame, 1-sigma angle in radians:
        the frames' typical sigma (bias and scatter, common to all) (+) the weighted
        scatter of their world directions over sqrt(effective count)), or None when no
        frame has one.
    """
    idx = np.flatnonzero(registered)
    if len(idx) == 0:
        return None
    g_rig, sig = gravity_at(imu, np.asarray(timestamps, float)[idx])
    ok = np.isfinite(sig)
    if not ok.any():
        return None
    g = np.einsum("nij,nj->ni", world_from_rig[idx[ok], :3, :3], g_rig[ok])
    k = np.zeros(len(g)) if steps_from_first is None else np.asarray(steps_from_first, float)[idx[ok]]
    w = 1.0 / (sig[ok] ** 2 + (k * ROTATION_STEP_SIGMA_RAD) ** 2)
    mean = (w[:, None] * g).sum(axis=0)
    mean /= np.linalg.norm(mean)
    ang = np.arccos(np.clip(g @ mean, -1.0, 1.0))
    n_eff = float(w.sum() ** 2 / (w**2).sum())
    scatter = math.sqrt(float((w * ang**2).sum() / w.sum()) / n_eff)
    return mean, math.hypot(float(np.median(sig[ok])), scatter)
