"""Camera motion read from a trajectory file instead of estimated (``sfm.trajectory_from``).

A user with an external trajectory (a total station, a tracked robot, or a simulator's
``ground_truth/poses.txt``) gives it as a TUM file: one line ``t tx ty tz qx qy qz qw``
per pose, seconds and mm, ``world_from_rig`` in any fixed world frame. Every moving
frame takes the pose whose time is nearest its own (within half the median frame
interval, else the run is refused naming the frame); a stationary frame keeps its
station's pose. The poses are re-expressed in the rig frame of frame 0 (the
:class:`~omnipipe.sfm.types.SfmResult` convention). omnipipe does not know the file's
uncertainty: ``scale_sigma_rel`` is NaN and the analysis falls back to its
``fallback_scale_sigma_rel`` (with a warning), and no step is checked or flagged.
"""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np

from omnipipe.dataset import read_tum
from omnipipe.errors import ConfigError, ReconstructionError
from omnipipe.sfm.types import SfmInputs, SfmResult


def trajectory_path(setting: str, inputs: SfmInputs) -> Path:
    """``sfm.trajectory_from`` as a path: absolute, or relative to the dataset's root.

    Raises:
        ConfigError: a relative path without a dataset to resolve it against.
    """
    path = Path(setting)
    if path.is_absolute():
        return path
    if inputs.dataset is None:
        raise ConfigError("sfm.trajectory_from", f"relative path {setting!r} needs a dataset")
    return Path(inputs.dataset.root) / path


def external_motion(path: Path, inputs: SfmInputs) -> SfmResult:
    """Every frame's pose from the TUM file at ``path`` (see the module docstring).

    Raises:
        DatasetError: the file is missing or malformed.
        ReconstructionError: no frame times, or a moving frame with no pose near its time.
    """
    if inputs.timestamps is None:
        raise ReconstructionError(f"{path}: frame times are needed to read an external trajectory")
    stamps, poses = read_tum(path)
    times = np.asarray(inputs.timestamps, float)
    n = inputs.n_frames
    moved = np.ones(n, bool) if inputs.moved is None else np.asarray(inputs.moved, bool).copy()
    moved[0] = True
    order = np.argsort(stamps)
    stamps, poses = stamps[order], poses[order]
    tol = 0.5 * float(np.median(np.diff(times))) if n > 1 else math.inf
    j = np.clip(np.searchsorted(stamps, times), 1, max(len(stamps) - 1, 1))
    left = np.clip(j - 1, 0, len(stamps) - 1)
    right = np.clip(j, 0, len(stamps) - 1)
    nearest = np.where(np.abs(stamps[left] - times) <= np.abs(stamps[right] - times), left, right)
    gap = np.abs(stamps[nearest] - times)
    bad = np.flatnonzero(moved & (gap > tol))
    if len(bad):
        raise ReconstructionError(
            f"{path}: no pose within {tol:.3g} s of frame {bad[0]} (t = {times[bad[0]]:g} s)"
        )
    station = np.cumsum(moved) - 1
    first = np.flatnonzero(moved)
    rig0_from_world = np.linalg.inv(poses[nearest[0]])
    world_from_station = rig0_from_world @ poses[nearest[first]]
    return SfmResult(
        world_from_rig=world_from_station[station],
        registered=np.ones(n, bool),
        keyframe=moved.copy(),
        stationary=~moved,
        station=station,
        warnings=[f"camera motion read from {path} (not estimated; its uncertainty is not known)"],
        scale_source=f"external trajectory ({path.name})",
    )
