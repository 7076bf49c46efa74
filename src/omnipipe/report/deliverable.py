"""The inspector's deliverable: ``defects.csv``, one crop image per defect, survey header.

Written by :func:`omnipipe.pipeline.write` beside report.json (docs/inspection_coding.md
explains each column and how it maps to NASSCO PACP and EN 13508-2).

Conventions (also written as ``#`` comment lines at the top of defects.csv):

- **Clock position**: viewed looking in the survey direction (the robot's direction of
  travel), clockwise from 12 o'clock (:mod:`omnipipe.report.clock`: survey.yaml
  ``clock_reference_deg``, else gravity from imu.txt, else image up in the first frame,
  said in the ``clock_reference`` column). ``clock_deg`` is 0-360 clockwise from 12,
  ``clock_sigma_deg`` its 1-sigma; ``clock`` is ``hh:mm`` (1 hour = 30 degrees,
  1 minute = 0.5 degree).
- **Distance**: metres along the pipe in the direction of travel from ``distance_from``:
  with survey.yaml the start node (``start_offset_m`` + the axial position from the first
  frame's mirror focus), without one the first measured ring (the start of the inspected
  stretch). ``distance_start_m`` / ``distance_end_m`` bound the defect, each with its
  1-sigma; a negative distance from the start node is flagged ``before_start_node``.
- **Flags**: ``truncated`` (the defect runs past the measured stretch: the sizes are those
  of the measured part, lower bounds), ``motion_unreliable``, ``before_start_node``.
- **Severity grade** 1-5 from the defect height as a percentage of the inner diameter
  (:data:`SEVERITY_BANDS_PCT`): bands chosen by omnipipe in the manner of PACP's
  structural grades (1 = minor ... 5 = most severe); they are not an official PACP or
  EN 13508-2 grading and must be reviewed by a certified inspector.
- **Best view**: the frame of the camera view (``camera_view``, :mod:`omnipipe.report.views`:
  the frame that sees the defect from closest); without one, the frame whose laser ring
  passed closest to the defect's axial centre.
- **Crop**: ``defects/defect_NN.png``, the unrolled wall (``unrolled.png``, 0.5 mm per
  px by default) around the defect: the defect's extent plus a margin, with a thin
  outline of its half-height extent; columns run clockwise as seen in the travel
  direction, rows along the pipe.
"""

from __future__ import annotations

import csv
import math
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any

from omnipipe.report.clock import (
    ClockReference,
    clock_position,
    clock_reference,
    image_up_angle_deg,
)

if TYPE_CHECKING:
    import numpy as np

    from omnipipe.contract import Defect
    from omnipipe.model.texture_grid import UnrolledImage
    from omnipipe.report.views import DefectView
    from omnipipe.survey import Survey

CSV_NAME = "defects.csv"
CROP_DIR = "defects"

# (upper bound of height / inner diameter in %, grade): the first band whose bound exceeds
# the defect's percentage gives its grade; beyond the last bound: grade 5.
SEVERITY_BANDS_PCT: tuple[tuple[float, int], ...] = ((1.0, 1), (3.0, 2), (5.0, 3), (10.0, 4))

CSV_COLUMNS = (
    "defect",
    "kind",
    "clock",
    "clock_deg",
    "clock_sigma_deg",
    "clock_reference",
    "distance_from",
    "distance_start_m",
    "distance_start_sigma_m",
    "distance_end_m",
    "distance_end_sigma_m",
    "height_mm",
    "height_sigma_mm",
    "width_mm",
    "width_sigma_mm",
    "length_mm",
    "length_sigma_mm",
    "height_pct_of_diameter",
    "severity_grade",
    "best_view_frame",
    "crop",
    "camera_view",
    "flags",
)

# Margin around the defect in a crop: this fraction of its size, at least MIN_MARGIN_MM.
CROP_MARGIN = 0.5
MIN_MARGIN_MM = 15.0
CROP_ASPECT = 0.5
"""A defect crop's shorter side is at least this fraction of its longer one."""


def severity_grade(height_mm: float, diameter_mm: float | None) -> tuple[int | None, float | None]:
    """(grade 1-5, height in % of the diameter) by :data:`SEVERITY_BANDS_PCT`;
    (None, None) without a diameter."""
    if diameter_mm is None or not diameter_mm > 0 or not math.isfinite(height_mm):
        return None, None
    pct = 100.0 * abs(height_mm) / diameter_mm
    for bound, grade in SEVERITY_BANDS_PCT:
        if pct < bound:
            return grade, pct
    return 5, pct


