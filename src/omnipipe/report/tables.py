"""The page's HTML sections other than the figures' images and the 3-D view: the survey
header, the summary rows (measurements, camera motion check, calibration), the
measured-vs-true table, the defect table with each defect's views, the features table, the
figures' section and the files table; :func:`value_pm` writes a value with its 1-sigma.
"""

from __future__ import annotations

import html
import math
from typing import TYPE_CHECKING, Any

from omnipipe.report.encode import collected, png_data_uri
from omnipipe.report.inputs import ReportInputs, survey_of, travel_sign
from omnipipe.report.plots import defect_relief

if TYPE_CHECKING:
    from collections.abc import Sequence

    from omnipipe.contract import Defect, TrajectoryQuality


def value_pm(value: float | None, sigma: float | None, *, plain: str = "±", digits: int = 2) -> str:
    """``value ± sigma`` with as many decimals as the sigma needs (at least ``digits``
    when it is large, 3 when it is under 0.1); "-" without a value, the value alone
    without a sigma."""
    if value is None or not isinstance(value, int | float) or not math.isfinite(value):
        return "-"
    if sigma is None or not isinstance(sigma, int | float) or not math.isfinite(sigma):
        return f"{round(value, digits) + 0.0:.{digits}f}"  # (+ 0.0: never "-0.00")
    nd = max(digits, 3 if sigma < 0.1 else 2) if sigma < 1 else max(1, digits - 1)
    return f"{round(value, nd) + 0.0:.{nd}f} {plain} {sigma:.{nd}f}"


def _fmt(value: Any, digits: int = 2) -> str:
    if value is None:
        return "–"
    if isinstance(value, float):
        return f"{value:.{digits}f}"
    return html.escape(str(value))


_SURVEY_LABELS = (
    ("site", "site"),
    ("asset_id", "asset ID"),
    ("pipe_material", "pipe material"),
    ("nominal_diameter_mm", "nominal diameter (mm)"),
    ("start_node", "start node"),
    ("end_node", "end node"),
    ("direction", "direction"),
    ("start_offset_m", "start node to first frame (m)"),
    ("operator", "operator"),
    ("date", "date"),
)


def survey_html(survey: dict[str, Any] | None) -> str:
    """The survey header (survey.yaml) as a two-column table, or '' without one."""
    if not survey:
        return ""
    rows = [
        f"<tr><td>{label}</td><td>{_fmt(survey.get(key))}</td></tr>"
        for key, label in _SURVEY_LABELS
        if survey.get(key) is not None
    ]
    return "<h2>Survey</h2><table class='survey'>" + "".join(rows) + "</table>" if rows else ""


def _defect_extras(inputs: ReportInputs) -> tuple[list[list[str]], list[str]]:
    """Per defect: the table's cells (clock, distance, grade, link to its views) and its
    views' card (relief map, wall texture, camera view; each enlarges when clicked)."""
    from omnipipe.report.deliverable import defect_rows

    rows = defect_rows(inputs.defects, inputs.summary, survey_of(inputs.summary), travel_sign(inputs))
    cells, cards = [], []
    for k, row in enumerate(rows):
        v = row.values
        views = _defect_views_html(inputs, row.defect, k)
        sig = v["clock_sigma_deg"]
        end_sig = v["distance_end_sigma_m"]
        cells.append(
            [
                f"{v['clock']}" + (f" ± {sig}°" if sig else ""),
                f"{v['distance_start_m']} – {v['distance_end_m']}" + (f" ± {end_sig}" if end_sig else ""),
                v["severity_grade"],
                f"<a href='#views-{k + 1}'>views</a>" if views else "",
            ]
        )
        if views:
            d = row.defect
            head = (
                f"#{k + 1} {html.escape(d.kind)} at {v['clock']}, {v['distance_start_m']} – "
                f"{v['distance_end_m']} m from the {html.escape(v['distance_from'])}: "
                f"{'≥ ' if d.truncated else ''}{d.height_mm:.2f} mm high"
                + (" <span class='warn'>(truncated: runs past the measured stretch)</span>" if d.truncated else "")
            )
            cards.append(f"<div class='card keep' id='views-{k + 1}'><h3>{head}</h3>{''.join(views)}</div>")
    return cells, cards


