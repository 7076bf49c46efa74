"""Evaluation stage: a reconstruction against a dataset's ground truth.

``run(config, inputs)`` compares what ``omnipipe reconstruct`` wrote (trajectory.txt,
points.ply, report.json) with ``ground_truth/`` (poses.txt, scene.json): trajectory
error, point-to-wall error, inner diameter and per-defect errors.

What is refused and what is reported (one rule each):

- ``ground_truth/poses.txt`` missing, or holding fewer poses than the dataset has
  frames: refused (DatasetError). A partial ground truth would silently evaluate a
  subset.
- ``ground_truth/scene.json`` missing: the trajectory is evaluated, and the result
  says that wall, diameter and defects were not (``not_evaluated`` and a warning,
  printed by ``omnipipe evaluate``). Present but malformed (not a mapping, no
  ``pipe`` or ``inner_diameter_mm``, a defect without its keys): refused.
- ``report.json`` not a mapping, or a defect in it without its keys: refused.
- estimated poses whose timestamp matches no ground-truth pose: left out, with a
  warning saying how many.
"""

from __future__ import annotations

import json
import math
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any

import numpy as np

from omnipipe.config import bounded
from omnipipe.contract import Defect
from omnipipe.dataset import open_dataset, read_tum
from omnipipe.errors import DatasetError, OmnipipeError
from omnipipe.evaluation.trajectory import TrajectoryErrors, trajectory_errors
from omnipipe.geometry import apply


@dataclass(frozen=True)
class EvaluationConfig:
    """How defects are paired with the true ones.

    Attributes:
        max_axial_gap_mm: largest distance between true and measured defect centres
            along the pipe for a pair.
        max_angle_gap_deg: largest angular distance between their centres.
    """

    max_axial_gap_mm: float = bounded(60.0, gt=0)
    max_angle_gap_deg: float = bounded(25.0, gt=0, le=180)


@dataclass(frozen=True)
class EvaluationInputs:
    """Paths: the reconstruction directory and the dataset directory with ground truth."""

    reconstruction_dir: Path
    dataset_dir: Path


@dataclass(frozen=True)
class DefectMatch:
    """A true defect and the measured one paired with it (same kind, nearest centres).

    Attributes:
        true: the ground truth's defect, or None (a measured defect with no true one:
            a false positive).
        measured: the reconstruction's defect, or None (the true one was not found).
        coverage: how the true defect lies in the stretch the run measured (report.json's
            stations, first to last): "inside", "partly" (it runs past an end: the
            measured one should be flagged truncated) or "outside" (no run could find it);
            "unknown" without stations.
    """

    true: Defect | None
    measured: Defect | None
    coverage: str = "unknown"

    @property
    def found(self) -> bool:
        """A true defect with a measured one paired."""
        return self.true is not None and self.measured is not None

    @property
    def false_positive(self) -> bool:
        """A measured defect that is in no ground truth."""
        return self.true is None

    def errors(self) -> dict[str, float]:
        """Measured minus true of each size and position (mm; ``angle_deg`` wrapped to
        [-180, 180)); empty unless :attr:`found`."""
        t, m = self.true, self.measured
        if t is None or m is None:
            return {}
        return {
            "height_mm": m.height_mm - t.height_mm,
            "width_mm": m.width_mm - t.width_mm,
            "length_mm": m.length_mm - t.length_mm,
            "axial_start_mm": m.axial_start_mm - t.axial_start_mm,
            "angle_deg": (m.angle_deg - t.angle_deg + 180.0) % 360.0 - 180.0,
        }

    def to_dict(self) -> dict[str, Any]:
        """The row of ``omnipipe evaluate --json``'s ``defects``."""
        measured = None if self.measured is None else self.measured.to_contract()
        if self.true is None:
            return {"true": None, "found": False, "measured": measured, "false_positive": True}
        row: dict[str, Any] = {"true": self.true.core(), "found": self.found, "coverage": self.coverage}
        if measured is not None:
            row["measured"] = measured
            row["errors"] = self.errors()
        return row


@dataclass
class EvaluationResult:
    """All errors; ``to_dict`` is what ``omnipipe evaluate --json`` prints."""

    trajectory: TrajectoryErrors | None
    frames: int
    frames_registered: int
    wall: dict[str, float] = field(default_factory=dict)
    diameter: dict[str, float] = field(default_factory=dict)
    defects: list[DefectMatch] = field(default_factory=list)
    not_evaluated: list[str] = field(default_factory=list)
    warnings: list[str] = field(default_factory=list)
    detection_limit_mm: float | None = None

    def to_dict(self) -> dict[str, Any]:
        return {
            "frames": self.frames,
            "frames_registered": self.frames_registered,
            "trajectory": None if self.trajectory is None else self.trajectory.to_dict(),
            "wall": self.wall,
            "diameter": self.diameter,
            "defects": [d.to_dict() for d in self.defects],
            "not_evaluated": self.not_evaluated,
            "warnings": self.warnings,
        }


