"""rig.yaml loading, validation and round trip."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
import yaml

from omnipipe.errors import ConfigError
from omnipipe.rig_yaml import load_rig, rig_from_dict, save_rig

GOOD = {
    "camera": {
        "width": 1600,
        "height": 1200,
        "cx": 799.5,
        "cy": 599.5,
        "f": 1200.0,
        "pixel_pitch": 0.0044,
        "radius_min": 110,
        "radius_max": 595,
    },
    "mirror": {"a": 20.0, "b": 30.0},
    "laser": {"plane": [0.0, 0.0, 1.0, 82.0], "channel": "red"},
}


def _with(path: str, value: object) -> dict:
    data = yaml.safe_load(yaml.safe_dump(GOOD))
    *parents, key = path.split(".")
    node = data
    for p in parents:
        node = node[p]
    if value is _DELETE:
        del node[key]
    else:
        node[key] = value
    return data


_DELETE = object()


def test_contract_example_loads_and_round_trips(tmp_path: Path) -> None:
    rig = rig_from_dict(GOOD)
    assert rig.camera.width == 1600 and rig.camera.f == 1200.0
    assert rig.mirror.c == pytest.approx((20.0**2 + 30.0**2) ** 0.5)
    assert rig.laser.distance_mm == pytest.approx(82.0)
    assert np.array([0.0, 0.0, -82.0]) @ rig.laser.normal_in_rig + rig.laser.offset_mm == pytest.approx(0.0)
    save_rig(rig, tmp_path / "rig.yaml")
    assert load_rig(tmp_path / "rig.yaml") == rig


def test_laser_calibration_uncertainty_round_trips(tmp_path: Path) -> None:
    rig = rig_from_dict(_with("laser.offset_sigma_mm", 0.08))
    assert rig.laser.offset_sigma_mm == 0.08
    assert rig.laser.scale_sigma_rel == pytest.approx(0.08 / 82.0)
    save_rig(rig, tmp_path / "rig.yaml")
    assert load_rig(tmp_path / "rig.yaml") == rig
    assert rig_from_dict(GOOD).laser.scale_sigma_rel == 0.0  # not stated


def test_optional_fields_may_be_absent() -> None:
    data = _with("camera.radius_min", _DELETE)
    del data["camera"]["radius_max"], data["camera"]["pixel_pitch"]
    del data["laser"]["channel"]
    rig = rig_from_dict(data)
    assert rig.camera.radius_min is None and rig.laser.channel == "red"


@pytest.mark.parametrize(
    ("path", "value", "field"),
    [
        ("camera.f", _DELETE, "camera.f"),
        ("camera.f", 0.0, "camera.f"),
        ("camera.f", -3.0, "camera.f"),
        ("camera.width", 0, "camera.width"),
        ("camera.height", "big", "camera.height"),
        ("mirror.a", -1.0, "mirror.a"),
        ("mirror.b", 0, "mirror.b"),
        ("mirror.b", _DELETE, "mirror.b"),
        ("camera.radius_min", 700, "camera.radius_min"),
        ("laser.plane", [0.0, 0.0, 0.0, 82.0], "laser.plane"),
        ("laser.plane", [0.0, 1.0, 82.0], "laser.plane"),
        ("laser.channel", "infrared", "laser.channel"),
        ("laser.plane", _DELETE, "laser.plane"),
        ("laser.offset_sigma_mm", -0.1, "laser.offset_sigma_mm"),
        ("laser.offset_sigma_mm", "small", "laser.offset_sigma_mm"),
    ],
)
def test_invalid_fields_are_named(path: str, value: object, field: str) -> None:
    with pytest.raises(ConfigError) as err:
        rig_from_dict(_with(path, value), source="rig.yaml")
    assert err.value.field == field
    assert field in str(err.value) and "rig.yaml" in str(err.value)


def test_missing_section_and_bad_files(tmp_path: Path) -> None:
    data = yaml.safe_load(yaml.safe_dump(GOOD))
    del data["mirror"]
    with pytest.raises(ConfigError, match="mirror"):
        rig_from_dict(data)
    with pytest.raises(ConfigError, match="file not found"):
        load_rig(tmp_path / "nope.yaml")
    bad = tmp_path / "bad.yaml"
    bad.write_text("camera: [unclosed\n")
    with pytest.raises(ConfigError, match="not valid YAML"):
        load_rig(bad)
    bad.write_text("- 1\n- 2\n")
    with pytest.raises(ConfigError, match="mapping"):
        load_rig(bad)
