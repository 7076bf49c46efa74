"""Analysis stage: inner diameter, ovality and defects of the measured pipe (Table I).

``run(config, inputs)`` takes the integrated ring points (world frame) and the poses
of the rings' frames and returns:

* the centreline by piecewise robust cylinder fitting (:mod:`.centreline`); the inner
  diameter is the single cylinder fitted to the whole run when the pipe is straight
  (the paper's cylinder fitting, Table I) and the median of the piecewise fits when it
  bends;
* per station (ring) a robust Fourier fit of the radius around the axis: station
  diameter and ovality (Dmax - Dmin) / D;
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
from concurrent.futures import Executor
from dataclasses import dataclass, field, replace

import numpy as np

from omnipipe.analysis.centreline import Centreline, fit_centreline
from omnipipe.analysis.cylinder import Cylinder, fit_cylinder
from omnipipe.analysis.defects import (
    DefectSearch,
    WallSamples,
    find_defects,
    fit_wall_profile,
    fourier_design,
)
from omnipipe.analysis.feature_types import Feature
from omnipipe.analysis.features import FeatureConfig, find_features
from omnipipe.contract import Defect
from omnipipe.errors import ReconstructionError, ShapeError
from omnipipe.progress import phase


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
        systematic_height_factor: the same for a defect's height against the wall beside
            it (the blurred ring on the defect's flanks), as a fraction of the wall noise.
        width_resolution_samples: lateral resolution of the light section in samples along
            the ring (the imaged ring is blurred over about a sample): added to widths.
    """

    window_mm: float | None = None
    straight_tolerance_mm: float = 1.0
    loss_scale_mm: float = 0.5
    profile_order: int = 2
    min_coverage_deg: float = 270.0
    min_height_mm: float = 1.0
    noise_factor: float = 6.0
    min_points: int = 4
    grid_mm: float = 0.25
    limit_width_mm: float = 10.0
    limit_length_mm: float = 20.0
    fallback_scale_sigma_rel: float = 0.01
    angle_pose_sigma_deg: float = 0.3
    systematic_radius_factor: float = 0.08
    systematic_height_factor: float = 0.5
    width_resolution_samples: float = 0.35
    features: FeatureConfig = field(default_factory=FeatureConfig)


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
    """

    points_in_world: np.ndarray
    frame_index: np.ndarray
    world_from_rig: np.ndarray
    reference_from_world: np.ndarray = field(default_factory=lambda: np.eye(4))
    ring_blur_mm: float = 0.0
    calibration_sigma_rel: float = 0.0
    axial_blur_mm: float = 0.0


@dataclass
class AnalysisResult:
    """Measurements of the pipe.

    Attributes:
        inner_diameter_mm: the fitted inner diameter.
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
        radius_mm: reference radius of the unrolled view (inner diameter / 2).
        warnings: human-readable notes.
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
    features: list[Feature] = field(default_factory=list)
    point_not_wall: np.ndarray = field(default_factory=lambda: np.zeros(0, bool))


