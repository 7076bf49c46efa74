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
  in it (:mod:`.defects`), in the data contract's convention (axial position along
  the centreline from the first frame's origin, angle from its x axis towards y).
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from omnipipe.analysis.centreline import Centreline, fit_centreline
from omnipipe.analysis.cylinder import Cylinder, fit_cylinder
from omnipipe.analysis.defects import WallSamples, find_defects, fit_wall_profile, fourier_design
from omnipipe.errors import ReconstructionError, ShapeError

__all__ = ["AnalysisConfig", "AnalysisInputs", "AnalysisResult", "Cylinder", "fit_cylinder", "run"]


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
        grid_mm: measurement grid cell of the defects.
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
    """

    points_in_world: np.ndarray
    frame_index: np.ndarray
    world_from_rig: np.ndarray
    reference_from_world: np.ndarray = field(default_factory=lambda: np.eye(4))


@dataclass
class AnalysisResult:
    """Measurements of the pipe.

    Attributes:
        inner_diameter_mm: the fitted inner diameter.
        straight: True when one cylinder describes the whole run.
        ovality_max: the largest station ovality (Dmax - Dmin) / D.
        stations_axial_mm, stations_diameter_mm, stations_ovality: (K,) per ring.
        defects: contract dicts, largest first.
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
    defects: list[dict]
    centreline: Centreline
    point_sigma_mm: np.ndarray
    point_theta_rad: np.ndarray
    point_deviation_mm: np.ndarray
    radius_mm: float
    warnings: list[str] = field(default_factory=list)


def run(config: AnalysisConfig, inputs: AnalysisInputs) -> AnalysisResult:
    """Measure the pipe from its integrated rings.

    Raises:
        ShapeError: malformed inputs.
        ReconstructionError: too few rings to fit the pipe.
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
    warnings: list[str] = []
    rings = [pts[frame == k] for k in range(len(poses))]
    axis_guess = poses[:, :3, 2]
    # A first whole-run fit gives the scale for the window.
    sample = pts[np.linspace(0, len(pts) - 1, min(len(pts), 6000)).astype(int)] if len(pts) else pts
    if len(sample) < 12:
        raise ReconstructionError(f"only {len(pts)} laser points in total: cannot fit the pipe")
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
    )
    straight = line.straightness_mm() <= config.straight_tolerance_mm
    if straight:
        whole = fit_cylinder(
            pts[np.linspace(0, len(pts) - 1, min(len(pts), 20000)).astype(int)],
            rough.axis,
            loss_scale_mm=config.loss_scale_mm,
        )
        diameter = whole.diameter_mm
    else:
        diameter = float(2.0 * np.median(line.radius_mm))
    sigma, rho, theta = line.coordinates(pts, frame)

    # Per station: the wall profile, its diameter and ovality, and each point's deviation.
    deviation = np.full(len(pts), np.nan)
    st_axial, st_diam, st_oval = [], [], []
    for k in range(len(poses)):
        on = frame == k
        if on.sum() < 12:
            continue
        th = theta[on]
        coverage = 360.0 - np.degrees(
            np.max(np.diff(np.sort(np.concatenate([th, [th.min() + 2 * np.pi]]))))
        )
        order = config.profile_order if coverage >= config.min_coverage_deg else 0
        coef = fit_wall_profile(th, rho[on], order, config.loss_scale_mm)
        deviation[on] = rho[on] - fourier_design(th, order) @ coef
        st_axial.append(float(np.median(sigma[on])))
        st_diam.append(2.0 * coef[0])
        st_oval.append(2.0 * float(np.hypot(coef[3], coef[4])) / coef[0] if order >= 2 else np.nan)
    ok = np.isfinite(deviation)
    radius = 0.5 * diameter
    circ = 2 * np.pi * radius
    samples = WallSamples(
        sigma_mm=sigma[ok],
        arc_mm=(theta[ok] % (2 * np.pi)) * radius,
        deviation_mm=deviation[ok],
        ring=frame[ok],
        circumference_mm=circ,
    )
    defects, w = find_defects(
        samples,
        min_height_mm=config.min_height_mm,
        noise_factor=config.noise_factor,
        min_points=config.min_points,
        grid_mm=config.grid_mm,
    )
    warnings.extend(w)
    st_oval_arr = np.array(st_oval)
    finite = st_oval_arr[np.isfinite(st_oval_arr)]
    return AnalysisResult(
        inner_diameter_mm=float(diameter),
        straight=bool(straight),
        ovality_max=float(finite.max()) if len(finite) else float("nan"),
        stations_axial_mm=np.array(st_axial),
        stations_diameter_mm=np.array(st_diam),
        stations_ovality=st_oval_arr,
        defects=defects,
        centreline=line,
        point_sigma_mm=sigma,
        point_theta_rad=theta,
        point_deviation_mm=np.nan_to_num(deviation),
        radius_mm=float(radius),
        warnings=warnings,
    )
