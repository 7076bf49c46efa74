"""The typed report.json records: their contract form (DATA_CONTRACT.md section 4)."""

from __future__ import annotations

import json
from dataclasses import FrozenInstanceError, replace

import pytest

from omnipipe.contract import CORE_KEYS, SIGMA_KEYS, Defect, TrajectoryQuality, UnreliableSpan
from omnipipe.sfm.scale_check import StepCheck


def _fitted() -> Defect:
    return Defect(
        "bulge", 5.7, 4.299, 50.434, -50.041, 60.295,
        height_sigma_mm=1.2035, width_sigma_mm=0.9389, length_sigma_mm=41.786,
        axial_start_sigma_mm=20.8964, angle_sigma_deg=0.3183, fit_noise_mm=0.3779,
        points=15, travel_mm=12.5,
    )


def test_defect_contract_entry_has_the_contract_keys_in_order() -> None:
    entry = _fitted().to_contract()
    assert list(entry) == [*CORE_KEYS, *SIGMA_KEYS, "fit_noise_mm", "points"]
    assert entry["kind"] == "bulge" and entry["angle_deg"] == 60.295
    assert "travel_mm" not in entry and "motion_unreliable" not in entry  # internal / unset
    flagged = replace(_fitted(), motion_unreliable=True).to_contract()
    assert flagged["motion_unreliable"] is True and list(flagged)[-1] == "motion_unreliable"


def test_an_unfitted_defect_states_null_sigmas_and_no_fit_noise() -> None:
    rough = Defect("dent", 2.0, 10.0, 20.0, 5.0, 90.0, points=8)
    entry = rough.to_contract()
    assert not rough.fitted
    assert all(entry[k] is None for k in SIGMA_KEYS) and "fit_noise_mm" not in entry
    assert json.loads(json.dumps(entry))[SIGMA_KEYS[0]] is None  # JSON null


def test_defect_round_trips_through_report_json() -> None:
    d = replace(_fitted(), travel_mm=None, motion_unreliable=True)
    assert Defect.from_contract(json.loads(json.dumps(d.to_contract()))) == d
    # A ground-truth entry (scene.json): the six keys only.
    truth = Defect.from_contract({k: d.core()[k] for k in CORE_KEYS})
    assert truth.core() == d.core() and not truth.fitted and truth.points == 0


def test_defect_is_frozen_and_measures_its_extent() -> None:
    d = _fitted()
    with pytest.raises(FrozenInstanceError):
        d.height_mm = 1.0  # type: ignore[misc]
    assert d.axial_end_mm == pytest.approx(-50.041 + 50.434)
    assert d.axial_centre_mm == pytest.approx(-50.041 + 0.5 * 50.434)


def test_trajectory_quality_contract_entry() -> None:
    step = StepCheck(0, 1, 7.5, 0.0, 7.4, 30, 7.456, "high", "", (7.5,))
    q = TrajectoryQuality(
        steps_checked=1,
        unreliable=(UnreliableSpan(5, 7, "ambiguous laser scale", 40.0, 52.5), UnreliableSpan(9, 9, "x")),
        scale_source="laser",
        laser_offset_pct=0.12,
        scale_sigma_pct=0.4,
        keyframe_steps=(step,),
    )
    entry = json.loads(json.dumps(q.to_contract()))
    assert entry["steps_checked"] == 1
    assert entry["unreliable"][0] == {
        "first_frame": 5, "last_frame": 7, "reason": "ambiguous laser scale",
        "axial_start_mm": 40.0, "axial_end_mm": 52.5,
    }
    assert entry["unreliable"][1] == {"first_frame": 9, "last_frame": 9, "reason": "x"}  # not located
    assert entry["keyframe_steps"] == [step.to_dict()]
    assert entry["wall_scale_gap_pct"] is None and entry["scale_sigma_pct"] == 0.4
