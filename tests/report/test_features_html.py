"""report.html's features table: every kind, each value with its sigma."""

from __future__ import annotations

from omnipipe.analysis.feature_types import Joint, Water
from omnipipe.report.html import _features_section


def test_features_table_shows_point_and_stretch_features_with_sigmas() -> None:
    feats = [
        Joint(axial_mm=120.0, axial_sigma_mm=0.4, gap_mm=8.0, gap_sigma_mm=0.5, offset_mm=None).to_contract(),
        Water(axial_from_mm=0.0, axial_from_sigma_mm=2.0, axial_to_mm=300.0, axial_to_sigma_mm=2.0,
              depth_mm=40.0, depth_sigma_mm=0.6, truncated=True).to_contract(),
    ]
    out = _features_section({"features": feats})
    assert "120.00 ± 0.40 mm" in out and "gap_mm 8.00 ± 0.50" in out
    assert "offset_mm" not in out  # not measured: no cell
    assert "0.0 ± 2.0 to 300.0 ± 2.0 mm (truncated)" in out and "depth_mm 40.00 ± 0.60" in out
    assert _features_section({"features": []}) == ""