def _defect_views_html(inputs: ReportInputs, d: Defect, k: int) -> list[str]:
    """The ``<figure>`` of each view of defect ``d`` (number ``k + 1``)."""
    views = []
    if inputs.wall is not None:
        views.append(
            _figure_html(collected(defect_relief(inputs, d, k)), "relief map: deviation from the fitted wall (mm)")
        )
    if inputs.unrolled is not None and inputs.unrolled_extent is not None and inputs.radius_mm:
        from omnipipe.report.deliverable import crop_unrolled

        ext = inputs.unrolled_extent
        crop = crop_unrolled(
            inputs.unrolled, inputs.unrolled_alpha, ext[2], (ext[3] - ext[2]) / inputs.unrolled.shape[0], d,
            2 * math.pi * inputs.radius_mm,
        )
        views.append(_figure_html(png_data_uri(crop), "wall texture (unrolled)"))
    view = inputs.defect_views[k] if k < len(inputs.defect_views) else None
    if view is not None:
        views.append(_figure_html(png_data_uri(view.image), f"camera view, frame {view.frame}"))
    return views


def _figure_html(uri: str, caption: str) -> str:
    return f"<figure>{_zoomable(uri, caption)}<figcaption>{html.escape(caption)}</figcaption></figure>"


def _zoomable(uri: str, alt: str) -> str:
    """An image that opens large when clicked (the page's zoom overlay)."""
    return f"<img class='crop zoomable' alt='{html.escape(alt)}' title='click to enlarge' src='{uri}'>"


def summary_rows(s: dict[str, Any]) -> str:
    """The summary table's rows of the measurements and the processing time."""
    rows = [
        f"<tr><td>frames</td><td>{_fmt(s.get('frames'))}</td></tr>",
        f"<tr><td>frames registered</td><td>{_fmt(s.get('frames_registered'))}</td></tr>",
        "<tr><td>inner diameter</td><td>"
        f"{value_pm(s.get('inner_diameter_mm'), s.get('inner_diameter_sigma_mm'))} mm</td></tr>",
    ]
    if s.get("run_length_mm") is not None:
        rows.append(
            "<tr><td>measured length of pipe</td><td>"
            f"{value_pm(s['run_length_mm'], s.get('run_length_sigma_mm'), digits=1)} mm</td></tr>"
        )
    if s.get("detection_limit_mm") is not None:
        ref = s.get("detection_limit_reference_mm") or {}
        size = (
            f" (smallest height reported; a defect {ref['width']:g} mm wide and {ref['length']:g} mm "
            "long this high rises above the detector's threshold with 95 % probability)"
            if ref.get("width") and ref.get("length")
            else ""
        )
        rows.append(
            f"<tr><td>detection limit</td><td>{_fmt(s['detection_limit_mm'])} mm high{size}</td></tr>"
        )
    if s.get("wall_noise_mm") is not None:
        rows.append(f"<tr><td>wall noise (1 sigma)</td><td>{_fmt(s['wall_noise_mm'], 3)} mm</td></tr>")
    if s.get("ovality_max") is not None:
        rows.append(f"<tr><td>largest ovality</td><td>{_fmt(100 * s['ovality_max'])} %</td></tr>")
    if s.get("timings_s"):
        t = s["timings_s"]
        rows.append(
            "<tr><td>processing time</td><td>"
            + ", ".join(f"{k} {v:.1f} s" for k, v in t.items())
            + "</td></tr>"
        )
    return "".join(rows)