def _read_json(path: Path) -> dict[str, Any]:
    """A JSON file that must hold an object (mapping)."""
    if not path.is_file():
        raise DatasetError(f"{path}: not found")
    try:
        data = json.loads(path.read_text(encoding="utf-8"))
    except json.JSONDecodeError as exc:
        raise DatasetError(f"{path}: not valid JSON ({exc.msg}, line {exc.lineno})") from None
    except (UnicodeDecodeError, RecursionError):
        raise DatasetError(f"{path}: not valid JSON (not UTF-8, or nested too deep)") from None
    if not isinstance(data, dict):
        raise DatasetError(f"{path}: must hold a JSON object, got {type(data).__name__}")
    return data


_DEFECT_KEYS = ("kind", "height_mm", "width_mm", "length_mm", "axial_start_mm", "angle_deg")


def _defect_list(data: dict[str, Any], path: Path) -> list[Defect]:
    """The ``defects`` of a report.json or scene.json, each checked for the contract keys."""
    defects = data.get("defects", [])
    if not isinstance(defects, list):
        raise DatasetError(f"{path}: defects must be a list, got {type(defects).__name__}")
    for i, d in enumerate(defects):
        if not isinstance(d, dict):
            raise DatasetError(f"{path}: defects[{i}] must be an object")
        for key in _DEFECT_KEYS:
            value = d.get(key)
            ok = (
                isinstance(value, str)
                if key == "kind"
                else (
                    isinstance(value, int | float)
                    and not isinstance(value, bool)
                    and math.isfinite(value)
                )
            )
            if not ok:
                raise DatasetError(f"{path}: defects[{i}].{key} missing or invalid ({value!r})")
    return [Defect.from_contract(d) for d in defects]


def read_points_ply(path: Path) -> np.ndarray:
    """(N, 3) vertex positions of a PLY point cloud (mm)."""
    import trimesh

    if not path.is_file():
        raise DatasetError(f"{path}: not found")
    try:
        cloud = trimesh.load(str(path), process=False)
    except Exception as exc:  # trimesh raises many types for corrupt files
        raise DatasetError(f"{path}: not a readable PLY ({type(exc).__name__})") from None
    return np.asarray(cloud.vertices, dtype=float)


def measured_stretch(report: dict[str, Any]) -> tuple[float, float] | None:
    """(first, last) axial position of report.json's stations (mm), or None."""
    axial = [
        float(st["axial_mm"])
        for st in report.get("stations") or []
        if isinstance(st, dict) and isinstance(st.get("axial_mm"), int | float)
    ]
    return (min(axial), max(axial)) if axial else None


def _coverage(true: Defect | None, report: dict[str, Any]) -> str:
    """"inside", "partly", "outside" the measured stretch, or "unknown" (no stations)."""
    stretch = measured_stretch(report)
    if true is None or stretch is None:
        return "unknown"
    lo, hi = stretch
    if true.axial_end_mm < lo or true.axial_start_mm > hi:
        return "outside"
    return "inside" if true.axial_start_mm >= lo and true.axial_end_mm <= hi else "partly"


def _pair_defects(
    true: list[Defect], measured: list[Defect], config: EvaluationConfig
) -> list[DefectMatch]:
    """Each true defect with the nearest unpaired measured one of its kind within the
    config's gaps (cost: the gaps as fractions of their limits), then the measured
    ones left over (false positives)."""
    rows = []
    used: set[int] = set()
    for t in true:
        best, best_cost = None, math.inf
        for j, m in enumerate(measured):
            if j in used or m.kind != t.kind:
                continue
            d_ax = abs(m.axial_centre_mm - t.axial_centre_mm)
            d_ang = abs((m.angle_deg - t.angle_deg + 180.0) % 360.0 - 180.0)
            if d_ax > config.max_axial_gap_mm or d_ang > config.max_angle_gap_deg:
                continue
            cost = d_ax / config.max_axial_gap_mm + d_ang / config.max_angle_gap_deg
            if cost < best_cost:
                best, best_cost = j, cost
        if best is not None:
            used.add(best)
        rows.append(DefectMatch(t, None if best is None else measured[best]))
    rows.extend(DefectMatch(None, m) for j, m in enumerate(measured) if j not in used)
    return rows


