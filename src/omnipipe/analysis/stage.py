"""Analysis stage: inner diameter, ovality and defects of the measured pipe (Table I).

``run(config, inputs)`` takes the integrated ring points (world frame) and the poses
of the rings' frames (:mod:`.records`: the stage's config, inputs and result) and returns:

* the centreline by piecewise robust cylinder fitting (:mod:`.centreline`,
  :mod:`.axis_fit`); the inner diameter is the single cylinder fitted to the whole run
  when the pipe is straight (the paper's cylinder fitting, Table I) and the median of the
  piecewise fits when it bends;
* each station re-centred on its own section (:func:`.centreline.recentred`), then per
  station (ring) a robust Fourier fit of the radius around the axis: mean diameter
  (Dmax + Dmin) / 2, ovality (Dmax - Dmin) / D and its axis, standing water from the
  ring's cut-off chord (:mod:`.station_profiles`, :mod:`.stations`); the headline inner
  diameter is the stations' mean (:mod:`.headline`, :func:`.stations.headline`), on a
  reducing run that of the section most stations measured
  (:func:`.stations.headline_of_a_section`), and the section features (taper, bend,
  ovality, water) follow from the stations and the centreline (:mod:`.sections`);
* the radial deviation of every point from that wall, and the bulges and dents found
  in it (:mod:`.defects`, sized by a model fit, :mod:`.sizing`), in the data contract's
  convention (axial position along the centreline from the first frame's origin, angle
  from its x axis towards y). The rings crossing a defect are then refitted without the
  defect's samples (so a wide defect does not pull its ring's wall profile) and the
  defects measured again on the corrected deviations (:mod:`.wall_measure`);
* a standard uncertainty for each number (:func:`.uncertainty.report_fields` adds the camera
  motion's scale uncertainty to everything measured along the pipe).
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from concurrent.futures import Executor

import numpy as np

from omnipipe.analysis.axis_fit import fit_axis, offset_breaks, recentred_line
from omnipipe.analysis.defect_accept import measured_only
from omnipipe.analysis.feature_types import Joint
from omnipipe.analysis.features import feature_zones, find_features, with_offset_joints_kept
from omnipipe.analysis.footprint import (
    footprint_mm,
    footprint_terms,
    water_footprint_terms,
    with_water_footprint,
)
from omnipipe.analysis.headline import (
    run_water,
    sections_and_headline,
    tilt_corrected,
    with_ring_terms,
)
from omnipipe.analysis.records import AnalysisConfig, AnalysisInputs, AnalysisResult, section_config
from omnipipe.analysis.station_profiles import ring_groups
from omnipipe.analysis.stations import EdgeReach, Section, SectionConfig, Station, with_water
from omnipipe.analysis.wall_measure import measure_wall, with_systematics
from omnipipe.errors import ReconstructionError, ShapeError
from omnipipe.spill import drop_pages, dropping_pages

ANALYSIS_DROP_S = 0.02
"""Seconds between two page drops (:func:`omnipipe.spill.dropping_pages`) within
:func:`run`: a pass over every point maps its arrays' pages within a fraction of a second."""


