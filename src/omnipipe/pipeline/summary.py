"""What a run's results say: report.json's content and the wall for the relief maps.

:func:`report_summary`: report.json's content (every measurement with its 1-sigma,
lengths in mm; stage times in s; the mesh's size and edge flips) and the reported defects,
flagged and widened where the camera motion is unreliable (:mod:`.quality`).
:func:`wall_points`: the analysis' wall points (axial mm, angle in degrees [0, 360),
deviation mm) for the relief maps.
"""

from __future__ import annotations

from dataclasses import replace
from typing import TYPE_CHECKING, Any

if TYPE_CHECKING:  # imported inside the functions: `omnipipe --help` stays fast
    from concurrent.futures import Executor

    from omnipipe.analysis import AnalysisResult
    from omnipipe.contract import Defect
    from omnipipe.dataset import Dataset
    from omnipipe.model import ModelResult
    from omnipipe.pipeline.run_config import ReconstructConfig, RunLog
    from omnipipe.pipeline.stage_calls import Measured, Motion
    from omnipipe.report.relief import WallPoints


def wall_points(res: AnalysisResult) -> WallPoints | None:
    """The analysis' wall points and deviations for the relief maps, or None."""
    import numpy as np

    from omnipipe.report.relief import WallPoints
    from omnipipe.spill import zeros_on_disk

    if not len(res.point_sigma_mm):
        return None
    # Each point's angle in degrees, in the run's scratch (omnipipe.spill) a chunk at a time.
    theta = res.point_theta_rad
    angle = zeros_on_disk(theta.shape, np.result_type(theta.dtype, np.float16))
    for a in range(0, len(theta), 1 << 16):
        angle[a : a + (1 << 16)] = np.degrees(theta[a : a + (1 << 16)]) % 360.0
    return WallPoints(
        axial_mm=res.point_sigma_mm,
        angle_deg=angle,
        deviation_mm=res.point_deviation_mm,
        radius_mm=res.radius_mm,
    )


def report_summary(
    config: ReconstructConfig,
    dataset: Dataset,
    motion: Motion,
    measured: Measured,
    mdl: ModelResult,
    executor: Executor,
    log: RunLog,
) -> tuple[dict[str, Any], list[Defect]]:
    """report.json's content (without ``input_quality``) and the reported defects."""
    import numpy as np

    from omnipipe import analysis
    from omnipipe.executor import describe as describe_executor
    from omnipipe.model.export import model_files
    from omnipipe.pipeline import quality

    n = len(dataset)
    sfm_result, stations, traj_quality = motion.result, measured.stations, measured.quality
    # Every measurement with its 1-sigma (lengths along the pipe: the motion's scale sigma).
    scale_rel = getattr(sfm_result, "scale_sigma_rel", float("nan"))
    features, feature_warnings = quality.flag_features(measured.result.features, traj_quality)
    result = replace(measured.result, features=features)
    fields, measure_warnings = analysis.report_fields(result, scale_rel, config.analysis)
    log.warnings.extend([*measure_warnings, *feature_warnings])
    if len(fields.get("stations", [])) == len(stations):
        for entry, frame in zip(fields["stations"], stations, strict=True):
            entry["frame"] = int(frame)  # the frame whose ring this station is
    defects = analysis.scaled_defects(result, scale_rel, config.analysis)
    defects, flag_warnings = quality.flag_defects(defects, traj_quality)
    log.warnings.extend(flag_warnings)
    widened = quality.widen_for_unreliable(fields["run_length_sigma_mm"], defects, traj_quality)
    defects = widened.defects
    log.warnings.extend(widened.warnings)
    fields["defects"] = [d.to_contract() for d in defects]
    fields["run_length_sigma_mm"] = widened.run_length_sigma_mm
    fields["run_length_unreliable_mm"] = widened.run_length_unreliable_mm
    timings = log.timings
    summary = {
        "frames": n,
        "frames_registered": len(motion.registered_frames),
        **fields,
        "timings_s": {k: round(v, 3) for k, v in timings.items()},
        # Frames of the run per second of each stage (and of the whole run).
        "frames_per_s": {
            k: round(n / v, 3) if v > 0 else None for k, v in timings.items() if k != "startup"
        },
        "executor": describe_executor(executor),
        "warnings": log.warnings,
        "stationary_frames": int(np.sum(sfm_result.stationary)),
        "wall_outliers_removed": measured.outliers_removed,
        "files": model_files(mdl),  # each 3-D file's unit and axes
        "mesh": _mesh_summary(mdl),
        "keyframes": int(np.sum(sfm_result.keyframe)),
        "tracked_frames": 0 if sfm_result.tracked is None else int(np.sum(sfm_result.tracked)),
        "trajectory_quality": traj_quality.to_contract(),
    }
    return summary, defects


def _mesh_summary(mdl: ModelResult) -> dict[str, Any]:
    """report.json's ``mesh``: its size and what the edge flips did."""
    flips = mdl.flip_stats
    return {
        "vertices": int(len(mdl.mesh_vertices)),
        "faces": int(len(mdl.mesh_faces)),
        "flips_per_pass": [] if flips is None else flips.flips,
        "photo_inconsistency_before": None if flips is None else round(flips.cost_before, 3),
        "photo_inconsistency_after": None if flips is None else round(flips.cost_after, 3),
    }
