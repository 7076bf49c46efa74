"""The typed record of a pipe feature: a part of a sound pipe (DATA_CONTRACT.md, "Real
pipes"), never also reported as a defect.

A :class:`Feature` is made by the analysis (:mod:`omnipipe.analysis.stations` for the
cross-section features: taper, bend, ovality, water) and becomes its report.json entry in
:meth:`Feature.to_contract` only. Lengths mm, angles degrees (the contract's units).
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

FEATURE_KINDS = ("joint", "lateral", "bend", "taper", "ovality", "water")
"""The contract's feature kinds."""


@dataclass(frozen=True)
class Feature:
    """One feature of the pipe, in the defects' position convention.

    Attributes:
        kind: one of :data:`FEATURE_KINDS`.
        axial_mm: position of a point-like feature (joint, lateral), else None.
        axial_from_mm, axial_to_mm: extent of a stretch (bend, taper, ovality, water),
            else None.
        angle_deg: around the axis, from the first rig frame's x axis towards y (an
            ovality's major axis: modulo 180), None when the kind has none.
        sizes: the contract's size keys and values, e.g. ``{"radius_mm": 225.0,
            "turn_deg": 90.0}`` for a bend, ``{"percent": 4.0}`` for an ovality.
        sigmas: 1-sigma of any of the above by its contract sigma key (``radius_sigma_mm``,
            ``axial_from_sigma_mm``, ``angle_sigma_deg``, ...).
        truncated: the stretch runs past the measured stations: its extent (and a bend's
            turn) are lower bounds (written as ``truncated: true``, as for defects).
    """

    kind: str
    axial_mm: float | None = None
    axial_from_mm: float | None = None
    axial_to_mm: float | None = None
    angle_deg: float | None = None
    sizes: dict[str, float] = field(default_factory=dict)
    sigmas: dict[str, float] = field(default_factory=dict)
    truncated: bool = False

    def to_contract(self) -> dict[str, Any]:
        """The report.json entry: ``kind``, the position keys set, the sizes, then each
        ``*_sigma_*`` partner (rounded; a non-finite sigma is null)."""
        out: dict[str, Any] = {"kind": self.kind}
        for key in ("axial_mm", "axial_from_mm", "axial_to_mm"):
            value = getattr(self, key)
            if value is not None:
                out[key] = round(float(value), 2)
        out.update({k: round(float(v), 3) for k, v in self.sizes.items()})
        if self.angle_deg is not None:
            out["angle_deg"] = round(float(self.angle_deg), 2)
        for k, v in self.sigmas.items():
            out[k] = round(float(v), 4) if v == v and abs(v) != float("inf") else None
        if self.truncated:
            out["truncated"] = True
        return out
