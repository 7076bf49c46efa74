"""``features.csv``: joints, laterals (and the other features of report.json) with their
clock position, distance and a NASSCO PACP / EN 13508-2 code where one exists.

The mapping (docs/inspection_coding.md, "Features"): a joint whose offset is
significant (>= 1 mm and > 2 sigma) is an offset joint, PACP JOM (< 5 % of the
diameter) or JOL, EN 13508-2 BAJB (radial displacement); otherwise a gap >= 3 mm is a
separated joint, PACP JSM (< 5 % of the diameter) or JSL, EN 13508-2 BAJA; a joint with
neither is a plain joint (no code). A lateral is PACP TF (the inspector picks TF / TB /
TS: omnipipe cannot tell a factory tap from a break-in), EN 13508-2 BCA. Ovality:
PACP D (deformed; DV/DH need gravity), EN BAA. Water: PACP MWL, EN 13508-2 BDD. The
size bands are omnipipe's, not the standards' (PACP grades offsets against the wall
thickness, which omnipipe does not measure): review by a certified inspector.
"""

from __future__ import annotations

import csv
from collections.abc import Sequence
from pathlib import Path
from typing import TYPE_CHECKING, Any

from omnipipe.report.deliverable import clock_position, distance_origin, header_lines, run_clock

if TYPE_CHECKING:
    from omnipipe.survey import Survey

CSV_NAME = "features.csv"
COLUMNS = (
    "feature", "kind", "pacp", "en13508_2", "clock", "clock_deg", "distance_m",
    "distance_sigma_mm", "gap_mm", "gap_sigma_mm", "offset_mm", "offset_sigma_mm",
    "diameter_mm", "diameter_sigma_mm", "note",
)


def codes(f: dict[str, Any], diameter_mm: float | None) -> tuple[str, str, str]:
    """(PACP code, EN 13508-2 code, note) of a report.json feature."""
    d = diameter_mm or float("nan")
    kind = f.get("kind")
    if kind == "joint":
        off, osig, gap = f.get("offset_mm") or 0.0, f.get("offset_sigma_mm") or 0.0, f.get("gap_mm") or 0.0
        if off >= 1.0 and off > 2.0 * osig:
            return ("JOM" if off < 0.05 * d else "JOL"), "BAJB", "offset joint"
        if gap >= 3.0:
            return ("JSM" if gap < 0.05 * d else "JSL"), "BAJA", "separated joint"
        return "", "", "joint (no observation)"
    if kind == "lateral":
        return "TF", "BCA", "lateral connection: inspector picks TF/TB/TS"
    if kind == "ovality":
        return "D", "BAA", "deformed (DV/DH need gravity)"
    if kind == "water":
        return "MWL", "BDD", "water level"
    return "", "", str(kind)


def _f(x: Any, nd: int) -> str:
    return "" if x is None else f"{float(x):.{nd}f}"


def feature_rows(
    features: Sequence[dict[str, Any]], diameter_mm: float | None, reference_deg: float,
    start_offset_m: float = 0.0,
) -> list[dict[str, str]]:
    """One row per feature (:data:`COLUMNS`); the clock of a joint is its offset's direction."""
    rows = []
    for i, f in enumerate(features, 1):
        pacp, en, note = codes(f, diameter_mm)
        if f.get("motion_unreliable"):
            note += "; on unreliable camera motion: position not trustworthy"
        angle = f.get("angle_deg")
        if f.get("kind") == "joint" and (f.get("offset_mm") or 0.0) > 2.0 * (f.get("offset_sigma_mm") or 0.0):
            angle = f.get("offset_angle_deg")  # a joint's clock: its offset's direction
        clock, clock_deg = clock_position(angle, reference_deg) if angle is not None else ("", None)
        axial = f.get("axial_mm", f.get("axial_from_mm"))
        rows.append({
            "feature": str(i), "kind": str(f.get("kind")), "pacp": pacp, "en13508_2": en,
            "clock": clock, "clock_deg": _f(clock_deg, 1),
            "distance_m": "" if axial is None else f"{start_offset_m + axial / 1000.0:.4f}",
            "distance_sigma_mm": _f(f.get("axial_sigma_mm"), 2),
            "gap_mm": _f(f.get("gap_mm"), 2), "gap_sigma_mm": _f(f.get("gap_sigma_mm"), 2),
            "offset_mm": _f(f.get("offset_mm"), 2), "offset_sigma_mm": _f(f.get("offset_sigma_mm"), 2),
            "diameter_mm": _f(f.get("diameter_mm"), 1), "diameter_sigma_mm": _f(f.get("diameter_sigma_mm"), 1),
            "note": note,
        })
    return rows


def write_features_csv(path: Path, rows: Sequence[dict[str, str]], comments: Sequence[str] = ()) -> None:
    """Write features.csv: ``# `` comment lines, the header, one row per feature."""
    with open(path, "w", encoding="utf-8", newline="") as fh:
        for line in comments:
            fh.write(f"# {line}\n")
        writer = csv.DictWriter(fh, fieldnames=COLUMNS, lineterminator="\n")
        writer.writeheader()
        writer.writerows(rows)


def write_features(
    out: Path, summary: dict[str, Any], survey: Survey | None, travel_along_rig_z: float = 1.0
) -> Path:
    """Write ``out/features.csv`` from report.json's ``features`` with defects.csv's
    conventions: the run's 12:00 (:func:`~omnipipe.report.deliverable.run_clock`: the
    survey's, gravity's, else image up), distances from the survey's start node or else
    the first measured ring (never a negative distance inside the run), the same comment
    lines; returns its path."""
    clock = run_clock(summary, survey, travel_along_rig_z)
    origin = distance_origin(summary, survey)
    rows = feature_rows(
        summary.get("features") or [], summary.get("inner_diameter_mm"), clock.angle_deg,
        origin.offset_m,
    )
    path = Path(out) / CSV_NAME
    conventions = [
        line for line in header_lines(summary, survey, travel_along_rig_z)[1:]
        if not line.startswith(("flags:", "severity_grade:"))
    ]
    lines = ["omnipipe features.csv", *conventions,
             "pacp, en13508_2: docs/inspection_coding.md 'Features' (omnipipe's size bands)"]
    write_features_csv(path, rows, lines)
    return path
