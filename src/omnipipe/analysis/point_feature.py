"""Point features of a sound pipe (joints, laterals) as report.json states them.

The data contract's "Real pipes" ``features`` entries: parts of a sound pipe, never also
reported as defects. Positions follow the defects' convention (axial along the
centreline from the first frame's origin, mm; ``angle_deg`` from the first rig frame's
x axis towards y).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any


def _r(x: float | None, nd: int = 3) -> float | None:
    return None if x is None or x != x else round(float(x), nd)


@dataclass(frozen=True)
class PointFeature:
    """A joint or a lateral (or another kind: the keys present are the kind's).

    Attributes:
        kind: "joint" or "lateral" (the contract also names bend, taper, ovality, water).
        axial_mm: joint: centre of the gap; lateral: centre of the hole (mm).
        angle_deg: lateral: the hole centre's angle around the axis (degrees, [0, 360)).
        gap_mm: joint: axial width of the gap at half depth.
        depth_mm: joint: radial depth of the gap below the wall (omnipipe extension).
        offset_mm: joint: radial displacement of the downstream section relative to the
            upstream one, towards ``offset_angle_deg``.
        diameter_mm: lateral: diameter of the opening (its circumferential chord).
        points: wall points excluded as inside the gap or the opening.
        *_sigma_*: 1-sigma of each (None: not estimated).
    """

    kind: str
    axial_mm: float
    axial_sigma_mm: float | None = None
    angle_deg: float | None = None
    angle_sigma_deg: float | None = None
    gap_mm: float | None = None
    gap_sigma_mm: float | None = None
    depth_mm: float | None = None
    offset_mm: float | None = None
    offset_sigma_mm: float | None = None
    offset_angle_deg: float | None = None
    offset_angle_sigma_deg: float | None = None
    diameter_mm: float | None = None
    diameter_sigma_mm: float | None = None
    points: int = 0

    def to_contract(self) -> dict[str, Any]:
        """The report.json entry: the kind's keys, each size with its ``_sigma_`` partner."""
        out: dict[str, Any] = {"kind": self.kind, "axial_mm": _r(self.axial_mm, 2)}
        out["axial_sigma_mm"] = _r(self.axial_sigma_mm)
        if self.kind == "joint":
            keys = ("gap_mm", "gap_sigma_mm", "offset_mm", "offset_sigma_mm",
                    "offset_angle_deg", "offset_angle_sigma_deg", "depth_mm")
        else:
            keys = ("angle_deg", "angle_sigma_deg", "diameter_mm", "diameter_sigma_mm")
        for k in keys:
            out[k] = _r(getattr(self, k))
        out["points"] = int(self.points)
        return out