def default_clock_reference_deg(travel_along_rig_z: float = 1.0) -> float:
    """The omnipipe angle of image up (:func:`omnipipe.report.clock.image_up_angle_deg`)."""
    return image_up_angle_deg(travel_along_rig_z)


@dataclass(frozen=True)
class DistanceOrigin:
    """Where the distances of defects.csv and the report start.

    Attributes:
        name: what the inspector reads (``start node MH-12`` or ``first measured ring``).
        offset_m: distance of the axial origin (the first frame's mirror focus) from it.
        from_node: True when it is the survey's start node.
    """

    name: str
    offset_m: float
    from_node: bool


def distance_origin(summary: dict[str, Any], survey: Survey | None) -> DistanceOrigin:
    """The survey's start node (with survey.yaml), else the first measured ring (the
    first station's axial position: no distance inside the measured stretch is negative)."""
    if survey is not None:
        node = survey.start_node or "(unnamed)"
        return DistanceOrigin(f"start node {node}", float(survey.start_offset_m), True)
    axial = [float(st["axial_mm"]) for st in summary.get("stations") or [] if st.get("axial_mm") is not None]
    first = min(axial) if axial else 0.0
    return DistanceOrigin("first measured ring (no survey.yaml)", -first / 1000.0, False)


@dataclass(frozen=True)
class DefectRow:
    """One row of defects.csv (see :data:`CSV_COLUMNS`); ``values`` maps column to text."""

    values: dict[str, str]
    defect: Defect


def _fmt(value: Any, digits: int) -> str:
    if value is None:
        return ""
    try:
        x = float(value)
    except (TypeError, ValueError):
        return ""
    return f"{x:.{digits}f}" if math.isfinite(x) else ""


def best_view_frame(centre_mm: float, stations: Sequence[dict[str, Any]]) -> int | None:
    """The frame of the station ring closest to ``centre_mm`` (axial, mm); None if the
    stations carry no frame numbers."""
    best = None
    for st in stations:
        if st.get("frame") is None or st.get("axial_mm") is None:
            continue
        gap = abs(float(st["axial_mm"]) - centre_mm)
        if best is None or gap < best[0]:
            best = (gap, int(st["frame"]))
    return None if best is None else best[1]


def run_clock(summary: dict[str, Any], survey: Survey | None, travel_along_rig_z: float) -> ClockReference:
    """The run's 12:00: report.json ``clock_reference`` when the pipeline stated it, else
    the survey's or image up."""
    return ClockReference.from_dict(summary.get("clock_reference")) or clock_reference(
        survey, None, travel_along_rig_z
    )


def defect_rows(
    defects: Sequence[Defect],
    summary: dict[str, Any],
    survey: Survey | None = None,
    travel_along_rig_z: float = 1.0,
) -> list[DefectRow]:
    """The rows of defects.csv.

    Args:
        defects: the reported defects, in report.json's order.
        summary: report.json content (``inner_diameter_mm``, ``stations``,
            ``clock_reference``).
        survey: start node, offset and clock reference (None: distances from the first
            measured ring).
        travel_along_rig_z: sign of the robot's motion along its first rig frame's z.
    """
    clock = run_clock(summary, survey, travel_along_rig_z)
    origin = distance_origin(summary, survey)
    diameter = summary.get("inner_diameter_mm")
    stations = summary.get("stations") or []
    rows = []
    for k, d in enumerate(defects, start=1):
        text, clock_deg = clock_position(d.angle_deg, clock.angle_deg)
        start, length = d.axial_start_mm, d.length_mm
        grade, pct = severity_grade(d.height_mm, diameter)
        frame = best_view_frame(start + 0.5 * length, stations)
        dist_start = origin.offset_m + start / 1000.0
        flags = [
            name
            for name, on in (
                ("truncated", d.truncated),
                ("motion_unreliable", d.motion_unreliable),
                ("before_start_node", origin.from_node and dist_start < 0),
            )
            if on
        ]
        end_sigma = (
            None
            if d.axial_start_sigma_mm is None or d.length_sigma_mm is None
            else math.hypot(d.axial_start_sigma_mm, d.length_sigma_mm)
        )
        values = {
            "defect": str(k),
            "kind": d.kind,
            "clock": text,
            "clock_deg": _fmt(clock_deg, 1),
            "clock_sigma_deg": _fmt(
                None if d.angle_sigma_deg is None else math.hypot(d.angle_sigma_deg, clock.sigma_deg), 2
            ),
            "clock_reference": clock.source,
            "distance_from": origin.name,
            "distance_start_m": _fmt(dist_start, 4),
            "distance_start_sigma_m": _fmt(None if d.axial_start_sigma_mm is None else d.axial_start_sigma_mm / 1000, 4),
            "distance_end_m": _fmt(dist_start + length / 1000.0, 4),
            "distance_end_sigma_m": _fmt(None if end_sigma is None else end_sigma / 1000, 4),
            "height_pct_of_diameter": _fmt(pct, 2),
            "severity_grade": "" if grade is None else str(grade),
            "best_view_frame": "" if frame is None else str(frame),
            "crop": f"{CROP_DIR}/defect_{k:02d}.png",
            "camera_view": "",
            "flags": ";".join(flags),
        }
        for what, value, sigma in (
            ("height", d.height_mm, d.height_sigma_mm),
            ("width", d.width_mm, d.width_sigma_mm),
            ("length", d.length_mm, d.length_sigma_mm),
        ):
            values[f"{what}_mm"] = _fmt(value, 2)
            values[f"{what}_sigma_mm"] = _fmt(sigma, 2)
        rows.append(DefectRow(values=values, defect=d))
    return rows


