"""defects.csv, defect crops and the survey header (omnipipe.report.deliverable, omnipipe.survey)."""

from __future__ import annotations

import csv
import io
from pathlib import Path
from types import SimpleNamespace

import numpy as np
import pytest

from omnipipe.cli import main
from omnipipe.contract import Defect
from omnipipe.errors import ConfigError
from omnipipe.report.deliverable import (
    CSV_COLUMNS,
    clock_position,
    crop_unrolled,
    default_clock_reference_deg,
    severity_grade,
    write_deliverable,
)
from omnipipe.survey import Survey, find_survey, load_survey, survey_from_dict


def _summary() -> dict:
    defect = {
        "kind": "bulge",
        "height_mm": 5.0,
        "width_mm": 10.0,
        "length_mm": 100.0,
        "axial_start_mm": 40.0,
        "angle_deg": 0.0,  # the first rig frame's +x axis: 3 o'clock looking along +z
        "height_sigma_mm": 0.05,
        "width_sigma_mm": 0.3,
        "length_sigma_mm": 0.8,
    }
    dent = {
        "kind": "dent",
        "height_mm": 25.0,
        "width_mm": 20.0,
        "length_mm": 30.0,
        "axial_start_mm": 200.0,
        "angle_deg": 270.0,  # -y: image up, 12 o'clock by default
        "motion_unreliable": True,
    }
    stations = [{"axial_mm": -82.0 + 12.5 * k, "frame": 2 * k} for k in range(40)]
    return {
        "inner_diameter_mm": 200.0,
        "inner_diameter_sigma_mm": 0.1,
        "defects": [defect, dent],
        "stations": stations,
    }


def _defects(summary: dict) -> list[Defect]:
    return [Defect.from_contract(d) for d in summary["defects"]]


def _read_csv(path: Path) -> tuple[list[str], list[dict[str, str]]]:
    lines = path.read_text(encoding="utf-8").splitlines()
    comments = [ln[2:] for ln in lines if ln.startswith("# ")]
    body = [ln for ln in lines if not ln.startswith("#")]
    return comments, list(csv.DictReader(io.StringIO("\n".join(body))))


def test_clock_positions_follow_the_documented_convention() -> None:
    ref = default_clock_reference_deg(+1.0)  # travel along +z: image up is -90 deg
    assert clock_position(-90.0, ref) == ("12:00", 0.0)
    assert clock_position(0.0, ref) == ("03:00", 90.0)
    assert clock_position(90.0, ref) == ("06:00", 180.0)
    assert clock_position(180.0, ref) == ("09:00", 270.0)
    assert clock_position(-75.0, ref)[0] == "12:30"  # 15 deg = 30 clock minutes
    # Travel along -z: angles run from x towards -y, so image up is +90 deg.
    assert clock_position(90.0, default_clock_reference_deg(-1.0))[0] == "12:00"


@pytest.mark.parametrize(
    ("height", "grade"), [(0.5, 1), (2.0, 2), (7.0, 3), (12.0, 4), (25.0, 5)]
)
def test_severity_bands(height: float, grade: int) -> None:
    got, pct = severity_grade(height, 200.0)
    assert got == grade
    assert pct == pytest.approx(height / 2.0)


def test_defects_csv_from_a_report(tmp_path: Path) -> None:
    survey = survey_from_dict(
        {"site": "Main St", "asset_id": "SW-1", "start_offset_m": 1.5, "direction": "upstream"}
    )
    files = write_deliverable(
        tmp_path, _summary(), _defects(_summary()), None, survey, travel_along_rig_z=1.0
    )
    assert files == [tmp_path / "defects.csv"]
    comments, rows = _read_csv(tmp_path / "defects.csv")
    assert "site: Main St" in comments and "direction: upstream" in comments
    assert any("no gravity reference" in c for c in comments)
    assert list(rows[0].keys()) == list(CSV_COLUMNS)
    bulge, dent = rows
    assert (bulge["kind"], bulge["clock"], float(bulge["clock_deg"])) == ("bulge", "03:00", 90.0)
    assert float(bulge["distance_start_m"]) == pytest.approx(1.5 + 0.040)
    assert float(bulge["distance_end_m"]) == pytest.approx(1.5 + 0.140)
    assert float(bulge["height_sigma_mm"]) == pytest.approx(0.05)
    assert (bulge["severity_grade"], bulge["height_pct_of_diameter"]) == ("2", "2.50")
    # Axial centre 90 mm: the ring at -82 + 12.5 * 14 = 93 mm is closest -> frame 28.
    assert bulge["best_view_frame"] == "28"
    assert bulge["crop"] == ""  # no unrolled image given
    assert (dent["clock"], dent["severity_grade"], dent["flags"]) == ("12:00", "5", "motion_unreliable")
    assert dent["height_sigma_mm"] == ""  # not estimated: empty, not zero