def motion_rows(s: dict[str, Any], q: TrajectoryQuality | None) -> str:
    """The summary table's rows of the camera motion check and the metric scale."""
    if q is None:
        return ""
    bad = q.unreliable
    steps = max(int(s.get("frames") or 1) - 1, 0)
    verdict = (
        f"<span class='warn'>UNRELIABLE in {len(bad)} stretch(es): frames "
        + ", ".join(f"{u.first_frame}-{u.last_frame}" for u in bad)
        + " (marked red on the unrolled wall and the trajectory)</span>"
        if bad
        else "every moving step confirmed by two scale sources"
    )
    rows = [
        f"<tr><td>camera motion check</td><td>{_fmt(q.steps_checked)} of {steps} frame "
        f"steps verified; {verdict}</td></tr>"
    ]
    if q.scale_source:
        gap, sigma = q.wall_scale_gap_pct, q.scale_sigma_pct
        rows.append(
            f"<tr><td>metric scale</td><td>{html.escape(str(q.scale_source))}"
            + (f"; 1-sigma {sigma:.2f} % of every length along the pipe" if sigma is not None else "")
            + (f"; wall vs laser before combining {gap:+.2f} %" if gap is not None else "")
            + "</td></tr>"
        )
    return "".join(rows)


def calibration_row(s: dict[str, Any]) -> str:
    """The summary table's row of the rig calibration's share of the uncertainties."""
    cal = s.get("calibration_sigma_rel")
    return (
        "<tr><td>rig calibration</td><td>"
        + (
            f"1-sigma {100 * cal:.3f} % of every length (rig.yaml laser.offset_sigma_mm), "
            "included in every uncertainty"
            if cal
            else "rig.yaml states no calibration uncertainty: the uncertainties above exclude it"
        )
        + "</td></tr>"
    )


def truth_table(truth: Sequence[tuple[Any, ...]] | None) -> str:
    """The measured-vs-true table (the paper's Table I), or '' without ground truth."""
    if not truth:
        return ""
    parts = [
        "<h2>Measured vs true (the paper's Table I)</h2><table><tr><th></th>"
        "<th>measured ± 1 sigma</th><th>true</th><th>error</th><th>error / sigma</th></tr>"
    ]
    for row in truth:
        name, meas, sig, true, unit = row if len(row) == 5 else (row[0], row[1], None, *row[2:])
        err = None if meas is None or true is None else meas - true
        z = "" if err is None or not sig else f"{err / sig:+.1f}"
        parts.append(
            f"<tr><td>{html.escape(name)}</td><td>{value_pm(meas, sig)} {unit}</td>"
            f"<td>{_fmt(true)} {unit}</td>"
            f"<td>{'' if err is None else f'{err:+.2f} {unit}'}</td><td>{z}</td></tr>"
        )
    parts.append("</table>")
    return "".join(parts)


def trajectory_note(ev: dict[str, Any] | None) -> str:
    """The trajectory's errors against ground truth, or ''."""
    if not ev or not ev.get("trajectory"):
        return ""
    tr = ev["trajectory"]
    return (
        "<p class='note'>Trajectory against ground truth: ATE "
        f"{tr['ate_rmse_mm']:.3f} mm RMS, scale error {tr['scale_error_percent']:.3f} %, rotation "
        f"{tr['rotation_rmse_deg']:.3f} deg RMS over {tr['path_length_mm']:.0f} mm.</p>"
    )


_DEFECT_COLUMNS = (
    "<table><thead><tr><th>#</th><th>kind</th><th>height (mm)</th><th>width (mm)</th><th>length (mm)</th>"
    "<th>clock</th><th>distance (m)</th>"
    "<th>grade</th><th>views</th></tr></thead>"
)


