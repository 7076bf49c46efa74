"""The typed records of pipe features: parts of a sound pipe (DATA_CONTRACT.md, "Real
pipes"), never also reported as defects.

One family: :class:`Feature` and its kinds. Point features (:class:`PointFeature`:
:class:`Joint`, :class:`Lateral`) sit at one axial position; extended ones
(:class:`Stretch`: :class:`Bend`, :class:`Taper`, :class:`Ovality`, :class:`Water`) run
from ``axial_from_mm`` to ``axial_to_mm``. Joints and laterals come from the rings
(:mod:`omnipipe.analysis.features`), the stretches from the stations
(:mod:`omnipipe.analysis.sections`). Each becomes its report.json entry in
:meth:`Feature.to_contract` only: its fields are the contract's keys, in order, each size
followed by its ``*_sigma_*`` partner.

Positions follow the defects' convention: axial along the centreline from the first
frame's origin (mm); ``angle_deg`` around the axis from the first rig frame's x axis
towards y (degrees; an ovality's major axis modulo 180). Lengths mm, angles degrees (the
contract's units).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, fields
from typing import Any, ClassVar

FEATURE_KINDS = ("joint", "lateral", "bend", "taper", "ovality", "water")
"""The contract's feature kinds."""


@dataclass(frozen=True, kw_only=True)
class Feature:
    """A feature of the pipe; ``kind`` is the class's contract kind."""

    kind: ClassVar[str] = ""

    @property
    def position_mm(self) -> float:
        """Where the feature starts along the pipe (mm): the axial order of report.json."""
        raise NotImplementedError

    def to_contract(self) -> dict[str, Any]:
        """The report.json entry: ``kind``, then every field by its contract key (values
        rounded to 3 decimals, sigmas to 4; None or a non-finite sigma: null; ``points``
        an integer; ``truncated`` only when true)."""
        out: dict[str, Any] = {"kind": self.kind}
        for f in fields(self):
            value = getattr(self, f.name)
            if isinstance(value, bool):
                if value:
                    out[f.name] = True
            elif isinstance(value, int):
                out[f.name] = value
            elif value is None or not math.isfinite(value):
                out[f.name] = None
            else:
                out[f.name] = round(float(value), 4 if "_sigma" in f.name else 3)
        return out


@dataclass(frozen=True, kw_only=True)
class PointFeature(Feature):
    """A feature at one axial position.

    Attributes:
        axial_mm: joint: centre of the gap; lateral: centre of the hole (mm).
        axial_sigma_mm: its 1-sigma.
        motion_unreliable: it lies in a stretch of unreliable camera motion (its position
            and axial sizes rest on untrusted motion; omnipipe extension).
    """

    axial_mm: float
    axial_sigma_mm: float | None = None
    motion_unreliable: bool = False

    @property
    def position_mm(self) -> float:
        return self.axial_mm


@dataclass(frozen=True, kw_only=True)
class Joint(PointFeature):
    """A circumferential joint.

    Attributes:
        gap_mm: axial width of the gap at half its depth.
        offset_mm: radial displacement of the downstream section relative to the
            upstream one, towards ``offset_angle_deg`` (None: too few rings on a side).
        depth_mm: radial depth of the gap beyond the wall (omnipipe extension).
        points: wall points found in the gap (omnipipe extension).
    """

    kind: ClassVar[str] = "joint"
    gap_mm: float
    gap_sigma_mm: float | None = None
    offset_mm: float | None = None
    offset_sigma_mm: float | None = None
    offset_angle_deg: float | None = None
    offset_angle_sigma_deg: float | None = None
    depth_mm: float | None = None
    points: int = 0


@dataclass(frozen=True, kw_only=True)
class Lateral(PointFeature):
    """A lateral connection (tap, tee): a round hole in the wall.

    Attributes:
        angle_deg: the hole centre's angle around the axis ([0, 360)).
        diameter_mm: diameter of the opening (its circumferential chord).
        points: points found in the opening (omnipipe extension).
    """

    kind: ClassVar[str] = "lateral"
    angle_deg: float
    angle_sigma_deg: float | None = None
    diameter_mm: float
    diameter_sigma_mm: float | None = None
    points: int = 0


@dataclass(frozen=True, kw_only=True)
class Stretch(Feature):
    """A feature over a stretch of the pipe.

    Attributes:
        axial_from_mm, axial_to_mm: its extent (mm), each with its 1-sigma (half the
            local station spacing: the edge lies between two stations).
        truncated: the stretch runs past the measured stations: its extent (and a bend's
            turn) are lower bounds.
        motion_unreliable: it overlaps a stretch of unreliable camera motion (omnipipe
            extension).
    """

    axial_from_mm: float
    axial_from_sigma_mm: float | None = None
    axial_to_mm: float
    axial_to_sigma_mm: float | None = None
    truncated: bool = False
    motion_unreliable: bool = False

    @property
    def position_mm(self) -> float:
        return self.axial_from_mm


@dataclass(frozen=True, kw_only=True)
class Bend(Stretch):
    """A bend (elbow): the centreline turns by ``turn_deg`` at radius ``radius_mm``.

    ``turn_motion_sigma_deg``: the camera motion's rotation error over the bend as the
    gyro shows it (omnipipe.pipeline.quality.bend_with_rotation), already in
    ``turn_sigma_deg`` and ``radius_sigma_mm``; None without a gyro."""

    kind: ClassVar[str] = "bend"
    radius_mm: float
    radius_sigma_mm: float | None = None
    turn_deg: float
    turn_sigma_deg: float | None = None
    turn_motion_sigma_deg: float | None = None


@dataclass(frozen=True, kw_only=True)
class Taper(Stretch):
    """A reducer (or increaser): the mean diameter goes from one value to another."""

    kind: ClassVar[str] = "taper"
    diameter_from_mm: float
    diameter_from_sigma_mm: float | None = None
    diameter_to_mm: float
    diameter_to_sigma_mm: float | None = None


@dataclass(frozen=True, kw_only=True)
class Ovality(Stretch):
    """An out-of-round stretch: (Dmax - Dmin) / Dnominal x 100 = ``percent``, the major
    axis at ``angle_deg`` (modulo 180)."""

    kind: ClassVar[str] = "ovality"
    percent: float
    percent_sigma: float | None = None
    angle_deg: float
    angle_sigma_deg: float | None = None


@dataclass(frozen=True, kw_only=True)
class Water(Stretch):
    """Standing water ``depth_mm`` above the invert."""

    kind: ClassVar[str] = "water"
    depth_mm: float
    depth_sigma_mm: float | None = None