def run(
    config: AnalysisConfig, inputs: AnalysisInputs, executor: Executor | None = None
) -> AnalysisResult:
    """Measure the pipe from its integrated rings (the stations' cylinder fits on
    ``executor``, :mod:`omnipipe.executor`; None: here; the result is the same).

    Raises:
        ShapeError: malformed inputs.
        ReconstructionError: too few rings to fit the pipe.
    """
    pts, frame, poses = _checked(inputs)
    line, whole = _fit_axis(config, inputs, pts, frame, poses, executor)
    straight = whole is not None
    diameter = whole.diameter_mm if whole is not None else float(2.0 * np.median(line.radius_mm))
    sigma, rho, theta = line.coordinates(pts, frame)
    radius = 0.5 * diameter
    # Joint gaps and lateral openings are not wall: out of the profiles and the defects.
    feats = find_features(config.features, line, sigma, rho, theta, frame, radius)
    stations, search = _measure_wall(
        config, inputs, frame, poses, sigma, rho, theta, radius, feats.not_wall
    )
    # Terms the fit cannot see: radial errors shared by whole rings, the ring's blur.
    radial_sys = config.systematic_radius_factor * search.noise_mm
    cal = float(inputs.calibration_sigma_rel)
    defects = _with_systematics(config, search, cal)
    st_diam = stations.diameter
    if whole is not None:
        # The single cylinder: its statistical spread, and the stations' scatter (errors
        # shared by the points of one ring: the ring's pose, its laser frame).
        n_pts = min(len(pts), 20000)
        stat = 2.0 * whole.scale_mm / math.sqrt(max(n_pts, 1))
        between = float(np.std(st_diam)) / math.sqrt(max(len(st_diam), 1))
        diameter_sigma = math.hypot(stat, between)
    else:
        # The median of the piecewise fits: 1.25 x the standard error of a mean.
        radii = 2.0 * np.asarray(line.radius_mm)
        diameter_sigma = 1.2533 * float(np.std(radii)) / math.sqrt(max(len(radii), 1))
    diameter_sigma = math.hypot(diameter_sigma, 2.0 * radial_sys)
    st_dsig = np.hypot(stations.diameter_sigma, 2.0 * radial_sys)
    if cal > 0:
        # The rig's calibration scales every measured length alike (the lengths along the
        # pipe too: report_fields).
        diameter_sigma = math.hypot(diameter_sigma, cal * float(diameter))
        st_dsig = np.hypot(st_dsig, cal * np.abs(st_diam))
    finite = stations.ovality[np.isfinite(stations.ovality)]
    return AnalysisResult(
        inner_diameter_mm=float(diameter),
        straight=bool(straight),
        ovality_max=float(finite.max()) if len(finite) else float("nan"),
        stations_axial_mm=stations.axial,
        stations_diameter_mm=st_diam,
        stations_ovality=stations.ovality,
        defects=defects,
        centreline=line,
        point_sigma_mm=sigma,
        point_theta_rad=theta,
        point_deviation_mm=np.nan_to_num(stations.deviation),
        radius_mm=float(radius),
        warnings=list(search.warnings),
        inner_diameter_sigma_mm=float(diameter_sigma),
        calibration_sigma_rel=cal,
        stations_diameter_sigma_mm=st_dsig,
        stations_ovality_sigma=stations.ovality_sigma,
        detection_limit_mm=float(search.detection_limit_mm),
        noise_mm=float(search.noise_mm),
        ring_spacing_mm=float(search.ring_spacing_mm),
        features=feats.features,
        point_not_wall=feats.not_wall,
    )


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


def _fit_axis(
    config: AnalysisConfig,
    inputs: AnalysisInputs,
    pts: np.ndarray,
    frame: np.ndarray,
    poses: np.ndarray,
    executor: Executor | None,
) -> tuple[Centreline, Cylinder | None]:
    """The piecewise centreline, and the single cylinder of the whole run when the
    centreline is straight (None: it bends)."""
    rings = [pts[frame == k] for k in range(len(poses))]
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
    )
    if line.straightness_mm() > config.straight_tolerance_mm:
        return line, None
    whole = fit_cylinder(
        pts[np.linspace(0, len(pts) - 1, min(len(pts), 20000)).astype(int)],
        rough.axis,
        loss_scale_mm=config.loss_scale_mm,
    )
    return line, whole


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
) -> tuple[_Stations, DefectSearch]:
    """The stations' wall profiles and the defects in the deviations from them.

    Pass 1 fits the profiles to all points; pass 2 without the samples of the defects
    found (so a wide defect does not pull its ring's wall profile), and so on until the
    excluded samples stop changing (at most two passes).
    """
    ok_station = np.array([(frame == k).sum() >= 12 for k in range(len(poses))])
    circ = 2 * np.pi * radius
    exclude = not_wall.copy()
    # The robot's travel from the first frame to each ring's frame (path along the poses).
    steps = np.linalg.norm(np.diff(poses[:, :3, 3], axis=0), axis=1)
    travel = np.concatenate([[0.0], np.cumsum(steps)])
    tick = phase("defects", 2)
    for done in range(1, 3):
        stations = _station_profiles(config, frame, theta, rho, sigma, ok_station, exclude)
        ok = np.isfinite(stations.deviation) & ~not_wall
        samples = WallSamples(
            sigma_mm=sigma[ok],
            arc_mm=(theta[ok] % (2 * np.pi)) * radius,
            deviation_mm=stations.deviation[ok],
            ring=frame[ok],
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
        )
        tick(done)
        if not search.defects:
            break
        cover = np.zeros(int(ok.sum()), bool)
        for m in search.masks or []:
            cover |= m
        new_exclude = not_wall.copy()
        new_exclude[np.flatnonzero(ok)[cover]] = True
        if np.array_equal(new_exclude, exclude):
            break
        exclude = new_exclude
    tick(2)
    return stations, search


