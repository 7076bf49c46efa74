"""Trajectory error against ground truth: SE(3) / Sim(3) alignment, ATE, scale, rotation.

Alignment uses both positions and orientations: the rotation is the chordal mean of
``R_gt_i R_est_i^T`` (well defined even for a nearly straight path, whose roll about
its own line positions alone cannot fix), the translation and the optional scale
follow from the positions by least squares.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from omnipipe.errors import ShapeError
from omnipipe.geometry import make_transform, rotation_angle


@dataclass(frozen=True)
class TrajectoryErrors:
    """Errors of an estimated trajectory against ground truth.

    Attributes:
        frames: number of frames compared.
        ate_rmse_mm: RMS position error after SE(3) alignment (no scale).
        ate_max_mm: largest position error after SE(3) alignment.
        scale_error: |s - 1| of the Sim(3) alignment (0.005 = 0.5 %).
        rotation_rmse_deg: RMS rotation error after alignment.
        path_length_mm: length of the true path.
        gt_from_est: (4, 4) the SE(3) alignment (ground-truth world from estimated world).
    """

    frames: int
    ate_rmse_mm: float
    ate_max_mm: float
    scale_error: float
    rotation_rmse_deg: float
    path_length_mm: float
    gt_from_est: np.ndarray

    def to_dict(self) -> dict[str, float | int]:
        return {
            "frames": self.frames,
            "ate_rmse_mm": self.ate_rmse_mm,
            "ate_max_mm": self.ate_max_mm,
            "scale_error": self.scale_error,
            "scale_error_percent": 100.0 * self.scale_error,
            "rotation_rmse_deg": self.rotation_rmse_deg,
            "path_length_mm": self.path_length_mm,
        }


def _chordal_mean(rotations: np.ndarray) -> np.ndarray:
    u, _, vt = np.linalg.svd(rotations.sum(axis=0))
    d = np.sign(np.linalg.det(u @ vt))
    return u @ np.diag([1.0, 1.0, d]) @ vt


def align(
    est_world_from_rig: np.ndarray, gt_world_from_rig: np.ndarray, with_scale: bool = False
) -> tuple[np.ndarray, float]:
    """Alignment gt_world_from_est_world (4, 4) and scale s of two (N, 4, 4) trajectories.

    With ``with_scale``, gt positions ~ s R p_est + t; otherwise s = 1.
    """
    est = np.asarray(est_world_from_rig, float)
    gt = np.asarray(gt_world_from_rig, float)
    if est.ndim != 3 or est.shape[1:] != (4, 4) or est.shape != gt.shape:
        raise ShapeError(
            f"trajectories: expected two (N, 4, 4) arrays of one N, got {est.shape} and {gt.shape}"
        )
    rotation = _chordal_mean(gt[:, :3, :3] @ np.transpose(est[:, :3, :3], (0, 2, 1)))
    p_est = est[:, :3, 3] @ rotation.T
    p_gt = gt[:, :3, 3]
    c_est, c_gt = p_est.mean(axis=0), p_gt.mean(axis=0)
    scale = 1.0
    if with_scale:
        denom = float(np.sum((p_est - c_est) ** 2))
        if denom > 1e-12:
            scale = float(np.sum((p_gt - c_gt) * (p_est - c_est)) / denom)
    translation = c_gt - scale * c_est
    return make_transform(rotation, translation), scale


def trajectory_errors(
    est_world_from_rig: np.ndarray, gt_world_from_rig: np.ndarray
) -> TrajectoryErrors:
    """ATE (SE(3) alignment, no scale), scale error (Sim(3)) and rotation RMSE."""
    gt_from_est, _ = align(est_world_from_rig, gt_world_from_rig)
    _, scale = align(est_world_from_rig, gt_world_from_rig, with_scale=True)
    aligned = gt_from_est[None] @ est_world_from_rig
    pos_err = np.linalg.norm(aligned[:, :3, 3] - gt_world_from_rig[:, :3, 3], axis=1)
    rot_err = np.array(
        [
            rotation_angle(a[:3, :3].T @ g[:3, :3])
            for a, g in zip(aligned, gt_world_from_rig, strict=True)
        ]
    )
    path = float(np.sum(np.linalg.norm(np.diff(gt_world_from_rig[:, :3, 3], axis=0), axis=1)))
    return TrajectoryErrors(
        frames=len(pos_err),
        ate_rmse_mm=float(np.sqrt(np.mean(pos_err**2))),
        ate_max_mm=float(pos_err.max()),
        scale_error=abs(scale - 1.0),
        rotation_rmse_deg=float(np.degrees(np.sqrt(np.mean(rot_err**2)))),
        path_length_mm=path,
        gt_from_est=gt_from_est,
    )