def test_clock_reference_from_survey(tmp_path: Path) -> None:
    survey = Survey(clock_reference_deg=0.0)  # +x is 12 o'clock
    write_deliverable(tmp_path, _summary(), _defects(_summary()), None, survey)
    comments, rows = _read_csv(tmp_path / "defects.csv")
    assert [r["clock"] for r in rows] == ["12:00", "09:00"]
    assert any("survey.yaml clock_reference_deg" in c for c in comments)


def test_crop_shows_the_defect_across_the_seam(tmp_path: Path) -> None:
    mm_per_px, circ = 0.5, 400.0
    h, w = 800, int(circ / mm_per_px)
    image = np.full((h, w, 3), 40, np.uint8)
    # A bright patch straddling angle 0 (the seam): columns -10..9, rows 200..299.
    image[200:300, -10:] = 250
    image[200:300, :10] = 250
    unrolled = SimpleNamespace(
        image=image,
        alpha=np.ones((h, w), bool),
        axial_min_mm=-100.0,
        mm_per_px=mm_per_px,
        circumference_mm=circ,
    )
    defect = {
        "kind": "bulge", "height_mm": 3.0, "width_mm": 10.0, "length_mm": 50.0,
        "axial_start_mm": 0.0, "angle_deg": 0.0,
    }
    crop = crop_unrolled(image, unrolled.alpha, -100.0, mm_per_px, Defect.from_contract(defect), circ)
    bright = crop[..., 2] > 245  # the patch (the outline is yellow: blue 0)
    rows, cols = np.nonzero(bright)
    assert bright.any()
    # The patch is centred in the crop in both directions (within 2 % of its size).
    assert abs(rows.mean() - crop.shape[0] / 2) < 0.02 * crop.shape[0]
    assert abs(cols.mean() - crop.shape[1] / 2) < 0.02 * crop.shape[1]
    # No sliver: a 5 x 100 mm bulge's crop is at least half as wide as it is long.
    long = Defect.from_contract(dict(defect, width_mm=5.0, length_mm=100.0))
    sliver = crop_unrolled(image, unrolled.alpha, -100.0, mm_per_px, long, circ)
    assert sliver.shape[0] >= 400 and 0.5 * sliver.shape[0] - 2 <= sliver.shape[1] <= 0.5 * sliver.shape[0] + 4
    summary = {"inner_diameter_mm": 127.3, "defects": [defect], "stations": []}
    files = write_deliverable(tmp_path, summary, _defects(summary), unrolled)
    assert [f.relative_to(tmp_path).as_posix() for f in files] == [
        "defects.csv",
        "defects/defect_01.png",
    ]
    assert _read_csv(tmp_path / "defects.csv")[1][0]["crop"] == "defects/defect_01.png"


def test_survey_yaml_valid_and_found_beside_the_dataset(tmp_path: Path) -> None:
    (tmp_path / "survey.yaml").write_text(
        "site: Main Street\nasset_id: 1042\nnominal_diameter_mm: 200\ndirection: Downstream\n"
        "date: 2024-05-01\nstart_offset_m: 0.35\nclock_reference_deg: -90\n",
        encoding="utf-8",
    )
    s = find_survey(tmp_path)
    assert s is not None
    assert (s.site, s.asset_id, s.nominal_diameter_mm) == ("Main Street", "1042", 200.0)
    assert (s.direction, s.date, s.start_offset_m, s.clock_reference_deg) == (
        "downstream", "2024-05-01", 0.35, 270.0
    )
    (tmp_path / "other").mkdir()
    assert find_survey(tmp_path / "other") is None
    assert find_survey(tmp_path / "run.mp4") == s  # a file: the survey beside it


@pytest.mark.parametrize(
    ("text", "field"),
    [
        ("direction: sideways\n", "direction"),
        ("nominal_diameter_mm: -200\n", "nominal_diameter_mm"),
        ("start_offset_m: .nan\n", "start_offset_m"),
        ("date: 2024-13-45\n", "date"),
        ("date: '1 May'\n", "date"),
        ("operatr: A. Smith\n", "operatr"),
        ("site: [a, b]\n", "site"),
        ("- a list\n", "survey"),
    ],
)
def test_bad_survey_field_is_named(tmp_path: Path, text: str, field: str) -> None:
    path = tmp_path / "survey.yaml"
    path.write_text(text, encoding="utf-8")
    with pytest.raises(ConfigError) as info:
        load_survey(path)
    assert info.value.field == field


