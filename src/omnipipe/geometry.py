"""Rigid transforms and rotations shared by every stage.

Transforms are (4, 4) homogeneous matrices named ``dst_from_src``:
``points_in_world = apply(world_from_rig, points_in_rig)``. Rotations are (3, 3)
matrices; quaternions are (x, y, z, w) as in the TUM format.
"""

from __future__ import annotations

import numpy as np
from scipy.spatial.transform import Rotation

from omnipipe.errors import ShapeError


def make_transform(rotation: np.ndarray, translation: np.ndarray) -> np.ndarray:
    """(4, 4) transform from a (3, 3) rotation and a (3,) translation (mm)."""
    T = np.eye(4)
    T[:3, :3] = rotation
    T[:3, 3] = np.asarray(translation, dtype=float).reshape(3)
    return T


def invert(dst_from_src: np.ndarray) -> np.ndarray:
    """The inverse transform src_from_dst of a (4, 4) rigid transform."""
    R = dst_from_src[:3, :3]
    t = dst_from_src[:3, 3]
    return make_transform(R.T, -R.T @ t)


def apply(dst_from_src: np.ndarray, points_in_src: np.ndarray) -> np.ndarray:
    """(N, 3) points in dst from (N, 3) points in src."""
    pts = np.asarray(points_in_src, dtype=float)
    if pts.ndim != 2 or pts.shape[1] != 3:
        raise ShapeError(f"points: expected shape (N, 3), got {pts.shape}")
    return pts @ dst_from_src[:3, :3].T + dst_from_src[:3, 3]


def rotate(dst_from_src: np.ndarray, vectors_in_src: np.ndarray) -> np.ndarray:
    """(N, 3) directions in dst from (N, 3) directions in src (rotation only)."""
    return np.asarray(vectors_in_src, dtype=float) @ dst_from_src[:3, :3].T


def transform_from_tum(txyz_qxyzw: np.ndarray) -> np.ndarray:
    """(4, 4) transform from a TUM row (tx, ty, tz, qx, qy, qz, qw)."""
    row = np.asarray(txyz_qxyzw, dtype=float)
    return make_transform(Rotation.from_quat(row[3:7]).as_matrix(), row[:3])


def tum_from_transform(dst_from_src: np.ndarray) -> np.ndarray:
    """(7,) TUM row (tx, ty, tz, qx, qy, qz, qw) of a transform, qw >= 0."""
    q = Rotation.from_matrix(dst_from_src[:3, :3]).as_quat()
    if q[3] < 0:
        q = -q
    return np.concatenate([dst_from_src[:3, 3], q])


def skew(v: np.ndarray) -> np.ndarray:
    """(3, 3) cross-product matrix [v]_x (the paper's T of Eq. (16) for v = t)."""
    x, y, z = np.asarray(v, dtype=float).reshape(3)
    return np.array([[0.0, -z, y], [z, 0.0, -x], [-y, x, 0.0]])


def rotation_angle(rotation: np.ndarray) -> float:
    """Angle (rad) of a (3, 3) rotation."""
    return float(Rotation.from_matrix(rotation).magnitude())


def interpolated_pose(world_from_a: np.ndarray, world_from_b: np.ndarray, f: float) -> np.ndarray:
    """The (4, 4) pose at fraction ``f`` (0..1) from ``world_from_a`` to ``world_from_b``:
    position linear, rotation slerped (about the relative rotation's axis)."""
    ra = Rotation.from_matrix(world_from_a[:3, :3])
    rel = (ra.inv() * Rotation.from_matrix(world_from_b[:3, :3])).as_rotvec()
    pose = np.eye(4)
    pose[:3, :3] = (ra * Rotation.from_rotvec(f * rel)).as_matrix()
    pose[:3, 3] = (1 - f) * world_from_a[:3, 3] + f * world_from_b[:3, 3]
    return pose
