"""Standard uncertainties of the analysis' measurements as report.json states them.

Lengths along the pipe (defect length and axial start, run length) get the camera
motion's relative scale uncertainty; angles the rotation drift of the trajectory
(:func:`report_fields`).
"""

from __future__ import annotations

import math
from typing import Any

import numpy as np

from omnipipe.analysis.stage import AnalysisConfig, AnalysisResult


def report_fields(
    res: AnalysisResult, scale_sigma_rel: float, config: AnalysisConfig | None = None
) -> tuple[dict[str, Any], list[str]]:
    """The analysis keys of report.json, each value with its 1-sigma uncertainty.

    Lengths along the pipe (defect length and axial start, run length) get the camera
    motion's relative scale uncertainty ``scale_sigma_rel`` (NaN:
    ``config.fallback_scale_sigma_rel``, with a warning) added in quadrature: over a
    stretch x of a run of length T, ``rel * sqrt(x T)`` (step errors add like a random
    walk; ``rel * T`` over the whole run); a defect's axial start takes x = the robot's
    travel from the first frame to the rings at its start. Angles get
    ``config.angle_pose_sigma_deg``.

    Returns:
        (keys, warnings): inner_diameter_mm and _sigma_mm, run_length_mm and _sigma_mm,
        detection_limit_mm, ovality_max, pipe_straight, stations, defects.
    """
    config = config or AnalysisConfig()
    warnings: list[str] = []
    rel = float(scale_sigma_rel)
    if not math.isfinite(rel):
        rel = config.fallback_scale_sigma_rel
        warnings.append(
            "the camera motion did not state its scale uncertainty: lengths along the pipe carry "
            f"an assumed {100 * rel:.1f} % (1 sigma)"
        )

    def r(x: float | None, nd: int = 3) -> float | None:
        return None if x is None or not math.isfinite(x) else round(float(x), nd)

    ax = np.asarray(res.stations_axial_mm, float)
    run_length = float(np.ptp(ax)) if len(ax) else 0.0

    def position_sigma(x: float) -> float:
        # Lengths from the steps' spread add like a random walk: a stretch x of a run of
        # length T carries rel * sqrt(x T) (rel * T is the sigma over the whole run); a
        # run-wide scale error gives rel * x, never more than that.
        x = abs(x)
        return math.hypot(rel * math.sqrt(x * max(run_length, x)), cal * x)

    cal = float(res.calibration_sigma_rel)
    defects = []
    for d in res.defects:
        d = dict(d)
        travel = d.pop("travel_mm", None)
        travel = abs(d["axial_start_mm"]) if travel is None else float(travel)
        if d.get("length_sigma_mm") is not None:
            d["length_sigma_mm"] = r(math.hypot(d["length_sigma_mm"], position_sigma(d["length_mm"])), 4)
            d["axial_start_sigma_mm"] = r(math.hypot(d["axial_start_sigma_mm"], position_sigma(travel)), 4)
            d["angle_sigma_deg"] = r(math.hypot(d["angle_sigma_deg"], config.angle_pose_sigma_deg), 4)
        defects.append(d)
    # Ends of the run: a ring position is known to about the point noise along the axis.
    run_sigma = math.hypot(
        position_sigma(run_length), math.sqrt(2.0) * (res.noise_mm if math.isfinite(res.noise_mm) else 0.0)
    )
    n = len(res.stations_diameter_mm)
    dsig = res.stations_diameter_sigma_mm if len(res.stations_diameter_sigma_mm) == n else np.full(n, np.nan)
    osig = res.stations_ovality_sigma if len(res.stations_ovality_sigma) == n else np.full(n, np.nan)
    stations = [
        {
            "axial_mm": round(float(a), 2),
            "diameter_mm": round(float(d), 3),
            "diameter_sigma_mm": r(float(ds), 4),
            "ovality": r(float(o), 5),
            "ovality_sigma": r(float(os_), 5),
        }
        for a, d, ds, o, os_ in zip(
            res.stations_axial_mm, res.stations_diameter_mm, dsig, res.stations_ovality, osig,
            strict=True,
        )
    ]
    fields = {
        "inner_diameter_mm": round(res.inner_diameter_mm, 3),
        "inner_diameter_sigma_mm": r(res.inner_diameter_sigma_mm, 4),
        "run_length_mm": round(run_length, 2),
        "run_length_sigma_mm": r(run_sigma, 3),
        "scale_sigma_rel": r(rel, 5),
        # The rig calibration's share (rig.yaml laser.offset_sigma_mm); None: not stated.
        "calibration_sigma_rel": r(cal, 6) if cal > 0 else None,
        "detection_limit_mm": r(res.detection_limit_mm, 3),
        "detection_limit_reference_mm": {
            "width": config.limit_width_mm,
            "length": config.limit_length_mm,
        },
        "wall_noise_mm": r(res.noise_mm, 4),
        "ring_spacing_mm": r(res.ring_spacing_mm, 2),
        "defects": defects,
        "ovality_max": r(res.ovality_max, 5),
        "pipe_straight": res.straight,
        "stations": stations,
    }
    return fields, warnings
