"""The analysis stage's typed records: its settings (:class:`AnalysisConfig`, and
:func:`section_config`, the part the section measurements read), what it measures
(:class:`AnalysisInputs`: world-frame ring points, mm, and the rings' poses) and what it
returns (:class:`AnalysisResult`). The stage itself is :func:`.stage.run`.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field, fields

import numpy as np

from omnipipe.analysis.centreline import Centreline
from omnipipe.analysis.feature_types import Feature
from omnipipe.analysis.features import FeatureConfig
from omnipipe.analysis.stations import SectionConfig, Station
from omnipipe.config import bounded
from omnipipe.contract import Defect


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
            on it (:func:`.wall_measure.blur_height_sigma`; the quick demo's 5 mm wide bulge, true
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
        edge_reach_rings_mm, edge_reach_rings_sigma_mm: (K,) the same measured at each
            ring's own cut (the stripe's half-height point at both ends,
            :func:`omnipipe.laser.extract.station_edge_reach`) and its 1-sigma; NaN (or
            empty: none measured) where a ring's takes the run's above.
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
    edge_reach_rings_mm: np.ndarray = field(default_factory=lambda: np.zeros(0))
    edge_reach_rings_sigma_mm: np.ndarray = field(default_factory=lambda: np.zeros(0))


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