def header_lines(
    summary: dict[str, Any], survey: Survey | None, travel_along_rig_z: float = 1.0
) -> list[str]:
    """The ``#`` comment lines of defects.csv: survey header and conventions."""
    lines = ["omnipipe defects.csv"]
    if survey is not None:
        for key, value in survey.to_dict().items():
            if key != "source" and value is not None:
                lines.append(f"{key}: {value}")
    diameter = summary.get("inner_diameter_mm")
    if diameter is not None:
        sigma = summary.get("inner_diameter_sigma_mm")
        pm = "" if sigma is None else f" +- {sigma:.2f}"
        lines.append(f"measured inner diameter: {diameter:.2f}{pm} mm")
    clock = run_clock(summary, survey, travel_along_rig_z)
    origin = distance_origin(summary, survey)
    lines += [
        "clock: viewed looking in the direction of travel, clockwise; 12:00 = "
        + ("the top of the pipe" if clock.gravity else "clock from image up: no gravity reference")
        + f" (clock_reference: {clock.source}; omnipipe angle {clock.angle_deg:.1f} deg)",
        f"distance_*_m: along the pipe in the direction of travel from the {origin.name}",
        "flags: truncated = runs past the measured stretch, sizes are lower bounds; "
        "motion_unreliable; before_start_node",
        "severity_grade: height as % of the inner diameter, bands "
        + ", ".join(f"<{b:g} %: {g}" for b, g in SEVERITY_BANDS_PCT)
        + ", else 5 (omnipipe's bands, not an official PACP/EN 13508-2 grade)",
        "*_sigma_*: 1-sigma standard uncertainty; empty where not estimated",
    ]
    return lines


def write_defects_csv(
    path: Path, rows: Sequence[DefectRow], comments: Sequence[str] = ()
) -> None:
    """Write defects.csv: ``# `` comment lines, the header row, one row per defect."""
    with open(path, "w", encoding="utf-8", newline="") as fh:
        for line in comments:
            fh.write(f"# {line}\n")
        writer = csv.DictWriter(fh, fieldnames=CSV_COLUMNS, lineterminator="\n")
        writer.writeheader()
        for row in rows:
            writer.writerow(row.values)


