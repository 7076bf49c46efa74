"""report.html's features table: every kind, each value with its sigma, distances and clock
positions in the defect table's conventions."""

from __future__ import annotations

from omnipipe.analysis.feature_types import Joint, Lateral, Water
from omnipipe.report.tables import features_section


def test_features_table_shows_point_and_stretch_features_with_sigmas() -> None:
    feats = [
        Joint(axial_mm=120.0, axial_sigma_mm=0.4, gap_mm=8.0, gap_sigma_mm=0.5, offset_mm=None).to_contract(),
        Water(axial_from_mm=0.0, axial_from_sigma_mm=2.0, axial_to_mm=300.0, axial_to_sigma_mm=2.0,
              depth_mm=40.0, depth_sigma_mm=0.6, truncated=True).to_contract(),
    ]
    out = features_section({"features": feats})
    assert "0.1200 ± 0.0004 m" in out and "gap_mm 8.00 ± 0.50" in out
    assert "offset_mm" not in out  # not measured: no cell
    assert "0.0000 ± 0.0020 – 0.3000 ± 0.0020 m (truncated)" in out and "depth_mm 40.00 ± 0.60" in out
    assert features_section({"features": []}) == ""


def test_features_table_reads_clock_and_distance_as_the_defects() -> None:
    """A lateral at omnipipe angle 30 deg with gravity's 12:00 at 90 deg is at 10:00; its
    distance counts from the first measured ring (no survey), never negative in the run."""
    lat = Lateral(axial_mm=-45.0, axial_sigma_mm=4.0, angle_deg=30.0, angle_sigma_deg=1.0,
                  diameter_mm=100.0, diameter_sigma_mm=3.0).to_contract()
    summary = {
        "features": [lat],
        "clock_reference": {"angle_deg": 90.0, "sigma_deg": 0.5, "source": "gravity (imu.txt)", "gravity": True},
        "stations": [{"axial_mm": -120.0}, {"axial_mm": 0.0}],
    }
    out = features_section(summary)
    assert "10:00 ± 1.0°" in out and "0.0750 ± 0.0040 m" in out
    assert "first measured ring" in out and "angle_deg" not in out


def test_no_negative_zero() -> None:
    from omnipipe.report.tables import value_pm

    assert value_pm(-0.00001, 0.0094, digits=4) == "0.0000 ± 0.0094"
    assert value_pm(-0.001, None) == "0.00" and value_pm(-0.01, None) == "-0.01"