def run(config: EvaluationConfig, inputs: EvaluationInputs) -> EvaluationResult:
    """Compare a reconstruction with ground truth.

    Raises:
        DatasetError: the dataset has no ground truth (or fewer true poses than frames),
            or an output or ground-truth file is missing, corrupt or malformed.
    """
    dataset = open_dataset(inputs.dataset_dir)
    gt_dir = dataset.ground_truth_dir
    if not (gt_dir / "poses.txt").is_file():
        raise DatasetError(
            f"{gt_dir / 'poses.txt'}: the dataset has no ground truth to evaluate against"
        )
    gt_stamps, gt_poses = read_tum(gt_dir / "poses.txt")
    if len(gt_stamps) < len(dataset):
        raise DatasetError(
            f"{gt_dir / 'poses.txt'}: {len(gt_stamps)} poses for {len(dataset)} frames "
            "(ground truth must have a pose for every frame)"
        )
    out = Path(inputs.reconstruction_dir)
    est_stamps, est_poses = read_tum(out / "trajectory.txt")
    report = _read_json(out / "report.json")
    measured_defects = _defect_list(report, out / "report.json")
    # Pair frames by timestamp.
    idx = np.searchsorted(gt_stamps, est_stamps).clip(0, len(gt_stamps) - 1)
    idx_lo = (idx - 1).clip(0)
    nearest = np.where(
        np.abs(gt_stamps[idx_lo] - est_stamps) < np.abs(gt_stamps[idx] - est_stamps), idx_lo, idx
    )
    ok = np.abs(gt_stamps[nearest] - est_stamps) < 1e-4
    traj = None
    if ok.sum() >= 2:
        traj = trajectory_errors(est_poses[ok], gt_poses[nearest[ok]])
    limit = report.get("detection_limit_mm")
    result = EvaluationResult(
        trajectory=traj,
        frames=len(gt_stamps),
        frames_registered=int(ok.sum()),
        detection_limit_mm=float(limit) if isinstance(limit, int | float) else None,
    )
    if (~ok).any():
        result.warnings.append(
            f"{int((~ok).sum())} of {len(ok)} poses of trajectory.txt have no ground-truth pose "
            "at their timestamp and are not evaluated"
        )

    scene_path = gt_dir / "scene.json"
    if not scene_path.is_file():
        result.not_evaluated = ["wall", "diameter", "defects"]
        result.warnings.append(
            f"{scene_path}: not found; wall, inner diameter and defects are not evaluated"
        )
        return result
    _against_scene(result, config, _read_json(scene_path), scene_path, out, report, measured_defects)
    return result


def _against_scene(
    result: EvaluationResult,
    config: EvaluationConfig,
    scene: dict[str, Any],
    scene_path: Path,
    out: Path,
    report: dict[str, Any],
    measured_defects: list[Defect],
) -> None:
    """The wall, inner diameter and defects of ``result`` against the true pipe of
    ``scene`` (scene.json), filled in place (``out``: the reconstruction, ``report``:
    its report.json).

    Raises:
        DatasetError: a malformed scene.json.
    """
    from omnipipe.sim.scene import Pipe

    true_d = scene.get("inner_diameter_mm")
    if not isinstance(true_d, int | float) or isinstance(true_d, bool) or not true_d > 0:
        raise DatasetError(f"{scene_path}: inner_diameter_mm missing or invalid ({true_d!r})")
    if not isinstance(scene.get("pipe"), dict):
        raise DatasetError(f"{scene_path}: pipe missing or not an object")
    true_defects = _defect_list(scene, scene_path)
    try:
        pipe = Pipe.from_dict(scene["pipe"])
    except OmnipipeError:
        raise
    except (KeyError, TypeError, ValueError) as exc:
        raise DatasetError(
            f"{scene_path}: pipe is not a valid pipe description ({type(exc).__name__}: {exc})"
        ) from None
    traj = result.trajectory
    if traj is not None and (out / "points.ply").is_file():
        pts = apply(traj.gt_from_est, read_points_ply(out / "points.ply"))
        if len(pts):
            sigma, rho, theta, *_ = pipe.pipe_coordinates(pts)
            err = rho - pipe.wall_radius(sigma, theta)
            result.wall = {
                "points": len(pts),
                "rmse_mm": float(np.sqrt(np.mean(err**2))),
                "bias_mm": float(np.mean(err)),
                "median_abs_mm": float(np.median(np.abs(err))),
                "p95_abs_mm": float(np.percentile(np.abs(err), 95)),
            }
    true_d = float(true_d)
    measured_d = report.get("inner_diameter_mm")
    result.diameter = {"true_mm": true_d}
    if isinstance(measured_d, int | float):
        result.diameter.update(
            {"measured_mm": float(measured_d), "error_mm": float(measured_d) - true_d}
        )
    result.defects = [
        replace(row, coverage=_coverage(row.true, report))
        for row in _pair_defects(true_defects, measured_defects, config)
    ]
