"""features.csv: codes follow the documented PACP / EN 13508-2 mapping."""

from __future__ import annotations

import csv

from omnipipe.report.features_csv import codes, write_features


def test_codes_follow_the_mapping() -> None:
    d = 300.0
    assert codes({"kind": "joint", "offset_mm": 5.0, "offset_sigma_mm": 0.3, "gap_mm": 3.0}, d)[:2] == ("JOM", "BAJB")
    assert codes({"kind": "joint", "offset_mm": 20.0, "offset_sigma_mm": 0.3, "gap_mm": 3.0}, d)[0] == "JOL"
    # An offset within 2 sigma is not significant: the 8 mm gap makes it a separated joint.
    assert codes({"kind": "joint", "offset_mm": 1.2, "offset_sigma_mm": 0.8, "gap_mm": 8.0}, d)[:2] == ("JSM", "BAJA")
    assert codes({"kind": "joint", "offset_mm": 0.2, "offset_sigma_mm": 0.1, "gap_mm": 1.0}, d)[:2] == ("", "")
    assert codes({"kind": "lateral"}, d)[:2] == ("TF", "BCA")


def test_features_csv_rows(tmp_path) -> None:
    summary = {
        "inner_diameter_mm": 300.0,
        "features": [
            {"kind": "joint", "axial_mm": 120.0, "axial_sigma_mm": 1.0, "gap_mm": 8.0,
             "gap_sigma_mm": 1.0, "offset_mm": 5.0, "offset_sigma_mm": 0.3, "offset_angle_deg": 0.0},
            {"kind": "lateral", "axial_mm": 250.0, "angle_deg": -90.0, "diameter_mm": 100.0},
        ],
    }
    path = write_features(tmp_path, summary, None)
    rows = list(csv.DictReader(line for line in path.read_text().splitlines() if not line.startswith("#")))
    assert [r["pacp"] for r in rows] == ["JOM", "TF"]
    assert rows[0]["distance_m"] == "0.1200" and rows[1]["distance_m"] == "0.2500"
    # Default reference: 12:00 is angle -90 (the first rig frame's -y axis).
    assert rows[1]["clock"] == "12:00" and rows[0]["clock"] == "03:00"


def test_features_csv_uses_the_runs_clock_and_distance_origin(tmp_path) -> None:
    """As defects.csv: 12:00 from report.json's clock_reference (gravity), distances from
    the first measured ring without a survey (no negative distance inside the run), the
    survey's start node with one."""
    from omnipipe.survey import Survey

    summary = {
        "inner_diameter_mm": 300.0,
        "clock_reference": {"angle_deg": 90.0, "sigma_deg": 0.5, "source": "gravity (imu.txt)", "gravity": True},
        "stations": [{"axial_mm": -120.0}, {"axial_mm": 0.0}],
        "features": [{"kind": "lateral", "axial_mm": -45.0, "axial_sigma_mm": 2.0, "angle_deg": 30.0}],
    }

    def rows_and_comments():
        text = (tmp_path / "features.csv").read_text().splitlines()
        rows = list(csv.DictReader(line for line in text if not line.startswith("#")))
        return rows, [line for line in text if line.startswith("#")]

    write_features(tmp_path, summary, None)
    rows, comments = rows_and_comments()
    assert rows[0]["clock"] == "10:00"  # 30 deg is 60 deg anticlockwise of up (90 deg)
    assert rows[0]["distance_m"] == "0.0750"  # 75 mm after the first ring at -120 mm
    assert any("gravity (imu.txt)" in c for c in comments)
    assert any("from the first measured ring" in c for c in comments)
    write_features(tmp_path, summary, Survey(start_node="MH-1", start_offset_m=2.0))
    rows, comments = rows_and_comments()
    assert rows[0]["distance_m"] == "1.9550" and any("start_node: MH-1" in c for c in comments)
