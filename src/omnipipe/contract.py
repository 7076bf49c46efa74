"""Typed records of report.json's entries (DATA_CONTRACT.md section 4).

The back half of the pipeline hands these between its stages: a :class:`Defect` is made
by the analysis (:mod:`omnipipe.analysis.defects`), its uncertainties and flags added by
``dataclasses.replace`` (:mod:`omnipipe.analysis.uncertainty`,
:mod:`omnipipe.pipeline.quality`), and read by the report, the deliverable and the
evaluation; a :class:`TrajectoryQuality` is made by :mod:`omnipipe.pipeline.quality`.
``to_contract()`` is the one place each becomes its report.json entry (keys and
meanings binding: DATA_CONTRACT.md); ``Defect.from_contract`` reads one back.

Lengths mm, angles degrees (the contract's units: these are the edge).
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any

if TYPE_CHECKING:
    import numpy as np

    from omnipipe.sfm.rotation_check import GyroCheck
    from omnipipe.sfm.scale_check import StepCheck

CORE_KEYS = ("kind", "height_mm", "width_mm", "length_mm", "axial_start_mm", "angle_deg")
"""The keys every defect entry of report.json and scene.json has."""

SIGMA_KEYS = (
    "height_sigma_mm",
    "width_sigma_mm",
    "length_sigma_mm",
    "axial_start_sigma_mm",
    "angle_sigma_deg",
)
"""The 1-sigma partners of the sizes and position, in report.json's order."""


@dataclass(frozen=True)
class Defect:
    """A bulge or dent of the wall, as report.json states it.

    Attributes:
        kind: "bulge" (into the pipe) or "dent" (out of it).
        height_mm: largest radial deviation from the fitted wall.
        width_mm: circumferential extent (arc length on the wall) at half height.
        length_mm: extent along the pipe axis at half height.
        axial_start_mm: where the half-height extent starts, along the centreline from
            the first frame's origin.
        angle_deg: around the axis, from the first rig frame's x axis towards y.
        height_sigma_mm ... angle_sigma_deg: 1-sigma of each (None: not estimated, the
            model fit failed and the sizes are the rough grid measurement).
        fit_noise_mm: robust sigma of the model fit's residuals (None: no fit).
        points: samples beyond the detector's threshold.
        travel_mm: the robot's travel from the first frame to the rings at the defect's
            start (the camera motion's position errors grow with it); not in report.json.
        motion_unreliable: the defect lies across a stretch of unreliable camera motion.
        truncated: the defect runs past the measured stretch (its start or end, or an
            unmeasured gap): its sizes are those of the measured part, lower bounds, and
            its extent ends at the last measured ring (report.json ``truncated: true``).
    """

    kind: str
    height_mm: float
    width_mm: float
    length_mm: float
    axial_start_mm: float
    angle_deg: float
    height_sigma_mm: float | None = None
    width_sigma_mm: float | None = None
    length_sigma_mm: float | None = None
    axial_start_sigma_mm: float | None = None
    angle_sigma_deg: float | None = None
    fit_noise_mm: float | None = None
    points: int = 0
    travel_mm: float | None = None
    motion_unreliable: bool = False
    truncated: bool = False

    @property
    def axial_end_mm(self) -> float:
        """End of the half-height extent along the pipe."""
        return self.axial_start_mm + self.length_mm

    @property
    def axial_centre_mm(self) -> float:
        """Centre of the half-height extent along the pipe."""
        return self.axial_start_mm + 0.5 * self.length_mm

    @property
    def fitted(self) -> bool:
        """Whether the sizes come from the model fit (and carry uncertainties)."""
        return self.height_sigma_mm is not None

    def to_contract(self) -> dict[str, Any]:
        """The report.json entry: the contract's keys, their ``*_sigma_*`` partners
        (null when not estimated), ``fit_noise_mm`` (with a fit), ``points`` and
        ``motion_unreliable: true`` and ``truncated: true`` (each only when set)."""
        out: dict[str, Any] = {key: getattr(self, key) for key in CORE_KEYS + SIGMA_KEYS}
        if self.fit_noise_mm is not None:
            out["fit_noise_mm"] = self.fit_noise_mm
        out["points"] = self.points
        if self.motion_unreliable:
            out["motion_unreliable"] = True
        if self.truncated:
            out["truncated"] = True
        return out

    def core(self) -> dict[str, Any]:
        """The six keys every defect entry has (:data:`CORE_KEYS`)."""
        return {key: getattr(self, key) for key in CORE_KEYS}

    @staticmethod
    def from_contract(entry: Mapping[str, Any]) -> Defect:
        """A defect entry of report.json or scene.json (the caller checks the core keys)."""
        sigmas = {key: _float_or_none(entry.get(key)) for key in SIGMA_KEYS}
        return Defect(
            kind=str(entry["kind"]),
            height_mm=float(entry["height_mm"]),
            width_mm=float(entry["width_mm"]),
            length_mm=float(entry["length_mm"]),
            axial_start_mm=float(entry["axial_start_mm"]),
            angle_deg=float(entry["angle_deg"]),
            fit_noise_mm=_float_or_none(entry.get("fit_noise_mm")),
            points=int(entry.get("points") or 0),
            motion_unreliable=bool(entry.get("motion_unreliable", False)),
            truncated=bool(entry.get("truncated", False)),
            **sigmas,
        )


