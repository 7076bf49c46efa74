"""Typed configuration from YAML."""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

import pytest

from omnipipe.config import dataclass_from_dict, load_yaml_mapping
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
