"""Lengths through unreliable motion: run length and later positions carry its length."""

from __future__ import annotations

import math

from omnipipe.pipeline.quality import flag_defects, widen_for_unreliable


def _fields() -> dict:
    return {
        "run_length_mm": 300.0,
        "run_length_sigma_mm": 0.8,
        "defects": [
            {"kind": "bulge", "axial_start_mm": 20.0, "length_mm": 10.0, "axial_start_sigma_mm": 0.3},
            {"kind": "dent", "axial_start_mm": 150.0, "length_mm": 30.0, "axial_start_sigma_mm": 0.4},
            {"kind": "dent", "axial_start_mm": 250.0, "length_mm": 5.0, "axial_start_sigma_mm": 0.5},
        ],
    }


def test_reliable_run_is_untouched() -> None:
    fields = _fields()
    assert widen_for_unreliable(fields, {"unreliable": []}) == []
    assert fields["run_length_sigma_mm"] == 0.8
    assert fields["run_length_unreliable_mm"] == 0.0
    assert [d["axial_start_sigma_mm"] for d in fields["defects"]] == [0.3, 0.4, 0.5]


def test_unreliable_stretches_widen_run_length_and_later_positions() -> None:
    quality = {
        "unreliable": [
            {"first_frame": 10, "last_frame": 14, "reason": "x", "axial_start_mm": 60.0, "axial_end_mm": 80.0},
            {"first_frame": 40, "last_frame": 41, "reason": "y", "axial_start_mm": 200.0, "axial_end_mm": 210.0},
        ]
    }
    fields = _fields()
    warnings = widen_for_unreliable(fields, quality)
    assert len(warnings) == 1 and "30 mm of unreliable motion" in warnings[0]
    assert fields["run_length_unreliable_mm"] == 30.0
    assert math.isclose(fields["run_length_sigma_mm"], math.hypot(0.8, 30.0), abs_tol=1e-3)
    before, middle, after = fields["defects"]
    assert before["axial_start_sigma_mm"] == 0.3  # upstream of every stretch
    assert math.isclose(middle["axial_start_sigma_mm"], math.hypot(0.4, 20.0), abs_tol=1e-3)
    assert math.isclose(after["axial_start_sigma_mm"], math.hypot(0.5, 30.0), abs_tol=1e-3)
    # None of them lies across a stretch.
    assert flag_defects(fields["defects"], quality) == []