def crop_unrolled(
    image: np.ndarray,
    alpha: np.ndarray | None,
    axial_min_mm: float,
    mm_per_px: float,
    defect: Defect,
    circumference_mm: float,
) -> np.ndarray:
    """The window of the unrolled wall around a defect, outlined, as (h, w, 3) uint8.

    Args:
        image: (H, W, 3) unrolled wall, row 0 at ``axial_min_mm``, column 0 at angle 0,
            W columns spanning ``circumference_mm``.
        alpha: (H, W) measured cells, or None; unmeasured cells are drawn grey.
        defect: the defect (its axial start, length, angle and width).
    The window wraps around the seam at angle 0.
    """
    import numpy as np

    h, w = image.shape[:2]
    px_per_col_mm = w / circumference_mm
    length = max(defect.length_mm, mm_per_px)
    width = max(defect.width_mm, circumference_mm / w)
    margin_z = max(CROP_MARGIN * length, MIN_MARGIN_MM)
    margin_u = max(CROP_MARGIN * width, MIN_MARGIN_MM)
    # No sliver: each side of the window at least CROP_ASPECT x the other (a long narrow
    # bulge gets the wall beside it, whose texture shows the bulge's edges and shading).
    span_z, span_u = length + 2 * margin_z, width + 2 * margin_u
    if span_u < CROP_ASPECT * span_z:
        margin_u = 0.5 * (CROP_ASPECT * span_z - width)
    elif span_z < CROP_ASPECT * span_u:
        margin_z = 0.5 * (CROP_ASPECT * span_u - length)
    z0 = defect.axial_start_mm - margin_z
    z1 = defect.axial_start_mm + length + margin_z
    r0 = int(np.clip(math.floor((z0 - axial_min_mm) / mm_per_px), 0, h - 1))
    r1 = int(np.clip(math.ceil((z1 - axial_min_mm) / mm_per_px), r0 + 1, h))
    centre_col = defect.angle_deg / 360.0 * w
    half = min(0.5 * width + margin_u, 0.5 * circumference_mm) * px_per_col_mm
    cols = np.arange(math.floor(centre_col - half), math.ceil(centre_col + half) + 1) % w
    crop = image[r0:r1][:, cols, :3].astype(np.uint8).copy()
    if alpha is not None:
        crop[~alpha[r0:r1][:, cols].astype(bool)] = 128
    # Outline of the half-height extent (yellow).
    top = (defect.axial_start_mm - axial_min_mm) / mm_per_px - r0
    bottom = top + defect.length_mm / mm_per_px
    left = centre_col - 0.5 * defect.width_mm * px_per_col_mm - math.floor(centre_col - half)
    right = left + defect.width_mm * px_per_col_mm
    ch, cw = crop.shape[:2]
    t, b = int(np.clip(round(top), 0, ch - 1)), int(np.clip(round(bottom), 0, ch - 1))
    lft, rgt = int(np.clip(round(left), 0, cw - 1)), int(np.clip(round(right), 0, cw - 1))
    colour = np.array([255, 220, 0], dtype=np.uint8)
    crop[t, lft : rgt + 1] = colour
    crop[b, lft : rgt + 1] = colour
    crop[t : b + 1, lft] = colour
    crop[t : b + 1, rgt] = colour
    # Small crops are hard to see: enlarge to at least 160 px on the short side.
    scale = max(1, math.ceil(160 / max(1, min(ch, cw))))
    if scale > 1:
        crop = np.repeat(np.repeat(crop, scale, axis=0), scale, axis=1)
    return crop


def write_deliverable(
    out: Path,
    summary: dict[str, Any],
    defects: Sequence[Defect],
    unrolled: UnrolledImage | None = None,
    survey: Survey | None = None,
    travel_along_rig_z: float = 1.0,
    views: Sequence[DefectView | None] = (),
) -> list[Path]:
    """Write defects.csv and ``defects/defect_NN.png`` into ``out``; returns the files.

    Args:
        out: output folder (the pipeline's temporary folder; the manifest lists
            everything in it).
        summary: report.json content (diameter, stations).
        defects: the reported defects, in report.json's order.
        unrolled: the unrolled wall image, or None (no crops).
        survey: the survey header, or None.
        travel_along_rig_z: sign of the robot's motion along its first rig frame's z.
        views: each defect's camera view (``defects/defect_NN_camera.png``; its frame
            becomes ``best_view_frame``).
    """
    from omnipipe.dataset import write_image

    out = Path(out)
    rows = defect_rows(defects, summary, survey, travel_along_rig_z)
    written = []
    for row, view in zip(rows, views, strict=False):
        if view is None:
            continue
        (out / CROP_DIR).mkdir(exist_ok=True)
        path = out / CROP_DIR / f"defect_{int(row.values['defect']):02d}_camera.png"
        write_image(path, view.image)
        written.append(path)
        row.values["best_view_frame"] = str(view.frame)
        row.values["camera_view"] = f"{CROP_DIR}/{path.name}"
    if unrolled is not None and rows:
        (out / CROP_DIR).mkdir(exist_ok=True)
        for row in rows:
            crop = crop_unrolled(
                unrolled.image,
                unrolled.alpha,
                unrolled.axial_min_mm,
                unrolled.mm_per_px,
                row.defect,
                unrolled.circumference_mm,
            )
            path = out / row.values["crop"]
            write_image(path, crop)
            written.append(path)
    else:
        for row in rows:
            row.values["crop"] = ""
    write_defects_csv(out / CSV_NAME, rows, header_lines(summary, survey, travel_along_rig_z))
    written.insert(0, out / CSV_NAME)
    return written
