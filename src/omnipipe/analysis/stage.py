"""Analysis stage: inner diameter, ovality and defects of the measured pipe (Table I).

``run(config, inputs)`` takes the integrated ring points (world frame) and the poses
of the rings' frames and returns:

* the centreline by piecewise robust cylinder fitting (:mod:`.centreline`); the inner
  diameter is the single cylinder fitted to the whole run when the pipe is straight
  (the paper's cylinder fitting, Table I) and the median of the piecewise fits when it
  bends;
* each station re-centred on its own section (:func:`.centreline.recentred`), then per
  station (ring) a robust Fourier fit of the radius around the axis: mean diameter
  (Dmax + Dmin) / 2, ovality (Dmax - Dmin) / D and its axis, standing water from the
  ring's cut-off chord (:mod:`.stations`); the headline inner diameter is the stations'
  mean (:func:`.stations.headline`), on a reducing run that of the section most stations
  measured (:func:`.stations.headline_of_a_section`), and the section features (taper,
  bend, ovality, water) follow from the stations and the centreline (:mod:`.sections`);
* the radial deviation of every point from that wall, and the bulges and dents found
  in it (:mod:`.defects`, sized by a model fit, :mod:`.sizing`), in the data contract's
  convention (axial position along the centreline from the first frame's origin, angle
  from its x axis towards y). The rings crossing a defect are then refitted without the
  defect's samples (so a wide defect does not pull its ring's wall profile) and the
  defects measured again on the corrected deviations;
* a standard uncertainty for each number (:func:`.uncertainty.report_fields` adds the camera
  motion's scale uncertainty to everything measured along the pipe).
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from concurrent.futures import Executor
from dataclasses import dataclass, field, fields, replace

import numpy as np

from omnipipe.analysis.centreline import (
    COORDINATE_BLOCK,
    Centreline,
    fit_centreline,
    recentred,
    rig_axis_prior,
)
from omnipipe.analysis.cylinder import Cylinder, fit_cylinder
from omnipipe.analysis.defect_accept import measured_only
from omnipipe.analysis.defect_search import FeatureZone
from omnipipe.analysis.defects import DefectSearch, find_defects
from omnipipe.analysis.feature_types import Feature, Joint, Ovality, PointFeature, Stretch, Taper
from omnipipe.analysis.features import (
    FeatureConfig,
    feature_zones,
    find_features,
    with_offset_joints_kept,
)
from omnipipe.analysis.footprint import footprint_mm, footprint_terms, with_footprint_terms
from omnipipe.analysis.ring_spans import RingGroups
from omnipipe.analysis.ring_tilt import ring_tilts, tilt_check, with_tilt
from omnipipe.analysis.sections import section_features
from omnipipe.analysis.stations import (
    EdgeReach,
    Headline,
    Section,
    SectionConfig,
    Station,
    headline,
    headline_of_a_section,
    ring_cut,
    section_order,
    station_from_section,
    with_deformation,
    with_water,
)
from omnipipe.analysis.wall_profile import WallSamples, fit_wall_profile, fourier_design
from omnipipe.config import bounded
from omnipipe.contract import Defect
from omnipipe.errors import ReconstructionError, ShapeError
from omnipipe.progress import phase
from omnipipe.spill import (
    ScratchWriter,
    compressed_on_disk,
    drop_pages,
    dropping_pages,
    zeros_on_disk,
)


@dataclass(frozen=True)
class AnalysisConfig:
    """Analysis settings.

    Attributes:
        window_mm: axial length of the piecewise cylinder fits; None: a quarter of the
            pipe's diameter, at least three ring spacings (follows bends: the oblique
            rings of a bend stay round to 0.2 % at bend radius 4 D).
        straight_tolerance_mm: station centres within this of one line: a straight
            pipe, measured by one cylinder over the whole run.
        loss_scale_mm: soft-L1 scale of the robust fits (about 3 x the point noise).
        profile_order: Fourier order of each station's wall profile (2: ellipse).
        min_coverage_deg: a ring covering less of the circumference fits order 0 only.
        min_height_mm: smallest deviation reported as a defect.
        noise_factor: the defect threshold is at least this many noise sigmas.
        min_points: points beyond the threshold a defect needs.
        grid_mm: grid cell of the defects' rough measurement (the fit's start).
        limit_width_mm, limit_length_mm: the reference defect (raised cosine, half-height
            extents) whose 95 %-detection height is the run's ``detection_limit_mm``.
        fallback_scale_sigma_rel: relative 1-sigma of lengths along the pipe when the
            camera motion stage could not state it (the measured scale errors of the
            scenarios reach 0.4 % at full size and 1.1 % at 800x600: conservative).
        angle_pose_sigma_deg: 1-sigma of the angle reference along the run (rotation
            drift of the trajectory), added to each defect's angle.
        systematic_radius_factor: radial errors shared by a whole ring or run (sub-pixel
            bias of the laser peak on a blurred, sampled ring), as a fraction of the wall
            noise: added to every diameter (x 2). One run cannot observe them; the factors
            are set from ``benchmarks/bench_metrology.py`` (0.08: +-2 sigma covers 96.7 %
            of 30 runs' inner diameters and 95.3 % of their stations, seeds 100-129).
        systematic_peak_px: 1-sigma (px of image radius) of the laser peaks' sub-pixel
            bias shared by a ring's samples (a sampled, blurred or clipped stripe), times
            each station's radial pixel scale (``AnalysisInputs.radial_mm_per_px``): added
            to its diameter (x 2), and with the run's median scale to the headline and the
            taper ends. 0.03: the synthetic ring test's bound on the mean peak error
            (tests/laser/test_laser.py); on the 34 true-motion random-features captures
            the straight stations' errors read -0.012 +- 0.023 px (MAD).
        systematic_height_factor: the same for a defect's height against the wall beside
            it (the blurred ring on the defect's flanks), as a fraction of the wall noise.
        width_resolution_samples: lateral resolution of the light section in samples along
            the ring (the imaged ring is blurred over about a sample): added to widths.
        blur_sigma_rel: relative 1-sigma of the light section's blur the defect fits
            model (``ring_blur_mm``, ``axial_blur_mm``): a narrow defect's height depends
            on it (:func:`blur_height_sigma`; the quick demo's 5 mm wide bulge, true
            5 mm, read 4.71 +- 0.11 mm without it; refitted with the blur x 1.25, 5.65 mm).
        water_min_pct: a ring's cut is standing water only from this depth (percent of
            the diameter) and 3 sigma (:class:`.stations.SectionConfig`).
    """

    window_mm: float | None = bounded(None, gt=0)
    straight_tolerance_mm: float = bounded(1.0, gt=0)
    loss_scale_mm: float = bounded(0.5, gt=0)
    profile_order: int = bounded(2, ge=0)
    min_coverage_deg: float = bounded(270.0, gt=0, le=360)
    min_height_mm: float = bounded(1.0, gt=0)
    noise_factor: float = bounded(6.0, gt=0)
    min_points: int = bounded(4, ge=1)
    grid_mm: float = bounded(0.25, gt=0)
    limit_width_mm: float = bounded(10.0, gt=0)
    limit_length_mm: float = bounded(20.0, gt=0)
    fallback_scale_sigma_rel: float = bounded(0.01, ge=0)
    angle_pose_sigma_deg: float = bounded(0.3, ge=0)
    systematic_radius_factor: float = bounded(0.08, ge=0)
    systematic_peak_px: float = bounded(0.03, ge=0)
    systematic_height_factor: float = bounded(0.5, ge=0)
    width_resolution_samples: float = bounded(0.35, gt=0)
    blur_sigma_rel: float = bounded(0.3, ge=0)
    cut_min_coverage_deg: float = bounded(200.0, gt=0, le=360)
    cut_min_deg: float = bounded(8.0, ge=0, le=360)
    ovality_feature_pct: float = bounded(2.0, ge=0, le=100)
    taper_min_mm: float = bounded(2.0, ge=0)
    bend_min_curvature: float = bounded(0.2, ge=0)
    bend_min_turn_deg: float = bounded(10.0, ge=0, le=180)
    water_min_pct: float = bounded(1.0, ge=0, le=100)
    features: FeatureConfig = field(default_factory=FeatureConfig)


def section_config(config: AnalysisConfig) -> SectionConfig:
    """The section measurements' settings (:class:`.stations.SectionConfig`) of ``config``:
    every SectionConfig field that ``config`` also has, by name (the others default)."""
    shared = {f.name for f in fields(SectionConfig)} & {f.name for f in fields(config)}
    return SectionConfig(**{name: getattr(config, name) for name in shared})


@dataclass
class AnalysisInputs:
    """What the analysis measures.

    Attributes:
        points_in_world: (N, 3) ring points, mm.
        frame_index: (N,) index of each point's ring into ``world_from_rig``.
        world_from_rig: (K, 4, 4) poses of the rings' frames.
        reference_from_world: (4, 4) the frame defining the axial origin and angle 0
            (the contract: the first registered frame's rig frame); identity when the
            world is that frame.
        ring_blur_mm: Gaussian sigma (mm along the wall) of the light section's
            smoothing along the ring (the imaged stripe's blur,
            :func:`omnipipe.laser.extract.ring_blur_mm`); defect fits model it. 0: none.
        axial_blur_mm: the same along the pipe axis
            (:func:`omnipipe.laser.extract.axial_blur_mm`). 0: none.
        calibration_sigma_rel: relative 1-sigma of every length the light section
            measures, from the rig's calibration (the laser plane's distance,
            :attr:`omnipipe.rig.LaserPlane.scale_sigma_rel`); shared by all points of the
            run, so no fit can see it: added to diameters and defect sizes. 0: none stated.
        radial_mm_per_px: (K,) each ring's radial pixel scale (mm per px of image radius,
            :func:`omnipipe.laser.triangulate.radial_mm_per_px`; NaN: unknown); empty:
            not known (no pixel-scale term).
        edge_reach_mm, edge_reach_sigma_mm: how far the ring's samples run on past the
            end of a lit stretch (a water line) and one ring's 1-sigma about that
            (:func:`omnipipe.laser.extract.edge_reach_mm`); the water depth's chord
            ends are taken that far back. 0: none.
    """

    points_in_world: np.ndarray
    frame_index: np.ndarray
    world_from_rig: np.ndarray
    reference_from_world: np.ndarray = field(default_factory=lambda: np.eye(4))
    ring_blur_mm: float = 0.0
    calibration_sigma_rel: float = 0.0
    axial_blur_mm: float = 0.0
    edge_reach_mm: float = 0.0
    edge_reach_sigma_mm: float = 0.0
    radial_mm_per_px: np.ndarray = field(default_factory=lambda: np.zeros(0))


@dataclass
class AnalysisResult:
    """Measurements of the pipe.

    Attributes:
        inner_diameter_mm: the mean diameter (Dmax + Dmin) / 2, averaged over the stations
            (:func:`.stations.headline`); on a reducing run over the stations of the
            section that holds most of them (:func:`.stations.headline_of_a_section`).
        straight: True when one cylinder describes the whole run.
        ovality_max: the largest station ovality (Dmax - Dmin) / D.
        stations_axial_mm, stations_diameter_mm, stations_ovality: (K,) per ring
            (ovality corrected for the upward bias of an amplitude in noise).
        stations_diameter_sigma_mm, stations_ovality_sigma: (K,) their 1-sigma.
        inner_diameter_sigma_mm: 1-sigma of the inner diameter.
        calibration_sigma_rel: the inputs' rig-calibration share of every length (relative).
        defects: largest first, with their 1-sigma uncertainties (axial sigmas without
            the camera motion's scale: :func:`.uncertainty.report_fields` adds it).
        detection_limit_mm: height of the smallest reference defect the run detects
            with >= 95 % probability; no reported defect is lower.
        noise_mm: robust sigma of the wall's deviation map.
        ring_spacing_mm: median distance between consecutive rings along the pipe.
        centreline: the fitted axis.
        point_sigma_mm, point_theta_rad, point_deviation_mm: (N,) unrolled pipe
            coordinates and deviation of every input point (the model's unrolled view).
        radius_mm: reference radius of the unrolled view (the first fit's diameter / 2).
        warnings: human-readable notes.
        stations: each station's cross-section (:class:`.stations.Station`).
        features: the pipe's features in axial order (:mod:`.feature_types`): joints and
            laterals (:mod:`.features`), taper, bend, ovality and water (:mod:`.sections`).
        inner_diameter_min_mm, inner_diameter_max_mm: smallest Dmin and largest Dmax of
            the stations (:func:`.stations.headline`).
        water_depth_mm, water_depth_sigma_mm: median standing water over the wet
            stations and its 1-sigma (None: no water seen).
    """

    inner_diameter_mm: float
    straight: bool
    ovality_max: float
    stations_axial_mm: np.ndarray
    stations_diameter_mm: np.ndarray
    stations_ovality: np.ndarray
    defects: list[Defect]
    centreline: Centreline
    point_sigma_mm: np.ndarray
    point_theta_rad: np.ndarray
    point_deviation_mm: np.ndarray
    radius_mm: float
    warnings: list[str] = field(default_factory=list)
    calibration_sigma_rel: float = 0.0
    inner_diameter_sigma_mm: float = math.nan
    stations_diameter_sigma_mm: np.ndarray = field(default_factory=lambda: np.zeros(0))
    stations_ovality_sigma: np.ndarray = field(default_factory=lambda: np.zeros(0))
    detection_limit_mm: float = math.nan
    noise_mm: float = math.nan
    ring_spacing_mm: float = math.nan
    stations: tuple[Station, ...] = ()
    features: tuple[Feature, ...] = ()
    inner_diameter_min_mm: float = math.nan
    inner_diameter_max_mm: float = math.nan
    water_depth_mm: float | None = None
    water_depth_sigma_mm: float | None = None
    point_not_wall: np.ndarray = field(default_factory=lambda: np.zeros(0, bool))


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
    line, whole, window = _fit_axis(config, inputs, pts, frame, poses, executor)
    line, (sigma, rho, theta) = _recentred_line(config, inputs, line, pts, frame, window, ())
    diameter = whole.diameter_mm if whole is not None else float(2.0 * np.median(line.radius_mm))
    radius = 0.5 * diameter
    # Joint gaps and lateral openings are not wall: out of the profiles and the defects.
    feats = find_features(config.features, line, sigma, rho, theta, frame, radius)
    breaks = _offset_breaks(feats.features, line)
    if breaks:
        # The sections either side of an offset joint are fitted separately (one window's
        # cylinder across the step tilts, and the wall beside the joint reads as a ramp).
        line, whole, window = _fit_axis(config, inputs, pts, frame, poses, executor, breaks)
        line, (sigma, rho, theta) = _recentred_line(config, inputs, line, pts, frame, window, breaks)
        feats = with_offset_joints_kept(feats, find_features(config.features, line, sigma, rho, theta, frame, radius))
    straight = whole is not None and line.straightness_mm() <= config.straight_tolerance_mm
    stations, search = _measure_wall(
        config, inputs, frame, poses, sigma, rho, theta, radius, feats.not_wall, executor,
        feature_zones(feats.features, radius, config.features.margin_mm, feats.opening_zones), feats.stray,
    )
    # Terms the fit cannot see: radial errors shared by whole rings, the ring's blur.
    radial_sys = config.systematic_radius_factor * search.noise_mm
    cal = float(inputs.calibration_sigma_rel)
    defects, unmeasured = measured_only(
        _with_systematics(config, search, cal, (inputs.ring_blur_mm, inputs.axial_blur_mm))
    )
    st_list, shared = _with_ring_terms(config, inputs, frame, len(poses), stations, radial_sys, diameter)
    sec_config = section_config(config)
    # The rings' axial footprints: sections they mix (taper ends, joints, tilted rings).
    measured = np.bincount(frame, minlength=len(poses))[: len(poses)] >= 12
    mixing = footprint_terms(st_list, footprint_mm(sigma, ring_groups(frame, len(poses)), measured))
    reach = EdgeReach(float(inputs.edge_reach_mm), float(inputs.edge_reach_sigma_mm))
    st_list, wet = with_water(st_list, list(stations.sections), search.noise_mm, sec_config, reach)
    st_list, shared = _tilt_corrected(st_list, shared, line, pts, frame, measured, radial_sys)
    st_list, features, head = _sections_and_headline(st_list, line, sec_config, radial_sys, shared, mixing)
    warnings = [*search.warnings, *unmeasured, *_section_warnings(st_list, wet), *_unseen_gap_warning(feats.unseen_gap_mm)]
    water, water_sigma = _run_water(st_list) if wet else (None, None)
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


def _sections_and_headline(
    st_list: list[Station],
    line: Centreline,
    sec_config: SectionConfig,
    radial_sys: float,
    shared: float,
    mixing: tuple[np.ndarray, np.ndarray],
) -> tuple[list[Station], list[Stretch], Headline]:
    """The stations with their deformation and shared terms, the section features
    (taper, bend, ovality, water) and the headline diameter: the stations' mean diameter,
    or on a reducer the section most stations measured, not the ramp."""
    head = headline(st_list, shared)
    st_list = with_deformation(st_list, head)
    st_list, features = _with_shared_terms(st_list, line, head, sec_config, radial_sys, shared, mixing)
    tapers = [f for f in features if isinstance(f, Taper)]
    if tapers:
        t = tapers[0]
        head = headline_of_a_section(
            head, st_list, (t.axial_from_mm, t.axial_to_mm), (t.diameter_from_mm, t.diameter_to_mm), shared
        )
        st_list = with_deformation(st_list, head)
    return st_list, features, head


def _with_ring_terms(
    config: AnalysisConfig,
    inputs: AnalysisInputs,
    frame: np.ndarray,
    k: int,
    stations: _Stations,
    radial_sys: float,
    diameter: float,
) -> tuple[list[Station], float]:
    """The stations with the terms whole rings share in their diameter sigmas (radial
    systematics, calibration, the peaks' sub-pixel bias), and the run's shared term (mm)
    for the headline."""
    cal = float(inputs.calibration_sigma_rel)
    peak_mm = _peak_bias_mm(config, inputs, frame, k)
    run_peak = float(np.median(peak_mm)) if len(peak_mm) else 0.0
    shared = math.hypot(2.0 * radial_sys, cal * float(diameter), 2.0 * run_peak)
    st_list = [
        replace(
            st,
            diameter_sigma_mm=math.hypot(st.diameter_sigma_mm, 2.0 * radial_sys, cal * st.diameter_mm, 2.0 * pk),
        )
        for st, pk in zip(_station_list(stations), _or_zeros(peak_mm, len(stations.axial)), strict=True)
    ]
    return st_list, shared


def _tilt_corrected(
    st_list: list[Station],
    shared: float,
    line: Centreline,
    pts: np.ndarray,
    frame: np.ndarray,
    measured: np.ndarray,
    radial_sys: float,
) -> tuple[list[Station], float]:
    """The stations and the headline's shared term (mm) after :func:`.ring_tilt.tilt_check`:
    rings square to the pipe under a centreline drawn off it measured in their own
    plane; an undecided tilt's ambiguity added to the shared term."""
    rings = np.flatnonzero(measured)
    if len(rings) != len(st_list) or not len(rings):
        return st_list, shared
    tilt, direction = ring_tilts(
        pts, RingGroups(frame, rings), line.tangent[rings], line.normal[rings], line.binormal[rings]
    )
    d = np.array([st.diameter_mm for st in st_list])
    check = tilt_check(st_list, tilt, direction, 4.0 * radial_sys / max(float(np.median(d)), 1e-9))
    return with_tilt(st_list, check), math.hypot(shared, check.ambiguity_mm(d))


def _peak_bias_mm(config: AnalysisConfig, inputs: AnalysisInputs, frame: np.ndarray, k: int) -> np.ndarray:
    """(S,) each measured station's radius error (mm) from the peaks' shared sub-pixel
    bias (``config.systematic_peak_px`` x its ring's radial pixel scale; a ring of unknown
    scale takes the run's median), in the order of the stations with enough points
    (:func:`_station_profiles`); empty when the inputs state no scale."""
    scale = np.asarray(inputs.radial_mm_per_px, float)
    if len(scale) != k or not np.isfinite(scale).any():
        return np.zeros(0)
    scale = np.where(np.isfinite(scale), scale, float(np.nanmedian(scale)))
    measured = np.bincount(frame, minlength=k)[:k] >= 12
    return config.systematic_peak_px * scale[measured]


def _or_zeros(x: np.ndarray, n: int) -> np.ndarray:
    return x if len(x) == n else np.zeros(n)


def _unseen_gap_warning(unseen_gap_mm: float) -> list[str]:
    """The warning for a stretch (mm) no laser ring sampled that could hide a joint gap."""
    if unseen_gap_mm < 3.0:
        return []
    return [
        f"the laser rings left {unseen_gap_mm:.1f} mm of the pipe unsampled between "
        "two of them: a joint gap narrower than that may lie there unseen"
    ]


def _with_shared_terms(
    st_list: list[Station],
    line: Centreline,
    head: Headline,
    sec_config: SectionConfig,
    radial_sys: float,
    shared_diameter_mm: float,
    mixing: tuple[np.ndarray, np.ndarray],
) -> tuple[list[Station], list[Stretch]]:
    """The stations and section features (ovality, tapers, ...) with the terms averaging
    the stations cannot remove: a ring-shape error shared by the run (``radial_sys`` mm
    in cos 2 theta) moves every station's ovality alike, by up to 4 radial_sys / D; the
    diameter's shared part (``shared_diameter_mm``: the systematic ring radius, the
    peaks' sub-pixel bias, the rig calibration; as in the headline's sigma) moves both
    ends of a taper with every station, as it moves the headline; the sections each ring
    mixes (``mixing``: :func:`.footprint.footprint_terms`, (S,) diameter mm and ovality
    per station) move neighbouring stations alike, so a taper end or an ovality stretch
    takes its stations' median of them whole. The features are found on the stations
    without the mixing terms (a taper's own ramp is no noise), which are then added."""
    oval_sys = 4.0 * radial_sys / max(head.diameter_mm, 1e-9)
    st_list = [replace(st, ovality_sigma=math.hypot(st.ovality_sigma, oval_sys)) for st in st_list]
    axial = np.array([st.axial_mm for st in st_list])
    d_mix, o_mix = mixing

    def median_over(term: np.ndarray, sel: np.ndarray) -> float:
        return float(np.median(term[sel])) if sel.any() else 0.0

    features: list[Stretch] = []
    for f in section_features(st_list, line, head, sec_config, d_mix):
        if isinstance(f, Ovality) and f.percent_sigma is not None:
            inside = (axial >= f.axial_from_mm) & (axial <= f.axial_to_mm)
            mix = 100.0 * median_over(o_mix, inside)
            f = replace(f, percent_sigma=math.hypot(f.percent_sigma, 100.0 * oval_sys, mix))
        elif isinstance(f, Taper):
            start, end = median_over(d_mix, axial <= f.axial_from_mm), median_over(d_mix, axial >= f.axial_to_mm)
            f = replace(
                f,
                diameter_from_sigma_mm=_hypot_or_none(f.diameter_from_sigma_mm, shared_diameter_mm, start),
                diameter_to_sigma_mm=_hypot_or_none(f.diameter_to_sigma_mm, shared_diameter_mm, end),
            )
        features.append(f)
    return with_footprint_terms(st_list, d_mix, o_mix), features


def _hypot_or_none(sigma: float | None, *terms: float) -> float | None:
    return None if sigma is None else math.hypot(sigma, *terms)


def _station_list(stations: _Stations) -> list[Station]:
    return [
        station_from_section(a, sec, 0.0, 0.0)
        for a, sec in zip(stations.axial, stations.sections, strict=True)
    ]


def _run_water(stations: list[Station]) -> tuple[float, float]:
    """Median water depth over the wet stations and its 1-sigma (mm): the independent
    part / sqrt(n), the part all stations share whole."""
    wet = [s for s in stations if s.water_depth_mm > 0]
    depth = np.array([s.water_depth_mm for s in wet])
    shared = float(np.median([s.water_depth_shared_sigma_mm for s in wet]))
    sig = np.sqrt(np.maximum(np.array([s.water_depth_sigma_mm for s in wet]) ** 2 - shared**2, 0.0))
    spread = float(np.std(depth)) if len(depth) > 2 else 0.0
    stat = 1.2533 * max(spread, float(np.median(sig))) / math.sqrt(len(depth))
    return float(np.median(depth)), math.hypot(stat, shared)


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


def _recentred_line(
    config: AnalysisConfig,
    inputs: AnalysisInputs,
    line: Centreline,
    pts: np.ndarray,
    frame: np.ndarray,
    window: float,
    breaks: Sequence[tuple[np.ndarray, np.ndarray]],
) -> tuple[Centreline, tuple[np.ndarray, np.ndarray, np.ndarray]]:
    """The centreline re-centred on each station's own section, and the points' (N,)
    pipe coordinates (sigma, rho, theta) about it."""
    centres = _section_centres(config, line, pts, frame)
    prior = rig_axis_prior(np.asarray(inputs.world_from_rig, float)[: len(line.arc_mm)], line.centre)
    line = recentred(line, centres, inputs.reference_from_world, 0.5 * window, breaks, axis_prior=prior)
    # The coordinates wait in the run's scratch, read when needed (24 bytes a point),
    # written there a block at a time (each point's numbers those of the whole run's).
    out = [ScratchWriter(len(frame), float) for _ in range(3)]
    for a in range(0, len(frame), COORDINATE_BLOCK):
        for w, part in zip(out, line.coordinates(pts[a : a + COORDINATE_BLOCK], frame[a : a + COORDINATE_BLOCK]), strict=True):
            w.write(part)
    sigma, rho, theta = (w.array() for w in out)
    drop_pages()  # the points' pages, read again when needed (omnipipe.spill)
    return line, (sigma, rho, theta)


def _offset_breaks(features: Sequence[PointFeature], line: Centreline) -> list[tuple[np.ndarray, np.ndarray]]:
    """(point, normal) world planes at the joints whose offset is significant (>= 0.5 mm
    and 3 sigma): the sections either side are fitted separately."""
    out = []
    for f in features:
        if not isinstance(f, Joint) or f.offset_mm is None:
            continue
        if f.offset_mm < max(0.5, 3.0 * (f.offset_sigma_mm or 0.0)):
            continue
        k = int(np.argmin(np.abs(line.arc_mm - f.axial_mm)))
        t = line.tangent[k]
        out.append((line.centre[k] + (f.axial_mm - line.arc_mm[k]) * t, t))
    return out


def _fit_axis(
    config: AnalysisConfig,
    inputs: AnalysisInputs,
    pts: np.ndarray,
    frame: np.ndarray,
    poses: np.ndarray,
    executor: Executor | None,
    breaks: Sequence[tuple[np.ndarray, np.ndarray]] = (),
) -> tuple[Centreline, Cylinder | None, float]:
    """The piecewise centreline (no window across a break plane: :func:`.fit_centreline`),
    the single cylinder of the whole run when the centreline is straight (None: it
    bends) and the window of the piecewise fits (mm)."""
    rings = _RingPoints(pts, ring_groups(frame, len(poses)))
    axis_guess = poses[:, :3, 2]
    # A first whole-run fit gives the scale for the window.
    sample = pts[np.linspace(0, len(pts) - 1, min(len(pts), 6000)).astype(int)]
    rough = fit_cylinder(sample, np.mean(axis_guess, axis=0), loss_scale_mm=config.loss_scale_mm)
    if config.window_mm:
        window = config.window_mm
    else:
        # A quarter diameter follows bends (a chord's sagitta there is L^2 / 8 R_bend), but
        # never fewer than about three rings.
        cents = np.array([r.mean(axis=0) for r in rings if len(r) >= 12])
        spacing = float(np.median(np.linalg.norm(np.diff(cents, axis=0), axis=1))) if len(cents) > 1 else 0.0
        window = max(0.25 * rough.diameter_mm, 3.0 * spacing)
    line = fit_centreline(
        rings,
        axis_guess,
        inputs.reference_from_world,
        window_mm=window,
        loss_scale_mm=config.loss_scale_mm,
        executor=executor,
        breaks=breaks,
    )
    if line.straightness_mm() > config.straight_tolerance_mm:
        return line, None, window
    whole = fit_cylinder(
        pts[np.linspace(0, len(pts) - 1, min(len(pts), 20000)).astype(int)],
        rough.axis,
        loss_scale_mm=config.loss_scale_mm,
    )
    return line, whole, window


class _RingPoints(Sequence[np.ndarray]):
    """Each ring's (M_k, 3) points of the run's (N, 3) ``pts``, gathered when indexed
    (the same arrays as ``[pts[g] for g in groups]``, not held: a copy of every point)."""

    def __init__(self, pts: np.ndarray, groups: list[np.ndarray]) -> None:
        self.pts, self.groups = pts, groups

    def __len__(self) -> int:
        return len(self.groups)

    def __getitem__(self, k: int) -> np.ndarray:  # type: ignore[override]
        return self.pts[self.groups[k]]


def _section_centres(config: AnalysisConfig, line: Centreline, pts: np.ndarray, frame: np.ndarray) -> np.ndarray:
    """(K, 2) each ring's section centre in its station's (normal, binormal) plane of
    ``line``: the order-1 terms of its wall profile (0 for a ring too sparse to fit).
    Each ring's coordinates are taken on their own (the same numbers as the whole run's):
    no (N,) array is held."""
    k = len(line.arc_mm)
    out = np.zeros((k, 2))
    sec_config = section_config(config)
    for i, on in enumerate(ring_groups(frame, k)):
        if len(on) < 12:
            continue
        _, rho, theta = line.coordinates(pts[on], frame[on])
        cut, coverage = ring_cut(theta, sec_config)
        order = section_order(cut, coverage, config.profile_order, sec_config)
        if order >= 1:
            coef = fit_wall_profile(theta, rho, order, config.loss_scale_mm)
            out[i] = coef[1:3]
    return out


def _measure_wall(
    config: AnalysisConfig,
    inputs: AnalysisInputs,
    frame: np.ndarray,
    poses: np.ndarray,
    sigma: np.ndarray,
    rho: np.ndarray,
    theta: np.ndarray,
    radius: float,
    not_wall: np.ndarray,
    executor: Executor | None = None,
    zones: Sequence[FeatureZone] = (),
    stray: np.ndarray | None = None,
) -> tuple[_Stations, DefectSearch]:
    """The stations' wall profiles and the defects in the deviations from them.

    Pass 1 fits the profiles to all points; pass 2 without the samples of the defects
    found (so a wide defect does not pull its ring's wall profile), and so on until the
    excluded samples stop changing (at most two passes).
    """
    ok_station = np.bincount(frame, minlength=len(poses))[: len(poses)] >= 12
    circ = 2 * np.pi * radius
    exclude = not_wall.copy()
    # The robot's travel from the first frame to each ring's frame (path along the poses).
    steps = np.linalg.norm(np.diff(poses[:, :3, 3], axis=0), axis=1)
    travel = np.concatenate([[0.0], np.cumsum(steps)])
    tick = phase("defects", 2)
    for done in range(1, 3):
        # Each ring's indices made per pass: not held under the defect search (8 bytes a point).
        groups = ring_groups(frame, len(poses))
        stations = _station_profiles(config, groups, theta, rho, sigma, ok_station, exclude, zones, radius, stray)
        del groups
        ok = np.isfinite(stations.deviation) & ~not_wall
        # In the run's scratch, gathered a block at a time (read when needed; a local
        # pool's workers share the files).
        samples = WallSamples(
            sigma_mm=compressed_on_disk(sigma, ok),
            arc_mm=compressed_on_disk(theta, ok, lambda t: _arcs(t, radius)),
            deviation_mm=compressed_on_disk(stations.deviation, ok),
            ring=compressed_on_disk(frame, ok),
            circumference_mm=circ,
            ring_travel_mm=travel,
        )
        search = find_defects(
            samples,
            min_height_mm=config.min_height_mm,
            noise_factor=config.noise_factor,
            min_points=config.min_points,
            grid_mm=config.grid_mm,
            limit_width_mm=config.limit_width_mm,
            limit_length_mm=config.limit_length_mm,
            ring_blur_mm=inputs.ring_blur_mm,
            axial_blur_mm=inputs.axial_blur_mm,
            zones=zones,
            executor=executor,
        )
        del samples  # the next pass' samples are built without these
        drop_pages()  # their copies the workers read
        tick(done)
        if not search.defects:
            break
        cover = np.zeros(int(ok.sum()), bool)
        for m in search.masks or []:
            cover[m] = True
        new_exclude = not_wall.copy()
        new_exclude[np.flatnonzero(ok)[cover]] = True
        if np.array_equal(new_exclude, exclude):
            break
        exclude = new_exclude
        if done < 2:  # the next pass' profiles replace these: not held both at once
            del stations, search, cover, new_exclude
    tick(2)
    return stations, search


def _arcs(theta: np.ndarray, radius: float) -> np.ndarray:
    """``theta`` (rad) made arcs in place: (theta % 2 pi) x ``radius`` (mm)."""
    np.remainder(theta, 2 * np.pi, out=theta)
    theta *= radius
    return theta


def blur_height_sigma(height: float, width: float, length: float, blur: tuple[float, float], rel: float) -> float:
    """1-sigma of a defect's height from a relative error ``rel`` of the light section's
    blur (Gaussian sigmas mm along the ring and the axis) its fit modelled.

    The fit keeps the blurred bump's area: taking the bump as a Gaussian of variance
    s^2 = (W / 2.355)^2 (W its fitted half-height extent), seen with variance s^2 + b^2,
    a relative error r of b moves the height by h (b / s)^2 r (per direction, in
    quadrature). Wide defects: nil. The quick demo's 5 mm wide bulge under a 1.2 mm blur:
    0.32 h r; refitted with the blur x 1.25 its height rose 0.94 mm (4.71 -> 5.65), so
    this is, if anything, low."""
    out = 0.0
    for extent, b in ((width, blur[0]), (length, blur[1])):
        if b > 0 and extent > 0:
            out = math.hypot(out, height * (2.355 * b / extent) ** 2 * rel)
    return out


def _with_systematics(
    config: AnalysisConfig, search: DefectSearch, cal: float, blur: tuple[float, float] = (0.0, 0.0)
) -> list[Defect]:
    """The found defects with the terms their fit cannot see added to height and width:
    the blurred ring on the defect's flanks, the blur's own uncertainty
    (:func:`blur_height_sigma`), the ring's lateral resolution and the rig calibration's
    share ``cal`` (relative; the lengths along the pipe get it in
    :func:`.uncertainty.report_fields`, with the motion's scale)."""
    width_res = config.width_resolution_samples * search.sample_spacing_mm
    out = []
    for d in search.defects:
        if d.height_sigma_mm is not None and d.width_sigma_mm is not None:
            d = replace(
                d,
                height_sigma_mm=round(
                    math.hypot(
                        d.height_sigma_mm,
                        config.systematic_height_factor * search.noise_mm,
                        blur_height_sigma(d.height_mm, d.width_mm, d.length_mm, blur, config.blur_sigma_rel),
                    ),
                    4,
                ),
                width_sigma_mm=round(math.hypot(d.width_sigma_mm, width_res), 4),
            )
        if cal > 0 and d.height_sigma_mm is not None and d.width_sigma_mm is not None:
            d = replace(
                d,
                height_sigma_mm=round(math.hypot(d.height_sigma_mm, cal * d.height_mm), 4),
                width_sigma_mm=round(math.hypot(d.width_sigma_mm, cal * d.width_mm), 4),
            )
        out.append(d)
    return out


@dataclass(frozen=True)
class _Stations:
    """Each station's wall profile (:func:`_station_profiles`).

    Attributes:
        axial, diameter, diameter_sigma, ovality, ovality_sigma: (K,) per station with
            enough points (mm; ovality a fraction, NaN below the profile order 2).
        deviation: (N,) every point's deviation from its station's profile (mm; NaN on
            stations without enough points).
    """

    axial: np.ndarray
    diameter: np.ndarray
    diameter_sigma: np.ndarray
    ovality: np.ndarray
    ovality_sigma: np.ndarray
    deviation: np.ndarray
    sections: tuple[Section, ...] = ()


def _with_openings(theta: np.ndarray, axial: float, zones: Sequence[FeatureZone], radius: float) -> np.ndarray:
    """A ring's angles (rad) with the lateral openings it crosses filled in (at 0.5 deg
    steps): where the ring lost its light in a branch it is not cut by water."""
    fill = [theta]
    for z in zones:
        if z.arc_mm is not None and z.axial_from_mm <= axial <= z.axial_to_mm:
            c, h = z.arc_mm / radius, z.half_arc_mm / radius
            fill.append(np.linspace(c - h, c + h, max(int(np.degrees(2 * h) / 0.5), 2)))
    return np.concatenate(fill) if len(fill) > 1 else theta


def ring_groups(frame: np.ndarray, n_rings: int) -> Sequence[np.ndarray]:
    """(n_rings,) the indices of each ring's points, ascending (``frame == k`` for every k,
    each made when indexed: :class:`.ring_spans.RingGroups`, a binary search of the
    integrated run's ring-ordered ``frame`` or one stable sort of any other; no index of
    every point held)."""
    return RingGroups(frame, np.arange(n_rings))


def _station_profiles(
    config: AnalysisConfig,
    groups: list[np.ndarray],
    theta: np.ndarray,
    rho: np.ndarray,
    sigma: np.ndarray,
    ok_station: np.ndarray,
    exclude: np.ndarray,
    zones: Sequence[FeatureZone] = (),
    radius: float = 1.0,
    stray: np.ndarray | None = None,
) -> _Stations:
    """Each station's wall profile (fitted without the ``exclude`` points) and every
    point's deviation from it.

    The diameter's sigma is the fit's (A^T A)^-1 scaled by the ring's robust residual
    spread. A ring cut off by water (one gap) keeps the order while the wall above it
    covers ``cut_min_coverage_deg`` (:func:`.stations.section_order`). Ovality is
    2 |(a2, b2)| / c0, bias-corrected (:func:`.stations.station_from_section`).
    A lateral's opening (``zones`` with an arc, on the ``radius`` mm wall) is no cut:
    the light lost in the branch is not a water line; ``stray`` samples (off the wall
    in a cut: :attr:`.features.FeatureSearch.stray`) do not close a cut.
    """
    deviation = zeros_on_disk((len(exclude),), float)  # in the run's scratch (omnipipe.spill)
    deviation.fill(np.nan)
    sec_config = section_config(config)
    axial, sections = [], []
    for k in np.flatnonzero(ok_station):
        on = groups[k]
        use = on[~exclude[on]]
        if len(use) < 12:
            use = on
        th = theta[use]
        # The cut (water) is where the ring has no points at all; the coverage for the
        # order is that of the points fitted (a defect's samples left out open a gap).
        lit = on if stray is None or not len(stray) else on[~stray[on]]
        cut, coverage = ring_cut(_with_openings(theta[lit], float(np.median(sigma[on])), zones, radius), sec_config)
        _, fitted_coverage = ring_cut(th, sec_config)
        order = section_order(cut, min(coverage, fitted_coverage), config.profile_order, sec_config)
        coef = fit_wall_profile(th, rho[use], order, config.loss_scale_mm)
        A = fourier_design(th, order)
        res = rho[use] - A @ coef
        spread = 1.4826 * float(np.median(np.abs(res)))
        inlier = np.abs(res) <= 4.0 * max(spread, 1e-6)
        cov = np.linalg.pinv(A[inlier].T @ A[inlier]) * spread**2
        deviation[on] = rho[on] - fourier_design(theta[on], order) @ coef
        axial.append(float(np.median(sigma[on])))
        sections.append(Section(coef, cov, order, cut, coverage))
    stations = [station_from_section(a, sec, 0.0, 0.0) for a, sec in zip(axial, sections, strict=True)]
    return _Stations(
        axial=np.array([st.axial_mm for st in stations]),
        diameter=np.array([st.diameter_mm for st in stations]),
        diameter_sigma=np.array([st.diameter_sigma_mm for st in stations]),
        ovality=np.array([st.ovality for st in stations]),
        ovality_sigma=np.array([st.ovality_sigma for st in stations]),
        deviation=deviation,
        sections=tuple(sections),
    )
