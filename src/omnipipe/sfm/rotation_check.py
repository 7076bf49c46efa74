"""The camera motion's rotation checked against the IMU's gyro.

The gyro's body rates integrated over the run (:func:`gyro_rotations`)
turn the rig as the images do, but from other evidence: a bend's turn is in both, a
drift of the images' rotation (tracks lagging a broad-textured wall, a kink at a
lateral's rim) in the images' only. Between two frames the angle of the one relative
rotation against the other is the images' rotation error there, to within the gyro's
own drift (its bias over the time between them, :data:`GYRO_BIAS_SIGMA_RAD_S`); a bend's
turn measured on the centreline carries the part beyond that drift (:func:`omnipipe.pipeline.quality.flag_features`).

Conventions: rotations rig_first_from_rig (the first checked frame's rig); angles rad;
times s.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from omnipipe.inputs.sensors import Imu

# 1-sigma of a gyro's bias over a run (rad/s, magnitude): the drift of its integrated
# rotation per second that the comparison cannot tell from the images' error. A MEMS
# gyro's in-run bias; the simulator draws 0.0005 rad/s per axis (0.0009 magnitude), and
# its integration stayed within 0.21-0.87 deg of the true rotation over random-features
# seeds 12, 25, 26, 30 (3-15 s).
GYRO_BIAS_SIGMA_RAD_S = 0.001
# 1-sigma floor of the gyro's rotation between two frames (rad): on those seeds' 3 s runs
# it still came within 0.11-0.32 deg of the truth (the frames' and readings' timing, the
# rig's start), more than their bias explains.
GYRO_FLOOR_RAD = 0.005
# The images' rotation departs from the gyro's by more than this many of its sigmas:
# a warning says where (random-features seeds: the departure tracked the images' true
# error within 0.6 deg on all 34, up to 14.8 deg on seed 26).
GYRO_GAP_SIGMAS = 3.0

# Largest gap (s) between a frame's time and the nearest gyro readings: outside them the
# rotation is not integrated.
MAX_GYRO_GAP_S = 0.5


def _rotvec_to_matrix(v: np.ndarray) -> np.ndarray:
    """Rodrigues: rotation matrix (3, 3) of a rotation vector (3,) (rad)."""
    theta = float(np.linalg.norm(v))
    if theta < 1e-12:
        return np.eye(3)
    k = v / theta
    kx = np.array([[0.0, -k[2], k[1]], [k[2], 0.0, -k[0]], [-k[1], k[0], 0.0]])
    return np.eye(3) + math.sin(theta) * kx + (1.0 - math.cos(theta)) * (kx @ kx)


def gyro_rotations(imu: Imu, timestamps: np.ndarray) -> np.ndarray | None:
    """(N, 3, 3) rig_first_from_rig of every frame: the gyro's body rates integrated
    (each reading interval one rotation of the intervals' mean rate; dR/dt = R [w]x with
    R = world_from_rig), at the frame times (the rate held over the part interval).

    Returns None without a gyro, or when a frame lies outside the readings by more than
    :data:`MAX_GYRO_GAP_S`.
    """
    if imu.gyro is None or len(imu) < 2:
        return None
    t = np.asarray(imu.timestamps, float)
    w = np.asarray(imu.gyro, float)
    ts = np.asarray(timestamps, float)
    if ts.min() < t[0] - MAX_GYRO_GAP_S or ts.max() > t[-1] + MAX_GYRO_GAP_S:
        return None
    rates = 0.5 * (w[1:] + w[:-1])
    cum = np.empty((len(t), 3, 3))
    cum[0] = np.eye(3)
    for k in range(len(t) - 1):
        cum[k + 1] = cum[k] @ _rotvec_to_matrix(rates[k] * (t[k + 1] - t[k]))
    k = np.clip(np.searchsorted(t, ts, side="right") - 1, 0, len(t) - 2)
    out = np.empty((len(ts), 3, 3))
    for i, (ki, ti) in enumerate(zip(k, ts, strict=True)):
        out[i] = cum[ki] @ _rotvec_to_matrix(rates[ki] * (ti - t[ki]))
    return np.transpose(out[0])[None] @ out


@dataclass(frozen=True)
class GyroCheck:
    """The images' rotation of every registered frame beside the gyro's.

    Attributes:
        frames: (M,) the registered frames checked, increasing.
        time_s: (M,) their timestamps (s).
        vision: (M, 3, 3) rig_first_from_rig from the camera motion.
        gyro: (M, 3, 3) rig_first_from_rig from the gyro.
    """

    frames: np.ndarray
    time_s: np.ndarray
    vision: np.ndarray
    gyro: np.ndarray

    def gap_rad(self) -> np.ndarray:
        """(M,) the angle between the images' and the gyro's rotation since the first
        frame (rad)."""
        rel = np.transpose(self.gyro, (0, 2, 1)) @ self.vision
        return np.arccos(np.clip((np.trace(rel, axis1=1, axis2=2) - 1.0) / 2.0, -1.0, 1.0))

    def between(self, frame_a: int, frame_b: int) -> tuple[float, float]:
        """The images' rotation error between two frames (rad: the angle of their relative
        rotation against the gyro's; the nearest checked frames taken) and the gyro's own
        1-sigma over the time between them (rad)."""
        i, j = (int(np.argmin(np.abs(self.frames - f))) for f in (frame_a, frame_b))
        v = self.vision[i].T @ self.vision[j]
        g = self.gyro[i].T @ self.gyro[j]
        err = math.acos(float(np.clip((np.trace(g.T @ v) - 1.0) / 2.0, -1.0, 1.0)))
        return err, gyro_sigma_rad(float(self.time_s[j] - self.time_s[i]))

    def worst(self) -> tuple[int, float, float]:
        """The frame where the images' rotation since the first frame departs furthest
        from the gyro's in its own sigmas: (frame, departure rad, the gyro's 1-sigma rad)."""
        gap = self.gap_rad()
        sig = np.array([gyro_sigma_rad(t - float(self.time_s[0])) for t in self.time_s])
        i = int(np.argmax(gap / sig))
        return int(self.frames[i]), float(gap[i]), float(sig[i])


def gyro_sigma_rad(duration_s: float) -> float:
    """1-sigma (rad) of the gyro's integrated rotation over ``duration_s``: its bias
    (:data:`GYRO_BIAS_SIGMA_RAD_S`) and floor (:data:`GYRO_FLOOR_RAD`) in quadrature."""
    return math.hypot(GYRO_BIAS_SIGMA_RAD_S * abs(duration_s), GYRO_FLOOR_RAD)


def gyro_warnings(check: GyroCheck | None) -> list[str]:
    """A warning when the images' rotation departs from the gyro's by more than
    :data:`GYRO_GAP_SIGMAS` of its sigmas somewhere in the run (none without a check)."""
    if check is None:
        return []
    frame, gap, sig = check.worst()
    if gap <= GYRO_GAP_SIGMAS * sig:
        return []
    return [
        f"the camera motion's rotation departs from the gyro's by {math.degrees(gap):.1f} deg "
        f"by frame {frame} (the gyro's own 1-sigma {math.degrees(sig):.1f} deg): turns and "
        "clock positions measured across it carry that error (bends' turn_sigma_deg include "
        "the departure over their own stretch beyond the gyro's drift)"
    ]


def gyro_check(
    imu: Imu | None, timestamps: np.ndarray | None, world_from_rig: np.ndarray, registered: np.ndarray
) -> GyroCheck | None:
    """The registered frames' rotations (``world_from_rig`` (N, 4, 4), ``registered`` (N,))
    beside the gyro's (``imu``, frames at ``timestamps`` (N,) s). None without a gyro,
    timestamps, two registered frames, or readings covering the frames."""
    if imu is None or imu.gyro is None or timestamps is None:
        return None
    frames = np.flatnonzero(np.asarray(registered, bool))
    if len(frames) < 2:
        return None
    times = np.asarray(timestamps, float)[frames]
    gyro = gyro_rotations(imu, times)
    if gyro is None:
        return None
    rot = np.asarray(world_from_rig, float)[frames, :3, :3]
    vision = rot[0].T[None] @ rot
    return GyroCheck(frames, times, vision, gyro)
