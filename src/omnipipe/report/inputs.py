"""The report stage's typed inputs (:class:`ReportInputs`) and its config
(:class:`ReportConfig`), and what the page's parts read off them alike: the run's survey,
its direction of travel, the omnipipe angle that is 12:00 and the point features (joints,
laterals) with their angles.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Any

import numpy as np

from omnipipe.config import bounded

if TYPE_CHECKING:
    from collections.abc import Sequence

    from omnipipe.contract import Defect, TrajectoryQuality
    from omnipipe.report.relief import WallPoints
    from omnipipe.report.views import DefectView
    from omnipipe.survey import Survey


@dataclass(frozen=True)
class ReportConfig:
    """Report knobs.

    Attributes:
        max_faces: the 3-D view keeps at most this many triangles (the rest are thinned).
        texture_max_px: longest side of the texture sent to the viewer (px).
        title: page title.
    """

    max_faces: int = bounded(250_000, ge=1)
    texture_max_px: int = bounded(4096, ge=16)
    title: str = "omnipipe inspection report"


@dataclass
class ReportInputs:
    """What the report shows.

    Attributes:
        summary: the report.json content (frames, inner_diameter_mm, stations, ...).
        world_from_rig: (N, 4, 4) estimated poses (mm).
        mesh_vertices: (V, 3) mm, world frame; None when there is no mesh.
        mesh_faces: (F, 3) vertex indices.
        mesh_uvs: (V, 2) texture coordinates in [0, 1] (v up), or None.
        texture: (H, W, 3) uint8 texture image, or None.
        unrolled: (H, W, 3) uint8 unrolled wall image (rows: along the pipe, columns: angle).
        unrolled_extent: (angle_min_deg, angle_max_deg, axial_min_mm, axial_max_mm) of it.
        unrolled_alpha: (H, W) bool, True where the wall was measured and textured; the
            other cells (a joint's gap, a lateral's opening, the unseen) are drawn
            hatched grey, not as dark wall. None: every cell shown as it is.
        stations_axial_mm, stations_diameter_mm, stations_ovality: per-station profile.
        radius_mm: fitted wall radius, for drawing defect outlines on the unrolled image.
        truth: rows of the measured-vs-true table: (name, measured, 1-sigma, true, unit)
            (or without the sigma), or None.
        evaluation: the evaluate result dict, when ground truth exists.
        frame_index: (N,) 0-based frame index of each pose in ``world_from_rig`` (to
            mark the unreliable stretches on the trajectory), or None.
        defects: the reported defects, in report.json's order.
        trajectory_quality: the camera motion check (unreliable stretches are marked on
            the unrolled wall and the trajectory), or None.
        wall: the measured wall points and their deviations (the relief maps), or None.
        defect_views: each defect's camera view (None where no frame sees it), in the
            defects' order; may be empty.
        wall_points_in_world: (N, 3) world positions (mm) of ``wall``'s points (the 3-D
            view's defect markers), or None.
    """

    summary: dict[str, Any]
    world_from_rig: np.ndarray
    mesh_vertices: np.ndarray | None = None
    mesh_faces: np.ndarray | None = None
    mesh_uvs: np.ndarray | None = None
    texture: np.ndarray | None = None
    unrolled: np.ndarray | None = None
    unrolled_extent: tuple[float, float, float, float] | None = None
    unrolled_alpha: np.ndarray | None = None
    stations_axial_mm: np.ndarray | None = None
    stations_diameter_mm: np.ndarray | None = None
    stations_ovality: np.ndarray | None = None
    radius_mm: float | None = None
    truth: Sequence[tuple[Any, ...]] | None = None
    evaluation: dict[str, Any] | None = field(default=None)
    frame_index: np.ndarray | None = None
    defects: Sequence[Defect] = ()
    trajectory_quality: TrajectoryQuality | None = None
    wall: WallPoints | None = None
    defect_views: Sequence[DefectView | None] = ()
    wall_points_in_world: np.ndarray | None = None


def clock_deg(inputs: ReportInputs) -> float:
    """The omnipipe angle that is 12:00 in this report."""
    from omnipipe.report.deliverable import run_clock

    return run_clock(inputs.summary, survey_of(inputs.summary), travel_sign(inputs)).angle_deg


def point_features(summary: dict[str, Any]) -> list[tuple[str, float, float | None]]:
    """(label, axial mm, omnipipe angle deg or None) of report.json's point features (joints,
    laterals): the angle is a lateral's hole centre or a joint's significant offset."""
    out = []
    for f in summary.get("features") or []:
        axial = f.get("axial_mm")
        if not isinstance(axial, int | float):
            continue
        angle = f.get("angle_deg")
        if f.get("kind") == "joint":
            off, osig = f.get("offset_mm") or 0.0, f.get("offset_sigma_mm") or 0.0
            angle = f.get("offset_angle_deg") if off > 2.0 * osig else None
        out.append((str(f.get("kind")), float(axial), float(angle) if isinstance(angle, int | float) else None))
    return out


def survey_of(summary: dict[str, Any]) -> Survey | None:
    """report.json's survey header (survey.yaml's fields) as a :class:`Survey`, or None."""
    from omnipipe.survey import FIELDS, Survey

    data = summary.get("survey")
    if not data:
        return None
    return Survey(**{k: v for k, v in data.items() if k in FIELDS})


def travel_sign(inputs: ReportInputs) -> float:
    """The rig's travel along the first rig frame's z (mm, last pose minus first: its sign
    is the direction of travel), 1.0 with fewer than two poses."""
    poses = np.asarray(inputs.world_from_rig)
    if poses.ndim != 3 or len(poses) < 2:
        return 1.0
    return float(poses[-1][2, 3] - poses[0][2, 3])