# The analysis passes over the run's per-point arrays in the scratch (the points, their
# pipe coordinates, the defect samples) one after the other: their pages dropped often.
@dropping_pages(ANALYSIS_DROP_S)
def run(
    config: AnalysisConfig, inputs: AnalysisInputs, executor: Executor | None = None
) -> AnalysisResult:
    """Measure the pipe from its integrated rings (the stations' cylinder fits and the
    defects' model fits on ``executor``, :mod:`omnipipe.executor`; None: here; the
    result is the same).

    Raises:
        ShapeError: malformed inputs.
        ReconstructionError: too few rings to fit the pipe.
    """
    pts, frame, poses = _checked(inputs)
    # The run's scratch arrays' pages (the points just written there, among them) are
    # read back when needed, not held resident under the analysis (omnipipe.spill).
    drop_pages()
    line, whole, window = fit_axis(config, inputs, pts, frame, poses, executor)
    line, (sigma, rho, theta) = recentred_line(config, inputs, line, pts, frame, window, (), executor)
    diameter = whole.diameter_mm if whole is not None else float(2.0 * np.median(line.radius_mm))
    radius = 0.5 * diameter
    # Joint gaps and lateral openings are not wall: out of the profiles and the defects.
    feats = find_features(config.features, line, sigma, rho, theta, frame, radius, executor, axial_blur_mm=inputs.axial_blur_mm)
    breaks = offset_breaks(feats.features, line)
    if breaks:
        # The sections either side of an offset joint are fitted separately (one window's
        # cylinder across the step tilts, and the wall beside the joint reads as a ramp).
        line, whole, window = fit_axis(config, inputs, pts, frame, poses, executor, breaks)
        line, (sigma, rho, theta) = recentred_line(config, inputs, line, pts, frame, window, breaks, executor)
        feats = with_offset_joints_kept(feats, find_features(config.features, line, sigma, rho, theta, frame, radius, executor, axial_blur_mm=inputs.axial_blur_mm))
    straight = whole is not None and line.straightness_mm() <= config.straight_tolerance_mm
    stations, search = measure_wall(
        config, inputs, frame, poses, sigma, rho, theta, radius, feats.not_wall, executor,
        feature_zones(feats.features, radius, config.features.margin_mm, feats.opening_zones), feats.stray,
    )
    # Terms the fit cannot see: radial errors shared by whole rings, the ring's blur.
    radial_sys = config.systematic_radius_factor * search.noise_mm
    cal = float(inputs.calibration_sigma_rel)
    defects, unmeasured = measured_only(
        with_systematics(config, search, cal, (inputs.ring_blur_mm, inputs.axial_blur_mm))
    )
    st_list, shared = with_ring_terms(config, inputs, frame, len(poses), stations, radial_sys, diameter)
    sec_config = section_config(config)
    # The rings' axial footprints: sections they mix (taper ends, joints, tilted rings).
    measured = np.bincount(frame, minlength=len(poses))[: len(poses)] >= 12
    mixing = footprint_terms(st_list, half := footprint_mm(sigma, ring_groups(frame, len(poses)), measured))
    water_terms = (_station_reaches(inputs, stations.rings), _joint_steps(feats.features))
    st_list, wet = _water(st_list, list(stations.sections), search.noise_mm, sec_config, water_terms, half)
    st_list, shared, tilt_dir = tilt_corrected(st_list, shared, line, pts, frame, measured, radial_sys)
    st_list, features, head, tilt_warn = sections_and_headline(st_list, line, sec_config, radial_sys, shared, mixing, tilt_dir, half)
    warnings = [*search.warnings, *unmeasured, *_section_warnings(st_list, wet), *tilt_warn, *_unseen_gap_warning(feats.unseen_gap_mm)]
    water, water_sigma = run_water(st_list) if wet else (None, None)
    ovality = np.array([st.ovality for st in st_list])  # as measured (ring_tilt)
    return AnalysisResult(
        inner_diameter_mm=head.diameter_mm,
        straight=bool(straight),
        ovality_max=float(np.nanmax(ovality)) if np.isfinite(ovality).any() else float("nan"),
        stations_axial_mm=stations.axial,
        stations_diameter_mm=np.array([st.diameter_mm for st in st_list]),
        stations_ovality=ovality,
        defects=defects,
        centreline=line,
        point_sigma_mm=sigma,
        point_theta_rad=theta,
        point_deviation_mm=np.nan_to_num(stations.deviation, copy=False),
        radius_mm=float(radius),
        warnings=warnings,
        inner_diameter_sigma_mm=head.sigma_mm,
        calibration_sigma_rel=cal,
        stations_diameter_sigma_mm=np.array([st.diameter_sigma_mm for st in st_list]),
        stations_ovality_sigma=stations.ovality_sigma,
        detection_limit_mm=float(search.detection_limit_mm),
        noise_mm=float(search.noise_mm),
        ring_spacing_mm=float(search.ring_spacing_mm),
        stations=tuple(st_list),
        features=tuple(sorted((*feats.features, *features), key=lambda f: f.position_mm)),
        inner_diameter_min_mm=head.min_mm,
        inner_diameter_max_mm=head.max_mm,
        water_depth_mm=water,
        water_depth_sigma_mm=water_sigma,
        point_not_wall=feats.not_wall,
    )


