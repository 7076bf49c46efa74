"""benchmarks/bench_features.py's unseen joints (a gap no frame's true laser ring crossed
is counted outside the run: nothing of it was measured, never as missed) and the true
headline of a reducing run (the constant section most rings measured)."""

from __future__ import annotations

import math
import sys
from pathlib import Path

import numpy as np
import pytest

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "benchmarks"))
import bench_features as bench

R, LEAD = 150.0, 70.0  # pipe radius, laser plane behind the rig (mm)


def _dataset(tmp_path: Path, stations: list[float], tilt_deg: float) -> tuple[Path, dict]:
    """Frames at pipe arc ``stations`` (mm) in a straight pipe along world z, the rig
    tilted ``tilt_deg`` about x; the laser plane at rig z = -LEAD."""
    (tmp_path / "ground_truth").mkdir()
    h = math.radians(tilt_deg) / 2.0
    rows = [f"{i * 0.1:.1f} 0 0 {s + 200.0:.3f} {math.sin(h):.9f} 0 0 {math.cos(h):.9f}"
            for i, s in enumerate(stations)]
    (tmp_path / "ground_truth" / "poses.txt").write_text("\n".join(rows) + "\n")
    (tmp_path / "rig.yaml").write_text(f"laser:\n  plane: [0.0, 0.0, 1.0, {LEAD}]\n  channel: red\n")
    z = np.arange(-200.0, 1000.0, 10.0)
    truth = {
        "first_station_sigma_mm": 200.0,
        "centreline_polyline_mm": {"sigma": z.tolist(), "points": [[0.0, 0.0, float(v)] for v in z]},
        "stations": [{"axial_mm": float(v - 200.0), "inner_diameter_mm": 2 * R} for v in z],
    }
    return tmp_path, truth


@pytest.mark.parametrize("tilt_deg", [0.0, 3.0])
def test_ring_spans_follow_the_laser_plane_and_its_tilt(tmp_path: Path, tilt_deg: float) -> None:
    data, truth = _dataset(tmp_path, [0.0, 40.0], tilt_deg)
    spans = bench._ring_spans(data, truth)
    assert spans is not None and len(spans) == 2
    for (lo, hi, mid, d), s in zip(spans, [0.0, 40.0], strict=True):
        assert abs(0.5 * (lo + hi) - (s - LEAD)) < 0.5 and abs(mid - (s - LEAD)) < 0.5
        assert abs((hi - lo) - 2 * R * math.tan(math.radians(tilt_deg))) < 0.3
        assert abs(d - 2 * R) < 1e-9


def test_a_gap_between_rings_is_unseen_unless_offset(tmp_path: Path) -> None:
    data, truth = _dataset(tmp_path, [0.0, 40.0], 1.0)
    spans = bench._ring_spans(data, truth)
    between = {"kind": "joint", "axial_mm": 20.0 - LEAD, "gap_mm": 5.0, "offset_mm": 0.0}
    crossed = {**between, "axial_mm": 40.0 - LEAD}
    assert bench._unseen(between, spans)
    assert not bench._unseen(crossed, spans)
    assert not bench._unseen({**between, "offset_mm": 2.0}, spans)  # its offset shows in the wall


def test_the_true_headline_of_a_reducing_run_is_its_longer_section(tmp_path: Path) -> None:
    """Seven rings, two before a 300 -> 260 mm reducer, one on its ramp, four after it:
    the truth is the narrow section's 260 mm (the median ring would read the ramp's 280
    on a run placed a few mm off); without a taper, the median of the rings."""
    data, truth = _dataset(tmp_path, [0.0, 10.0, 40.0, 70.0, 80.0, 90.0, 100.0], 0.0)
    z = np.array(truth["centreline_polyline_mm"]["sigma"]) - 200.0
    truth["stations"] = [{"axial_mm": float(v), "inner_diameter_mm": float(np.interp(v, [-40.0, -20.0], [300.0, 260.0]))}
                         for v in z]
    truth["features"] = [{"kind": "taper", "axial_from_mm": -40.0, "axial_to_mm": -20.0}]
    spans = bench._ring_spans(data, truth)
    assert spans is not None
    assert abs(bench._headline_truth(truth, spans) - 260.0) < 1e-6
    truth["features"] = []
    assert abs(bench._headline_truth(truth, spans) - 260.0) < 1e-6  # four of seven at 260
    assert abs(bench._headline_truth({"features": []}, spans[:3]) - 300.0) < 1e-6


def test_a_stretch_beside_the_true_one_is_false_not_found() -> None:
    """A reported stretch touching the true one by a few mm (ovality-bench seeds 1 and 11:
    overlaps of 1-2 mm) matches nothing; one covering most of it matches."""
    true = {"kind": "ovality", "axial_from_mm": -120.0, "axial_to_mm": -20.0}
    beside = {"kind": "ovality", "axial_from_mm": -159.0, "axial_to_mm": -118.0}
    inside = {"kind": "ovality", "axial_from_mm": -110.0, "axial_to_mm": -40.0}
    assert bench._match(true, [beside]) is None
    assert bench._match(true, [beside, inside]) is inside
    assert bench._match(true, [{**inside, "kind": "water"}]) is None


def test_the_listing_gives_each_joint_and_lateral_its_signed_error_or_why_not_counted(tmp_path: Path) -> None:
    """``--list``: found - true axial (mm) and a lateral's clock error; a miss; a joint
    under the issue's class, one outside the stations and one no true ring crossed are
    listed as not counted; a reported joint matching no true one is FALSE."""
    data, truth = _dataset(tmp_path, [0.0, 40.0], 1.0)
    spans = bench._ring_spans(data, truth)
    seen = {"kind": "joint", "axial_mm": 40.0 - LEAD, "gap_mm": 5.0, "offset_mm": 0.0}
    truth["inner_diameter_mm"] = 2 * R
    truth["features"] = [
        seen,
        {**seen, "axial_mm": 20.0 - LEAD},  # between the rings: unseen
        {**seen, "axial_mm": -60.0, "gap_mm": 1.0},  # under the class
        {"kind": "lateral", "axial_mm": -10.0, "angle_deg": 350.0, "diameter_mm": 80.0},
        {**seen, "axial_mm": 300.0},  # beyond the stations
    ]
    report = {
        "stations": [{"axial_mm": -100.0}, {"axial_mm": 100.0}],
        "features": [
            {"kind": "joint", "axial_mm": 40.0 - LEAD + 1.5},
            {"kind": "lateral", "axial_mm": -12.0, "angle_deg": 5.0},
            {"kind": "joint", "axial_mm": 80.0},
        ],
    }
    lines = bench._listing(7, report, truth, spans)
    assert lines[0].endswith("+1.5 mm")
    assert lines[1].endswith("MISS (not counted: unseen)")
    assert lines[2].endswith("MISS (not counted: below the class)")
    assert lines[3].endswith("-2.0 mm, clock +15.0 deg")
    assert lines[4].endswith("MISS (not counted: outside)")
    assert lines[5] == "  s7 joint   at     80.0: FALSE"
    assert len(lines) == 6
