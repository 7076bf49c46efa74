"""Lengths through unreliable motion: run length and later positions carry its length."""

from __future__ import annotations

import math
from types import SimpleNamespace

import pytest

from omnipipe.errors import ReconstructionError
from omnipipe.pipeline.quality import flag_defects, refuse_untrusted_motion, widen_for_unreliable
from omnipipe.sfm.scale_check import StepCheck


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
    assert len(warnings) == 1 and "about 30 mm" in warnings[0]
    assert fields["run_length_unreliable_mm"] == 30.0
    assert math.isclose(fields["run_length_sigma_mm"], math.hypot(0.8, 30.0), abs_tol=1e-3)
    before, middle, after = fields["defects"]
    assert before["axial_start_sigma_mm"] == 0.3  # upstream of every stretch
    assert math.isclose(middle["axial_start_sigma_mm"], math.hypot(0.4, 20.0), abs_tol=1e-3)
    assert math.isclose(after["axial_start_sigma_mm"], math.hypot(0.5, 30.0), abs_tol=1e-3)
    # None of them lies across a stretch.
    assert flag_defects(fields["defects"], quality) == []


def test_collapsed_stretch_counts_its_expected_length() -> None:
    # Steps without any relative motion collapse in the adjustment (0.2 mm for 21 mm):
    # the stretch counts as its unreliable steps times the median trusted step.
    steps = [
        {"first_frame": 0, "last_frame": 5, "confidence": "high", "scale_mm": 10.0},
        {"first_frame": 5, "last_frame": 9, "confidence": "none", "scale_mm": None},
        {"first_frame": 9, "last_frame": 14, "confidence": "none", "scale_mm": None},
        {"first_frame": 14, "last_frame": 19, "confidence": "resolved", "scale_mm": 12.0},
    ]
    quality = {
        "keyframe_steps": steps,
        "unreliable": [
            {"first_frame": 5, "last_frame": 14, "reason": "x", "axial_start_mm": 10.0, "axial_end_mm": 10.3},
        ],
    }
    fields = _fields()
    widen_for_unreliable(fields, quality)
    assert fields["run_length_unreliable_mm"] == 22.0  # 2 steps x median(10, 12)
    assert math.isclose(fields["run_length_sigma_mm"], math.hypot(0.8, 22.0), abs_tol=1e-3)


def test_one_unconfirmed_laser_length_is_no_scale() -> None:
    """Every step without relative motion but one, whose laser length no feature confirms:
    refused in one line (random seed 3 chained that one 197 mm length through the run);
    a run with one step whose two sources agree is not."""
    lost = [StepCheck(k, k + 1, math.nan, 0.0, math.nan, 0, math.nan, "none", "relative motion not found")
            for k in range(30)]
    lone = StepCheck(30, 31, 197.1, 0.0, math.nan, 0, 197.1, "low", "laser scale not confirmed by feature depths")
    with pytest.raises(ReconstructionError, match="could not be trusted at any of the 31 steps"):
        refuse_untrusted_motion(SimpleNamespace(step_checks=[*lost, lone]))
    both = StepCheck(30, 31, 10.3, 0.0, 10.1, 40, 10.2, "low", "laser and feature depths offset")
    refuse_untrusted_motion(SimpleNamespace(step_checks=[*lost, both]))  # not refused