def _float_or_none(value: Any) -> float | None:
    return None if value is None else float(value)


@dataclass(frozen=True)
class UnreliableSpan:
    """A stretch of frames whose camera motion could not be trusted.

    Attributes:
        first_frame, last_frame: 0-based frame indices (frames/ order), inclusive.
        reason: why (e.g. "ambiguous laser scale").
        axial_start_mm, axial_end_mm: its extent along the pipe (the defects' axial
            convention), None when its stations' positions are unknown (omnipipe's
            addition to the contract: report.html marks it on the unrolled wall).
    """

    first_frame: int
    last_frame: int
    reason: str
    axial_start_mm: float | None = None
    axial_end_mm: float | None = None

    @property
    def located(self) -> bool:
        """Whether its extent along the pipe is known."""
        return self.axial_start_mm is not None and self.axial_end_mm is not None

    def to_contract(self) -> dict[str, Any]:
        """Its entry of ``trajectory_quality.unreliable``."""
        out: dict[str, Any] = {
            "first_frame": int(self.first_frame),
            "last_frame": int(self.last_frame),
            "reason": self.reason,
        }
        if self.located:
            out["axial_start_mm"] = self.axial_start_mm
            out["axial_end_mm"] = self.axial_end_mm
        return out


@dataclass(frozen=True)
class RotationCheck:
    """The camera motion's rotation against the IMU's gyro (omnipipe's addition to
    ``trajectory_quality``: ``rotation_check``).

    Attributes:
        max_gap_deg: where the images' rotation since the first frame departs furthest
            from the gyro's in the gyro's sigmas: the departure (deg) ...
        max_gap_frame: ... at this frame ...
        gyro_sigma_deg: ... and the gyro's own 1-sigma there (deg).
        gyro: the frames' rotations by both (not in report.json).
        station_frames: (K,) first frame of each station (not in report.json).
        station_axial_mm: (K,) their axial positions, NaN unknown (not in report.json).
    """

    max_gap_deg: float
    max_gap_frame: int
    gyro_sigma_deg: float
    gyro: GyroCheck
    station_frames: np.ndarray
    station_axial_mm: np.ndarray

    def to_contract(self) -> dict[str, Any]:
        """Its entry ``trajectory_quality.rotation_check``."""
        return {
            "source": "gyro",
            "max_gap_deg": round(float(self.max_gap_deg), 3),
            "max_gap_frame": int(self.max_gap_frame),
            "gyro_sigma_deg": round(float(self.gyro_sigma_deg), 3),
        }


@dataclass(frozen=True)
class TrajectoryQuality:
    """report.json's ``trajectory_quality``: what the user is told about the camera motion.

    Attributes:
        steps_checked: frame-to-frame steps the run could check.
        unreliable: the stretches whose motion could not be trusted, in frame order.
        scale_source: where the metric scale came from (sfm's description).
        laser_offset_pct: the laser-anchored run's offset (percent).
        wall_scale_gap_pct: after the adjustment, how far the wall's lengths were from the
            laser-anchored run's (percent; None: not measured).
        scale_correction_pct: the correction applied (percent; None: not measured).
        scale_sigma_pct: 1-sigma of every length along the pipe (percent; None: unknown).
        keyframe_steps: every keyframe step's evidence (laser length and consensus
            peaks, feature depth length, confidence).
        rotation_check: the rotation against the gyro, or None (no gyro).
    """

    steps_checked: int
    unreliable: tuple[UnreliableSpan, ...] = ()
    scale_source: str = ""
    laser_offset_pct: float = 0.0
    wall_scale_gap_pct: float | None = None
    scale_correction_pct: float | None = None
    scale_sigma_pct: float | None = None
    keyframe_steps: tuple[StepCheck, ...] = ()
    rotation_check: RotationCheck | None = None

    def to_contract(self) -> dict[str, Any]:
        """The report.json entry (the contract's keys, then omnipipe's)."""
        out = {
            "steps_checked": self.steps_checked,
            "scale_source": self.scale_source,
            "laser_offset_pct": self.laser_offset_pct,
            "wall_scale_gap_pct": self.wall_scale_gap_pct,
            "scale_correction_pct": self.scale_correction_pct,
            "scale_sigma_pct": self.scale_sigma_pct,
            "unreliable": [u.to_contract() for u in self.unreliable],
            "keyframe_steps": [c.to_dict() for c in self.keyframe_steps],
        }
        if self.rotation_check is not None:
            out["rotation_check"] = self.rotation_check.to_contract()
        return out