def _feature_cells(f: dict[str, Any], reference_deg: float, offset_m: float) -> tuple[str, str, str]:
    """(distance, clock, sizes) cells of one report.json feature, in the defect table's
    conventions (metres from the distance origin, clock positions); each value with its
    sigma."""
    from omnipipe.report.deliverable import clock_position

    def pm(key: str) -> str:
        sig = f.get(key.replace("_mm", "_sigma_mm").replace("_deg", "_sigma_deg") if key != "percent" else "percent_sigma")
        return value_pm(f[key], sig, digits=2)

    def metres(key: str) -> str:
        sig = f.get(key.replace("_mm", "_sigma_mm"))
        return value_pm(offset_m + float(f[key]) / 1000.0, None if sig is None else float(sig) / 1000.0, digits=4)

    if f.get("axial_mm") is not None:
        where = metres("axial_mm") + " m"
    else:
        where = f"{metres('axial_from_mm')} – {metres('axial_to_mm')} m" + (" (truncated)" if f.get("truncated") else "")
    if f.get("motion_unreliable"):
        where += " (on unreliable camera motion)"
    angle_key = "angle_deg"
    if f.get("kind") == "joint":  # a joint's clock: its offset's direction, when significant
        off, osig = f.get("offset_mm") or 0.0, f.get("offset_sigma_mm") or 0.0
        angle_key = "offset_angle_deg" if off > 2.0 * osig else ""
    clock = ""
    if angle_key and isinstance(f.get(angle_key), int | float):
        clock = clock_position(float(f[angle_key]), reference_deg)[0]
        sig = f.get(angle_key.replace("_deg", "_sigma_deg"))
        clock += "" if sig is None else f" ± {float(sig):.1f}°"
    skip = {"kind", "axial_mm", "axial_from_mm", "axial_to_mm", "truncated", "points", "angle_deg", "offset_angle_deg"}
    sizes = [
        f"{k} {pm(k)}" for k, v in f.items()
        if k not in skip and "_sigma" not in k and isinstance(v, (int, float)) and not isinstance(v, bool)
    ]
    if isinstance(f.get("turn_motion_sigma_deg"), int | float):  # a bend's share of the motion's rotation
        sizes.append(f"of the turn's sigma the camera motion's rotation (gyro) {float(f['turn_motion_sigma_deg']):.2f}°")
    return html.escape(where), html.escape(clock), html.escape(", ".join(sizes))


def features_section(s: dict[str, Any], travel_along_rig_z: float = 1.0) -> str:
    """The features' table (report.json ``features``: joints, laterals, bends, tapers,
    ovality and water stretches; features.csv codes them): distances and clock positions
    as the defect table's."""
    from omnipipe.report.deliverable import distance_origin, run_clock

    feats = s.get("features") or []
    if not feats:
        return ""
    survey = survey_of(s)
    reference = run_clock(s, survey, travel_along_rig_z).angle_deg
    origin = distance_origin(s, survey)
    rows = "".join(
        f"<tr><td>{html.escape(str(f.get('kind')))}</td><td>{a}</td><td>{b}</td><td>{c}</td></tr>"
        for f in feats
        for a, b, c in [_feature_cells(f, reference, origin.offset_m)]
    )
    return (
        "<h3 id='features'>Features (parts of the pipe, not defects)</h3>"
        f"<table><tr><th>kind</th><th>distance (m) from the {html.escape(origin.name)}</th>"
        f"<th>clock</th><th>sizes (± 1 sigma)</th></tr>{rows}</table>"
    )