def test_bad_survey_is_one_line_on_the_cli(tmp_path: Path, capsys) -> None:
    path = tmp_path / "s.yaml"
    path.write_text("direction: sideways\n", encoding="utf-8")
    code = main(["reconstruct", str(tmp_path / "ds"), "--out", str(tmp_path / "out"),
                 "--survey", str(path), "--quiet"])
    err = capsys.readouterr().err.strip().splitlines()
    assert code == 1
    assert len(err) == 1 and "direction" in err[0] and str(path) in err[0]
    assert not (tmp_path / "out").exists()


def test_report_html_has_survey_header_clock_crops_and_print_css() -> None:
    from omnipipe.report import ReportInputs, render_html

    summary = _summary()
    summary["survey"] = survey_from_dict(
        {"site": "Main St", "asset_id": "SW-1", "start_node": "MH-12", "start_offset_m": 1.5}
    ).to_dict()
    poses = np.repeat(np.eye(4)[None], 2, axis=0)
    poses[1, 2, 3] = 300.0  # travel along +z
    image = np.full((800, 1257, 3), 90, np.uint8)
    html_text = render_html(
        ReportInputs(
            summary=summary,
            world_from_rig=poses,
            unrolled=image,
            unrolled_extent=(0.0, 360.0, -100.0, 300.0),
            radius_mm=100.0,
            defects=_defects(summary),
        )
    )
    assert "<h2>Survey</h2>" in html_text and "SW-1" in html_text and "MH-12" in html_text
    assert "<td>03:00</td>" in html_text and "<td>12:00</td>" in html_text
    assert "1.5400 – 1.6400" in html_text  # distance of the bulge from the start node, m
    assert html_text.count("class='crop zoomable'") == 2  # one texture view per defect
    assert "clock from image up: no gravity reference" in html_text
    assert "@media print" in html_text and "break-inside:avoid" in html_text
    assert "<div class='screen-only'><h2>3-D model</h2>" in html_text


def test_truncated_defect_and_distances_without_a_survey(tmp_path: Path) -> None:
    """No survey.yaml: distances from the first measured ring (never negative inside the
    measured stretch); a truncated defect is flagged; sigmas of distance and clock."""
    summary = _summary()
    summary["defects"][0].update(
        axial_start_mm=-82.0, axial_start_sigma_mm=0.6, angle_sigma_deg=0.2, truncated=True
    )
    write_deliverable(tmp_path, summary, _defects(summary), None, None)
    comments, rows = _read_csv(tmp_path / "defects.csv")
    bulge = rows[0]
    assert bulge["distance_from"] == "first measured ring (no survey.yaml)"
    assert float(bulge["distance_start_m"]) == pytest.approx(0.0)
    assert float(bulge["distance_end_m"]) == pytest.approx(0.100)
    assert float(bulge["distance_start_sigma_m"]) == pytest.approx(0.0006)
    assert float(bulge["distance_end_sigma_m"]) == pytest.approx(np.hypot(0.6, 0.8) / 1000, abs=1e-4)
    assert float(bulge["clock_sigma_deg"]) == pytest.approx(0.2)
    assert bulge["flags"] == "truncated"
    assert bulge["clock_reference"] == "image up in the first frame: no gravity reference"
    assert any("truncated" in c for c in comments)
    assert all(float(r["distance_start_m"]) >= 0 for r in rows)


def test_clock_from_imu_gravity(tmp_path: Path) -> None:
    """The IMU's accelerometer at the first frame gives 12:00: up along the rig's +x is
    omnipipe angle 0, so a defect at angle 0 is at 12:00 and one at 270 deg at 9:00."""
    from omnipipe.inputs.sensors import make_imu
    from omnipipe.report.clock import clock_reference, imu_up

    rng = np.random.default_rng(0)
    t = np.arange(0.0, 5.0, 0.01)
    acc = np.array([9.81, 0.0, 0.3]) + rng.normal(0, 0.05, (len(t), 3))
    imu = make_imu("test", t, acc, None, str)
    found = imu_up(imu, 0.0)  # the recording starts at the frame: the first whole window
    assert found is not None
    up, sigma = found
    ref = clock_reference(None, up, 1.0, sigma)
    assert ref.gravity and ref.source == "gravity (imu.txt)"
    assert ref.angle_deg == pytest.approx(0.0, abs=1.0) and 0 < ref.sigma_deg < 1.0
    summary = _summary() | {"clock_reference": ref.to_dict()}
    write_deliverable(tmp_path, summary, _defects(summary), None, None)
    comments, rows = _read_csv(tmp_path / "defects.csv")
    assert [r["clock"] for r in rows] == ["12:00", "09:00"]
    assert any("the top of the pipe" in c for c in comments)
    # Up along the mirror axis: no clock position across it.
    assert imu_up(make_imu("axis", t, np.tile([0.0, 0.0, 9.81], (len(t), 1)), None, str), 1.0) is None
