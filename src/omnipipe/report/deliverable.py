"""The inspector's deliverable: ``defects.csv``, one crop image per defect, survey header.

Written by :func:`omnipipe.pipeline.write` beside report.json (docs/inspection_coding.md
explains each column and how it maps to NASSCO PACP and EN 13508-2).

Conventions (also written as ``#`` comment lines at the top of defects.csv):

- **Clock position**: viewed looking in the survey direction (the robot's direction of
  travel), clockwise from 12 o'clock. omnipipe has no gravity reference: 12 o'clock is
  the first rig frame's -y axis (image up) unless survey.yaml gives
  ``clock_reference_deg`` (the omnipipe angle, degrees from the first rig frame's x axis
  towards y, that is 12 o'clock). ``clock_deg`` is 0-360 clockwise from 12; ``clock``
  is ``hh:mm`` (1 hour = 30 degrees, 1 minute = 0.5 degree; 12:00 = top).
- **Distance**: metres from the survey's start node along the pipe in the direction of
  travel: ``start_offset_m`` (survey.yaml; 0 without one) + the axial position of the
  defect's start (``distance_start_m``) and end (``distance_end_m``). The axial origin
  is the first frame's mirror focus.
- **Severity grade** 1-5 from the defect height as a percentage of the inner diameter
  (:data:`SEVERITY_BANDS_PCT`): bands chosen by omnipipe in the manner of PACP's
  structural grades (1 = minor ... 5 = most severe); they are not an official PACP or
  EN 13508-2 grading and must be reviewed by a certified inspector.
- **Best view**: the frame whose laser ring passed closest to the defect's axial centre.
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

if TYPE_CHECKING:
    import numpy as np

    from omnipipe.contract import Defect
    from omnipipe.model.texture import UnrolledImage
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
    "distance_start_m",
    "distance_end_m",
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
    "flags",
)

# Margin around the defect in a crop: this fraction of its size, at least MIN_MARGIN_MM.
CROP_MARGIN = 0.5
MIN_MARGIN_MM = 15.0


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


def clock_position(angle_deg: float, reference_deg: float) -> tuple[str, float]:
    """(``"hh:mm"``, degrees clockwise from 12) of an omnipipe angle.

    Args:
        angle_deg: degrees from the first rig frame's x axis towards y, in the frame
            whose third axis is the direction of travel (report.json ``angle_deg``);
            increasing angles run clockwise as seen looking along the travel direction.
        reference_deg: the angle that is 12 o'clock.
    """
    clock_deg = (angle_deg - reference_deg) % 360.0
    minutes = round(clock_deg * 2.0) % 720  # 0.5 degree per clock minute
    hours, mins = divmod(minutes, 60)
    return f"{hours or 12:02d}:{mins:02d}", clock_deg


def default_clock_reference_deg(travel_along_rig_z: float = 1.0) -> float:
    """The omnipipe angle of the first rig frame's -y axis (image up).

    The angle is measured around the direction of travel from x towards the axis that
    completes a right-handed frame: y when the robot moves along +z of its rig frame,
    -y when along -z. ``travel_along_rig_z``: the sign of that motion.
    """
    return -90.0 if travel_along_rig_z >= 0 else 90.0


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


def defect_rows(
    defects: Sequence[Defect],
    summary: dict[str, Any],
    survey: Survey | None = None,
    travel_along_rig_z: float = 1.0,
) -> list[DefectRow]:
    """The rows of defects.csv.

    Args:
        defects: the reported defects, in report.json's order.
        summary: report.json content (``inner_diameter_mm``, ``stations``).
        survey: start offset and clock reference (None: offset 0, image up = 12).
        travel_along_rig_z: sign of the robot's motion along its first rig frame's z.
    """
    offset_m = survey.start_offset_m if survey is not None else 0.0
    ref = None if survey is None else survey.clock_reference_deg
    if ref is None:
        ref = default_clock_reference_deg(travel_along_rig_z)
    diameter = summary.get("inner_diameter_mm")
    stations = summary.get("stations") or []
    rows = []
    for k, d in enumerate(defects, start=1):
        clock, clock_deg = clock_position(d.angle_deg, ref)
        start, length = d.axial_start_mm, d.length_mm
        grade, pct = severity_grade(d.height_mm, diameter)
        frame = best_view_frame(start + 0.5 * length, stations)
        flags = ["motion_unreliable"] if d.motion_unreliable else []
        values = {
            "defect": str(k),
            "kind": d.kind,
            "clock": clock,
            "clock_deg": _fmt(clock_deg, 1),
            "distance_start_m": _fmt(offset_m + start / 1000.0, 4),
            "distance_end_m": _fmt(offset_m + (start + length) / 1000.0, 4),
            "height_pct_of_diameter": _fmt(pct, 2),
            "severity_grade": "" if grade is None else str(grade),
            "best_view_frame": "" if frame is None else str(frame),
            "crop": f"{CROP_DIR}/defect_{k:02d}.png",
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
    summary: dict[str, Any], survey: Survey | None, reference_deg: float
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
    lines += [
        "clock: viewed looking in the direction of travel, clockwise; 12:00 = omnipipe angle "
        f"{reference_deg:.1f} deg ("
        + (
            "survey.yaml clock_reference_deg"
            if survey is not None and survey.clock_reference_deg is not None
            else "the first rig frame's -y axis, image up: no gravity reference"
        )
        + ")",
        "distance_*_m: from the start node along the pipe (survey start_offset_m + axial "
        "position from the first frame's mirror focus)",
        "severity_grade: height as % of the inner diameter, bands "
        + ", ".join(
            f"<{b:g} %: {g}" for b, g in SEVERITY_BANDS_PCT
        )
        + ", else 5 (omnipipe's bands, not an official PACP/EN 13508-2 grade)",
        "*_sigma_mm: 1-sigma standard uncertainty; empty where not estimated",
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
    """
    from omnipipe.dataset import write_image

    out = Path(out)
    rows = defect_rows(defects, summary, survey, travel_along_rig_z)
    ref = survey.clock_reference_deg if survey is not None else None
    if ref is None:
        ref = default_clock_reference_deg(travel_along_rig_z)
    written = []
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
    write_defects_csv(out / CSV_NAME, rows, header_lines(summary, survey, ref))
    written.insert(0, out / CSV_NAME)
    return written