def _station_reaches(inputs: AnalysisInputs, rings: np.ndarray) -> list[EdgeReach]:
    """Each station's (of ``rings``, indices into the inputs' rings) reach past its cut's
    ends: the one measured at its ring's cut (``inputs.edge_reach_rings_mm``) where there
    is one, else the median of the run's measured ones, else the run's model
    (``inputs.edge_reach_mm``)."""
    own = np.asarray(inputs.edge_reach_rings_mm, float)
    own_sig = np.asarray(inputs.edge_reach_rings_sigma_mm, float)
    ok = np.isfinite(own[: len(own_sig)]) & np.isfinite(own_sig[: len(own)])
    if ok.any():
        model = EdgeReach(float(np.median(own[ok])), float(np.median(own_sig[ok])), measured=True)
    else:
        model = EdgeReach(float(inputs.edge_reach_mm), float(inputs.edge_reach_sigma_mm))
    out = []
    for k in np.asarray(rings, int):
        if k < len(own) and k < len(own_sig) and math.isfinite(own[k]) and math.isfinite(own_sig[k]):
            out.append(EdgeReach(float(own[k]), float(own_sig[k]), measured=True))
        else:
            out.append(model)
    return out


def _water(
    st_list: list[Station],
    sections: list[Section],
    noise_mm: float,
    sec_config: SectionConfig,
    terms: tuple[list[EdgeReach], list[tuple[float, float, float]]],
    half: np.ndarray,
) -> tuple[list[Station], bool]:
    """:func:`.stations.with_water` (``terms``: reaches, joints' steps), then each wet
    station's footprint term in its depth's sigma (:func:`.footprint.water_footprint_terms`
    over ``half``, the rings' half axial extents): after the is-water test, not in it."""
    st_list, wet = with_water(st_list, sections, noise_mm, sec_config, *terms)
    return with_water_footprint(st_list, water_footprint_terms(st_list, half)), wet


def _joint_steps(features: Sequence[object]) -> list[tuple[float, float, float]]:
    """Each found joint's band (its gap and 3 sigma of its centre each side; axial mm)
    and the step its sections make at the wall (offset and gap depth in quadrature, mm):
    :func:`.stations.with_water`'s ``joints``."""
    out = []
    for f in features:
        if isinstance(f, Joint):
            half = 0.5 * f.gap_mm + 3.0 * float(f.axial_sigma_mm or 0.0)
            out.append((f.axial_mm - half, f.axial_mm + half, math.hypot(f.offset_mm or 0.0, f.depth_mm or 0.0)))
    return out


def _unseen_gap_warning(unseen_gap_mm: float) -> list[str]:
    """The warning for a stretch (mm) no laser ring sampled that could hide a joint gap."""
    if unseen_gap_mm < 3.0:
        return []
    return [
        f"the laser rings left {unseen_gap_mm:.1f} mm of the pipe unsampled between "
        "two of them: a joint gap narrower than that may lie there unseen"
    ]


def _section_warnings(stations: list[Station], wet: bool) -> list[str]:
    """What the user must know about the sections' measurement."""
    out = []
    if wet:
        n = sum(s.water_depth_mm > 0 for s in stations)
        out.append(
            f"standing water cuts the laser ring at the invert on {n} of {len(stations)} stations: "
            "their diameter and ovality rest on the wall above the water only"
        )
    low = sum(not math.isfinite(s.ovality) for s in stations)
    if low:
        out.append(f"{low} station(s) cover too little of the wall for an ovality (diameter only)")
    return out


def _checked(inputs: AnalysisInputs) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(N, 3) points, (N,) ring indices and (K, 4, 4) poses of ``inputs``, checked.

    Raises:
        ShapeError: malformed inputs.
        ReconstructionError: fewer than 12 points.
    """
    pts = np.asarray(inputs.points_in_world, float)
    frame = np.asarray(inputs.frame_index, int)
    poses = np.asarray(inputs.world_from_rig, float)
    if pts.ndim != 2 or pts.shape[1] != 3 or frame.shape != (len(pts),):
        raise ShapeError(
            f"analysis: points (N, 3) and frame_index (N,) expected, got {pts.shape} and {frame.shape}"
        )
    if poses.ndim != 3 or poses.shape[1:] != (4, 4) or (len(frame) and frame.max() >= len(poses)):
        raise ShapeError(
            f"analysis: world_from_rig must be (K, 4, 4) covering frame_index, got {poses.shape}"
        )
    if len(pts) < 12:
        raise ReconstructionError(f"only {len(pts)} laser points in total: cannot fit the pipe")
    return pts, frame, poses
