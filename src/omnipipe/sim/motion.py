"""Peristaltic (earthworm) locomotion of the robot's head, which carries the rangefinder.

Paper Sec. II: a longitudinal contraction wave runs from the anterior unit to the
rear. A unit moves forward only while it extends; while it is contracted it is
anchored against the wall. The front unit therefore advances by one stroke during
its own extension phase (1 / n_units of the gait cycle, with a smooth velocity
profile) and stands still while the wave travels through the other units. The
head's small lateral offset, tilt and roll change only while it moves: an anchored
unit cannot drift, so stationary frames have exactly the same pose.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from scipy.spatial.transform import Rotation

from omnipipe.errors import ConfigError
from omnipipe.geometry import make_transform
from omnipipe.sim.scene import Pipe


@dataclass(frozen=True)
class MotionConfig:
    """Earthworm gait and the head's pose disturbances.

    Attributes:
        n_units: number of peristaltic units (paper: 4).
        stroke_mm: head advance per gait cycle (mm).
        frames_per_cycle: camera frames per gait cycle.
        start_mm: centreline arc length of the rig origin at frame 0 (mm).
        lateral_mm: amplitude of the head's lateral offset from the centreline (mm).
        tilt_deg: amplitude of the head's pitch/yaw against the pipe axis (deg).
        roll_drift_deg_per_m: slow roll drift as the robot twists along (deg per m).
        roll_wobble_deg: amplitude of roll wobble (deg).
        speed_jitter: relative random variation of each stroke (0.1 = +-10 %).
        moving_frames: None: the front unit moves during 1 / n_units of each cycle
            (the paper's gait, frames_per_cycle / n_units moving frames). Otherwise a
            free rhythm: each stroke takes ``moving_frames`` frames and is followed by
            ``frames_per_cycle - moving_frames`` frames at rest (>= 1), each stop's rest
            varying by up to ``rest_jitter_frames`` frames (at least 1 frame at rest).
        rest_jitter_frames: per-stop variation of the rest (frames, free rhythm only).
        min_rest_frames: fewest frames at rest after a stroke (free rhythm only; 0 lets
            strokes follow each other without a stop, a continuously crawling robot).
    """

    n_units: int = 4
    stroke_mm: float = 24.0
    frames_per_cycle: int = 8
    start_mm: float = 200.0
    lateral_mm: float = 2.0
    tilt_deg: float = 0.8
    roll_drift_deg_per_m: float = 6.0
    roll_wobble_deg: float = 0.6
    speed_jitter: float = 0.1
    moving_frames: int | None = None
    rest_jitter_frames: int = 0
    min_rest_frames: int = 1

    def __post_init__(self) -> None:
        if self.n_units < 1:
            raise ConfigError("motion.n_units", f"must be >= 1, got {self.n_units}")
        if self.frames_per_cycle < 1:
            raise ConfigError(
                "motion.frames_per_cycle", f"must be >= 1, got {self.frames_per_cycle}"
            )
        if self.stroke_mm < 0:
            raise ConfigError("motion.stroke_mm", f"must be >= 0, got {self.stroke_mm}")
        if self.min_rest_frames < 0:
            raise ConfigError(
                "motion.min_rest_frames", f"must be >= 0, got {self.min_rest_frames}"
            )
        top = self.frames_per_cycle - self.min_rest_frames
        if self.moving_frames is not None and not 1 <= self.moving_frames <= top:
            raise ConfigError(
                "motion.moving_frames",
                f"must be in [1, frames_per_cycle - min_rest_frames = {top}], "
                f"got {self.moving_frames}",
            )
        if self.rest_jitter_frames < 0:
            raise ConfigError(
                "motion.rest_jitter_frames", f"must be >= 0, got {self.rest_jitter_frames}"
            )


def head_travel(
    config: MotionConfig, n_frames: int, rng: np.random.Generator
) -> tuple[np.ndarray, np.ndarray]:
    """Head advance along the centreline for each frame.

    Returns:
        travel_mm: (n_frames,) distance travelled since frame 0 (mm), non-decreasing.
        moving: (n_frames,) True where the head moved since the previous frame.
    """
    if config.moving_frames is not None:
        return _free_rhythm_travel(config, n_frames, rng)
    fpc = config.frames_per_cycle
    n_cycles = n_frames // fpc + 2
    strokes = config.stroke_mm * (1.0 + config.speed_jitter * rng.uniform(-1, 1, n_cycles))
    # Gait phase of frame i in [0, 1); the front unit extends during the first 1/n_units.
    phase = (np.arange(n_frames) % fpc) / fpc
    cycle = np.arange(n_frames) // fpc
    active = 1.0 / config.n_units
    tau = np.clip(phase / active, 0.0, 1.0)
    within = 0.5 * (1.0 - np.cos(np.pi * tau))  # smooth start and stop
    done = np.concatenate([[0.0], np.cumsum(strokes)])
    travel = done[cycle] + strokes[cycle] * within
    moving = np.concatenate([[False], np.diff(travel) > 1e-9])
    return travel, moving


def _free_rhythm_travel(
    config: MotionConfig, n_frames: int, rng: np.random.Generator
) -> tuple[np.ndarray, np.ndarray]:
    """Head travel of the free rhythm: frame 0 at rest, then per stroke ``moving_frames``
    moving frames (smooth velocity) and a rest of its own length (see MotionConfig)."""
    m = int(config.moving_frames)  # type: ignore[arg-type]
    rest0 = config.frames_per_cycle - m
    min_rest = config.min_rest_frames
    # Enough strokes even with the shortest rests.
    n_cycles = n_frames // (m + 1) + 2 if min_rest >= 1 else n_frames // m + 2
    strokes = config.stroke_mm * (1.0 + config.speed_jitter * rng.uniform(-1, 1, n_cycles))
    jit = config.rest_jitter_frames
    rests = rest0 + (rng.integers(-jit, jit + 1, n_cycles) if jit else np.zeros(n_cycles, int))
    rests = np.maximum(rests, min_rest)
    within = 0.5 * (1.0 - np.cos(np.pi * np.arange(1, m + 1) / m))  # smooth start and stop
    travel = [0.0]
    done = 0.0
    for stroke, rest in zip(strokes, rests, strict=True):
        if len(travel) >= n_frames:
            break
        travel.extend(done + stroke * within)
        done += stroke
        travel.extend([done] * int(rest))
    out = np.array(travel[:n_frames])
    moving = np.concatenate([[False], np.diff(out) > 1e-9])
    return out, moving


def _smooth_profile(
    s: np.ndarray, rng: np.random.Generator, amplitude: float, n_terms: int = 4
) -> np.ndarray:
    """Sum of random sinusoids in travel distance s (wavelengths 150..800 mm)."""
    out = np.zeros_like(s)
    for _ in range(n_terms):
        wavelength = rng.uniform(150.0, 800.0)
        out += np.sin(2 * math.pi * s / wavelength + rng.uniform(0, 2 * math.pi))
    return amplitude * out / math.sqrt(n_terms / 2.0)


def simulate_trajectory(
    pipe: Pipe, config: MotionConfig, n_frames: int, seed: int
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """True rig poses of an earthworm-robot run along ``pipe``.

    Returns:
        world_from_rig: (n_frames, 4, 4) poses (mm); rig z along the direction of travel.
        sigma_mm: (n_frames,) centreline arc length of each rig origin's station.
        moving: (n_frames,) True where the rig moved since the previous frame.
    """
    if n_frames < 1:
        raise ConfigError("frames", f"must be >= 1, got {n_frames}")
    rng = np.random.default_rng(seed)
    travel, moving = head_travel(config, n_frames, rng)
    poses, sigma = _poses_at_travel(pipe, config, travel, rng)
    return poses, sigma, moving


def poses_at_travel(
    pipe: Pipe, config: MotionConfig, n_frames: int, seed: int, travel_mm: np.ndarray
) -> np.ndarray:
    """Rig poses (M, 4, 4) of the run of :func:`simulate_trajectory` at any head travel
    ``travel_mm`` (M,) (mm since frame 0): the same disturbances, between the frames too
    (the simulated IMU samples the run between frames with it)."""
    rng = np.random.default_rng(seed)
    head_travel(config, n_frames, rng)  # the same draws as simulate_trajectory
    poses, _ = _poses_at_travel(pipe, config, np.asarray(travel_mm, float), rng)
    return poses


def travel_at_times(
    frame_times_s: np.ndarray, travel_mm: np.ndarray, times_s: np.ndarray
) -> np.ndarray:
    """Head travel (mm) at any times (s), between frames by monotone cubic (PCHIP)
    interpolation of the frames' travel: at rest where two frames are at rest, never
    backwards; before the first and after the last frame the head stands still."""
    from scipy.interpolate import PchipInterpolator

    t = np.clip(np.asarray(times_s, float), frame_times_s[0], frame_times_s[-1])
    if len(frame_times_s) < 2:
        return np.full(t.shape, float(travel_mm[0]))
    return PchipInterpolator(frame_times_s, travel_mm)(t)


def _poses_at_travel(
    pipe: Pipe, config: MotionConfig, travel: np.ndarray, rng: np.random.Generator
) -> tuple[np.ndarray, np.ndarray]:
    """Poses (M, 4, 4) and stations sigma (M,) at head travel ``travel``; the lateral
    offset, tilt and roll disturbances drawn from ``rng``."""
    n_frames = len(travel)
    sigma = config.start_mm + travel
    # Disturbances are functions of the distance travelled, so they freeze when anchored.
    off_n = _smooth_profile(travel, rng, config.lateral_mm)
    off_b = _smooth_profile(travel, rng, config.lateral_mm)
    pitch = np.radians(_smooth_profile(travel, rng, config.tilt_deg))
    yaw = np.radians(_smooth_profile(travel, rng, config.tilt_deg))
    roll = np.radians(
        config.roll_drift_deg_per_m * travel / 1000.0
        + _smooth_profile(travel, rng, config.roll_wobble_deg)
    )
    centre, normal, binormal, tangent = pipe.frame_at(sigma)
    poses = np.empty((n_frames, 4, 4))
    for i in range(n_frames):
        pipe_frame = np.stack([normal[i], binormal[i], tangent[i]], axis=1)  # columns N, B, T
        wobble = Rotation.from_euler("xyz", [pitch[i], yaw[i], roll[i]]).as_matrix()
        origin = centre[i] + off_n[i] * normal[i] + off_b[i] * binormal[i]
        poses[i] = make_transform(pipe_frame @ wobble, origin)
    return poses, sigma
