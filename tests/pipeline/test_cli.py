"""The reconstruct command's last line (pipeline.cli.closing_line)."""

from __future__ import annotations

from pathlib import Path

from omnipipe.pipeline.cli import closing_line


def _summary(**extra: object) -> dict:
    return {
        "warnings": ["w1"], "frames": 11, "frames_registered": 11, "inner_diameter_mm": 249.8123,
        "inner_diameter_sigma_mm": 0.034, "defects": [{}], "timings_s": {"total": 3.21},
        "trajectory_quality": {"steps_checked": 10, "unreliable": []}, **extra,
    }


def test_last_line_states_the_diameter_with_its_sigma_range_and_the_features() -> None:
    s = _summary(
        inner_diameter_min_mm=242.61, inner_diameter_max_mm=257.64,
        features=[{"kind": "joint"}, {"kind": "water"}, {"kind": "joint"}],
    )
    first, last = closing_line(s, Path("out")).split("\n")
    assert first == "warning: w1"
    assert "inner diameter 249.812 +- 0.034 mm (min 242.6, max 257.6)" in last
    assert "1 defect(s), features 2 joint, 1 water; 3.2 s; motion checked (10 of 10" in last


def test_last_line_without_features_or_range_says_neither() -> None:
    last = closing_line(_summary(inner_diameter_sigma_mm=None), Path("out")).split("\n")[-1]
    assert "inner diameter 249.81 mm, 1 defect(s), 3.2 s;" in last and "features" not in last