def defects_section(inputs: ReportInputs) -> str:
    """The defect table and its note, or the sentence that none was found."""
    s = inputs.summary
    if not inputs.defects:
        limit = s.get("detection_limit_mm")
        return (
            "<p>No bulges or dents"
            + ("" if limit is None else f" {_fmt(limit)} mm high or more")
            + " were found.</p>"
        )
    extra, cards = _defect_extras(inputs)
    parts = [_DEFECT_COLUMNS]
    for k, d in enumerate(inputs.defects):
        cells = [
            value_pm(value, sigma, digits=nd)
            for value, sigma, nd in (
                (d.height_mm, d.height_sigma_mm, 2),
                (d.width_mm, d.width_sigma_mm, 2),
                (d.length_mm, d.length_sigma_mm, 2),
            )
        ]
        if d.truncated:
            cells = ["≥ " + c for c in cells]
        kind = html.escape(d.kind) + (
            " <span class='warn'>(across unreliable motion)</span>" if d.motion_unreliable else ""
        ) + (
            " <span class='warn'>TRUNCATED: runs past the measured stretch; sizes are lower bounds</span>"
            if d.truncated
            else ""
        )
        cells += extra[k] if k < len(extra) else ["", "", "", ""]
        parts.append(
            f"<tr id='defect-{k + 1}'><td>{k + 1}</td><td>{kind}</td>" + "".join(f"<td>{c}</td>" for c in cells) + "</tr>"
        )
    parts.append("</table>")
    from omnipipe.report.deliverable import distance_origin, run_clock

    clock = run_clock(s, survey_of(s), travel_sign(inputs))
    origin = distance_origin(s, survey_of(s))
    parts.append(
        "<p class='note'>clock: looking in the direction of travel, clockwise; 12:00 = "
        + (
            f"the top of the pipe ({html.escape(clock.source)})"
            if clock.gravity
            else "<span class='warn'>clock from image up: no gravity reference</span> (the first "
            "frame's image up; give survey.yaml clock_reference_deg or imu.txt)"
        )
        + f". distance: metres along the pipe from the {html.escape(origin.name)} to the defect's "
        "start and end (± 1 sigma of the end). grade: height as % "
        "of the inner diameter, omnipipe's bands (docs/inspection_coding.md), not an official "
        "PACP / EN 13508-2 grade. views: the relief map (deviation from the fitted wall, mm; blue "
        "into the pipe), the wall texture around the defect and the camera's own view (a "
        "perspective crop of the frame that sees it closest, defects.csv best_view_frame), its "
        "half-height extent outlined (dashed: truncated); click a view to enlarge it. "
        "report.json keeps the angle in degrees "
        "from the first rig frame's x axis (angle_deg).</p>"
    )
    if cards:
        parts.append("<h2>Defect views</h2>" + "".join(cards))
    return "".join(parts)


def figures(plots: dict[str, str], holes: bool = False) -> str:
    """The unrolled wall, the diameter profile and the trajectory (those drawn); ``holes``:
    the unrolled wall has cells with no wall (hatched, and said so)."""
    parts = []
    if "unrolled" in plots or "relief" in plots:
        parts.append("<h2>Unrolled wall</h2>")
        if "unrolled" in plots and "relief" in plots:
            parts.append(
                "<p class='screen-only'><label><input type='radio' name='wallmode' checked "
                "onclick=\"wallMode('texture')\"> texture</label> <label><input type='radio' "
                "name='wallmode' onclick=\"wallMode('relief')\"> deviation map (mm)</label></p>"
            )
        if "unrolled" in plots:
            parts.append(f"<img id='unrolled' class='zoomable' alt='unrolled wall' src='{plots['unrolled']}'>")
            if holes:
                parts.append(
                    "<p class='note'>Hatched grey: no wall there (a joint's gap, a lateral's opening, "
                    "or wall no frame saw); nothing is painted into it.</p>"
                )
        if "relief" in plots:
            hidden = " style='display:none'" if "unrolled" in plots else ""
            parts.append(
                f"<img id='relief' class='zoomable' alt='deviation map'{hidden} src='{plots['relief']}'>"
            )
    if "profile" in plots:
        parts.append(
            "<h2>Diameter and ovality along the pipe</h2>"
            f"<img id='profile' alt='diameter profile' src='{plots['profile']}'>"
        )
    if "trajectory" in plots:
        parts.append(
            f"<h2>Trajectory</h2><img id='trajectory' alt='trajectory' src='{plots['trajectory']}'>"
        )
    return "".join(parts)


def files_table(files: dict[str, dict[str, Any]] | None) -> str:
    """Each 3-D file's unit and axes (report.json ``files``), or ''."""
    if not files:
        return ""
    return (
        "<h2>Files</h2><table><thead><tr><th>file</th><th>unit</th><th>axes</th>"
        "<th>stated in the file</th></tr></thead>"
        + "".join(
            "<tr>" + "".join(f"<td>{html.escape(str(c))}</td>" for c in (n, *f.values())) + "</tr>"
            for n, f in files.items()
        )
        + "</table>"
    )
