"""Standard uncertainties of the analysis' measurements as report.json states them.

Lengths along the pipe (defect length and axial start, run length) get the camera
motion's relative scale uncertainty; angles the rotation drift of the trajectory
(:func:`report_fields`).
"""

from __future__ import annotations

import math
from dataclasses import replace
from typing import Any

import numpy as np

from omnipipe.analysis.records import AnalysisConfig, AnalysisResult
from omnipipe.contract import Defect


def scale_sigma(scale_sigma_rel: float, config: AnalysisConfig) -> tuple[float, list[str]]:
    """The camera motion's relative scale 1-sigma, or (NaN) ``config.fallback_scale_sigma_rel``
    with a warning saying so."""
    rel = float(scale_sigma_rel)
    if math.isfinite(rel):
        return rel, []
    rel = config.fallback_scale_sigma_rel
    return rel, [
        "the camera motion did not state its scale uncertainty: lengths along the pipe carry "
        f"an assumed {100 * rel:.1f} % (1 sigma)"
    ]


def run_length_mm(res: AnalysisResult) -> float:
    """Extent of the measured stations along the pipe (mm)."""
    ax = np.asarray(res.stations_axial_mm, float)
    return float(np.ptp(ax)) if len(ax) else 0.0


def position_sigma(x: float, rel: float, run_length: float, cal: float) -> float:
    """1-sigma (mm) of a length ``x`` along a run of length ``run_length``.

    Lengths from the steps' spread add like a random walk: a stretch x of a run of
    length T carries rel * sqrt(x T) (rel * T is the sigma over the whole run); a
    run-wide scale error gives rel * x, never more than that; the rig calibration's
    share ``cal`` scales it alike.
    """
    x = abs(x)
    return math.hypot(rel * math.sqrt(x * max(run_length, x)), cal * x)


def _r(x: float | None, nd: int = 3) -> float | None:
    return None if x is None or not math.isfinite(x) else round(float(x), nd)


def scaled_defects(
    res: AnalysisResult, scale_sigma_rel: float, config: AnalysisConfig | None = None
) -> list[Defect]:
    """The analysis' defects with the lengths along the pipe widened by the camera
    motion's scale (:func:`report_fields`) and the angles by the trajectory's rotation
    drift (``config.angle_pose_sigma_deg``); ``travel_mm`` is spent."""
    config = config or AnalysisConfig()
    rel, _ = scale_sigma(scale_sigma_rel, config)
    run_length = run_length_mm(res)
    cal = float(res.calibration_sigma_rel)
    out = []
    for d in res.defects:
        travel = abs(d.axial_start_mm) if d.travel_mm is None else float(d.travel_mm)
        if (
            d.length_sigma_mm is not None
            and d.axial_start_sigma_mm is not None
            and d.angle_sigma_deg is not None
        ):
            d = replace(
                d,
                length_sigma_mm=_r(
                    math.hypot(d.length_sigma_mm, position_sigma(d.length_mm, rel, run_length, cal)), 4
                ),
                axial_start_sigma_mm=_r(
                    math.hypot(d.axial_start_sigma_mm, position_sigma(travel, rel, run_length, cal)), 4
                ),
                angle_sigma_deg=_r(math.hypot(d.angle_sigma_deg, config.angle_pose_sigma_deg), 4),
            )
        out.append(replace(d, travel_mm=None))
    return out


def headline_position_sigma(res: AnalysisResult, rel: float, cal: float) -> float:
    """1-sigma (mm) the headline inner diameter takes from where its median station lies
    along a taper: on a reducing run the median reads the station in the middle of the
    ramp, and the run's length scale (``rel``, the camera motion's; ``cal``, the rig
    calibration's) places that station, as any position along the pipe
    (:func:`position_sigma` of its travel from the first station), so the diameter it
    stands for is uncertain by the ramp's slope times that. 0 off a taper.
    Random-features seed 25 (a 339 -> 281 mm reducer, the motion's scale 10.5 % at 1
    sigma): 306.9 +- 0.85 mm read against 294.4 mm where the stations say it lies."""
    from omnipipe.analysis.feature_types import Taper

    st = res.stations
    if not st:
        return 0.0
    axial = np.array([s.axial_mm for s in st])
    d = np.array([s.diameter_mm for s in st])
    at = float(axial[int(np.argmin(np.abs(d - res.inner_diameter_mm)))])
    run_length = run_length_mm(res)
    out = 0.0
    for f in res.features:
        if isinstance(f, Taper) and f.axial_from_mm <= at <= f.axial_to_mm and f.axial_to_mm > f.axial_from_mm:
            slope = abs(f.diameter_to_mm - f.diameter_from_mm) / (f.axial_to_mm - f.axial_from_mm)
            out = max(out, slope * position_sigma(at - float(axial.min()), rel, run_length, cal))
    return out


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
        detection_limit_mm, ovality_max, pipe_straight, stations, defects
        (:func:`scaled_defects`, in their report.json form).
    """
    config = config or AnalysisConfig()
    rel, warnings = scale_sigma(scale_sigma_rel, config)
    run_length = run_length_mm(res)
    cal = float(res.calibration_sigma_rel)
    # Ends of the run: a ring position is known to about the point noise along the axis.
    run_sigma = math.hypot(
        position_sigma(run_length, rel, run_length, cal),
        math.sqrt(2.0) * (res.noise_mm if math.isfinite(res.noise_mm) else 0.0),
    )
    head_sigma = math.hypot(res.inner_diameter_sigma_mm, headline_position_sigma(res, rel, cal))
    fields = {
        "inner_diameter_mm": round(res.inner_diameter_mm, 3),
        "inner_diameter_sigma_mm": _r(head_sigma, 4),
        "run_length_mm": round(run_length, 2),
        "run_length_sigma_mm": _r(run_sigma, 3),
        "scale_sigma_rel": _r(rel, 5),
        # The rig calibration's share (rig.yaml laser.offset_sigma_mm); None: not stated.
        "calibration_sigma_rel": _r(cal, 6) if cal > 0 else None,
        "detection_limit_mm": _r(res.detection_limit_mm, 3),
        "detection_limit_reference_mm": {
            "width": config.limit_width_mm,
            "length": config.limit_length_mm,
        },
        "wall_noise_mm": _r(res.noise_mm, 4),
        "ring_spacing_mm": _r(res.ring_spacing_mm, 2),
        "defects": [d.to_contract() for d in scaled_defects(res, scale_sigma_rel, config)],
        "ovality_max": _r(res.ovality_max, 5),
        "pipe_straight": res.straight,
        "stations": _stations(res),
        "features": [f.to_contract() for f in res.features],
    }
    if math.isfinite(res.inner_diameter_min_mm):
        fields["inner_diameter_min_mm"] = _r(res.inner_diameter_min_mm, 3)
        fields["inner_diameter_max_mm"] = _r(res.inner_diameter_max_mm, 3)
    fields["water_depth_mm"] = _r(res.water_depth_mm, 2) if res.water_depth_mm is not None else 0.0
    fields["water_depth_sigma_mm"] = _r(res.water_depth_sigma_mm, 3) if res.water_depth_sigma_mm is not None else None
    return fields, warnings


def _stations(res: AnalysisResult) -> list[dict[str, Any]]:
    """report.json's ``stations``: each station's contract keys with their 1-sigma
    (:meth:`.stations.Station.to_contract`)."""
    return [st.to_contract() for st in res.stations]