def _with_systematics(config: AnalysisConfig, search: DefectSearch, cal: float) -> list[Defect]:
    """The found defects with the terms their fit cannot see added to height and width:
    the blurred ring on the defect's flanks, the ring's lateral resolution and the rig
    calibration's share ``cal`` (relative; the lengths along the pipe get it in
    :func:`.uncertainty.report_fields`, with the motion's scale)."""
    width_res = config.width_resolution_samples * search.sample_spacing_mm
    out = []
    for d in search.defects:
        if d.height_sigma_mm is not None and d.width_sigma_mm is not None:
            d = replace(
                d,
                height_sigma_mm=round(
                    math.hypot(d.height_sigma_mm, config.systematic_height_factor * search.noise_mm), 4
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


def _station_profiles(
    config: AnalysisConfig,
    frame: np.ndarray,
    theta: np.ndarray,
    rho: np.ndarray,
    sigma: np.ndarray,
    ok_station: np.ndarray,
    exclude: np.ndarray,
) -> _Stations:
    """Each station's wall profile (fitted without the ``exclude`` points) and every
    point's deviation from it.

    The diameter's sigma is the fit's (A^T A)^-1 scaled by the ring's robust residual
    spread. Ovality is 2 |(a2, b2)| / c0; the amplitude of a pair of noisy coefficients is
    biased upward (E|a|^2 = |a_true|^2 + 2 var), so |a|^2 - 2 var is used (0 when negative).
    """
    deviation = np.full(len(frame), np.nan)
    out: dict[str, list[float]] = {
        k: [] for k in ("axial", "diameter", "diameter_sigma", "ovality", "ovality_sigma")
    }
    for k in np.flatnonzero(ok_station):
        on = frame == k
        use = on & ~exclude
        if use.sum() < 12:
            use = on
        th = theta[use]
        coverage = 360.0 - np.degrees(
            np.max(np.diff(np.sort(np.concatenate([th, [th.min() + 2 * np.pi]]))))
        )
        order = config.profile_order if coverage >= config.min_coverage_deg else 0
        coef = fit_wall_profile(th, rho[use], order, config.loss_scale_mm)
        A = fourier_design(th, order)
        res = rho[use] - A @ coef
        spread = 1.4826 * float(np.median(np.abs(res)))
        inlier = np.abs(res) <= 4.0 * max(spread, 1e-6)
        cov = np.linalg.pinv(A[inlier].T @ A[inlier]) * spread**2
        deviation[on] = rho[on] - fourier_design(theta[on], order) @ coef
        out["axial"].append(float(np.median(sigma[on])))
        out["diameter"].append(2.0 * coef[0])
        out["diameter_sigma"].append(2.0 * math.sqrt(max(cov[0, 0], 0.0)))
        if order >= 2:
            var2 = 0.5 * (cov[3, 3] + cov[4, 4])
            amp2 = coef[3] ** 2 + coef[4] ** 2 - 2.0 * var2
            out["ovality"].append(2.0 * math.sqrt(max(amp2, 0.0)) / coef[0])
            out["ovality_sigma"].append(2.0 * math.sqrt(var2) / coef[0])
        else:
            out["ovality"].append(math.nan)
            out["ovality_sigma"].append(math.nan)
    return _Stations(
        axial=np.array(out["axial"]),
        diameter=np.array(out["diameter"]),
        diameter_sigma=np.array(out["diameter_sigma"]),
        ovality=np.array(out["ovality"]),
        ovality_sigma=np.array(out["ovality_sigma"]),
        deviation=deviation,
    )
