"""Typed configuration from YAML."""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

import pytest

from omnipipe.config import bounded, dataclass_from_dict, deep_merge, load_yaml_mapping
from omnipipe.errors import ConfigError


@dataclass(frozen=True)
class Inner:
    count: int = 3
    scale: float = 1.0


@dataclass(frozen=True)
class Outer:
    name: str = "x"
    enabled: bool = True
    limit: float | None = None
    size: tuple[int, int] = (4, 3)
    inner: Inner = field(default_factory=Inner)


def test_fields_are_replaced_and_coerced() -> None:
    cfg = dataclass_from_dict(Outer, {"limit": 2, "size": [8, 6], "inner": {"scale": 3}})
    assert cfg.limit == 2.0 and cfg.size == (8, 6) and cfg.inner == Inner(3, 3.0) and cfg.enabled


@pytest.mark.parametrize(
    ("data", "field_name"),
    [
        ({"nope": 1}, "sec.nope"),
        ({"enabled": "yes"}, "sec.enabled"),
        ({"inner": {"count": 2.5}}, "sec.inner.count"),
        ({"size": [1]}, "sec.size"),
        ({"name": 3}, "sec.name"),
    ],
)
def test_bad_values_name_the_field(data: dict, field_name: str) -> None:
    with pytest.raises(ConfigError) as err:
        dataclass_from_dict(Outer, data, "sec", source="c.yaml")
    assert err.value.field == field_name


def test_yaml_files(tmp_path: Path) -> None:
    p = tmp_path / "c.yaml"
    p.write_text("sec: {name: y}\n")
    assert load_yaml_mapping(p) == {"sec": {"name": "y"}}
    p.write_text("[1, 2]\n")
    with pytest.raises(ConfigError, match="mapping"):
        load_yaml_mapping(p)
    with pytest.raises(ConfigError, match="not found"):
        load_yaml_mapping(tmp_path / "none.yaml")


@dataclass(frozen=True)
class Bounded:
    grid_mm: float = bounded(1.0, gt=0)
    count: int = bounded(3, ge=1, le=10)


@pytest.mark.parametrize(
    ("data", "message"),
    [({"grid_mm": 0}, "must be > 0"), ({"count": 0}, "must be >= 1"), ({"count": 11}, "<= 10")],
)
def test_values_outside_bounds_are_refused_naming_the_field(data: dict, message: str) -> None:
    with pytest.raises(ConfigError, match=message) as err:
        dataclass_from_dict(Bounded, data, "sec", source="c.yaml")
    assert err.value.field == f"sec.{next(iter(data))}"
    assert "\n" not in str(err.value)


def test_values_inside_bounds_are_taken() -> None:
    assert dataclass_from_dict(Bounded, {"grid_mm": 0.5, "count": 10}) == Bounded(0.5, 10)


def test_deep_merge_keeps_nested_siblings() -> None:
    base = {"sfm": {"features": {"views": 6, "max_features": 100}, "x": 1}}
    merged = deep_merge(base, {"sfm": {"features": {"max_features": 500}}})
    assert merged == {"sfm": {"features": {"views": 6, "max_features": 500}, "x": 1}}
    assert base["sfm"]["features"]["max_features"] == 100


def test_yaml_views_survive_a_features_override(tmp_path: Path) -> None:
    from omnipipe.pipeline import ReconstructConfig

    p = tmp_path / "c.yaml"
    p.write_text("sfm:\n  features: {views: 6}\n")
    cfg = ReconstructConfig.from_yaml(p, {"sfm": {"features": {"max_features": 500}}})
    assert cfg.sfm.features.views == 6 and cfg.sfm.features.max_features == 500
