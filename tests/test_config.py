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


def test_cli_features_keeps_the_yaml_views(
    tiny_dataset: Path, tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """``reconstruct --config c.yaml --features 500`` through the CLI: the config the run
    gets keeps the YAML's ``views`` (the run itself is stopped before any work)."""
    import omnipipe.pipeline.cli as reconstruct_cli
    from omnipipe.cli import main

    seen = []

    def stop(config, *args, **kwargs):
        seen.append(config)
        raise ConfigError("test", "stopped before any work")

    monkeypatch.setattr(reconstruct_cli, "run", stop)
    p = tmp_path / "c.yaml"
    p.write_text("sfm:\n  features: {views: 6}\n")
    argv = ["reconstruct", str(tiny_dataset), "--out", str(tmp_path / "out"), "--quiet"]
    assert main([*argv, "--config", str(p), "--features", "500"]) == 1
    (cfg,) = seen
    assert cfg.sfm.features.views == 6 and cfg.sfm.features.max_features == 500


def _stage_config_classes() -> list[type]:
    """Every ``*Config`` dataclass of omnipipe's stages (found by walking the package)."""
    import dataclasses
    import importlib
    import pkgutil

    import omnipipe

    found: dict[str, type] = {}
    for info in pkgutil.walk_packages(omnipipe.__path__, "omnipipe."):
        module = importlib.import_module(info.name)
        for name, obj in vars(module).items():
            if name.endswith("Config") and dataclasses.is_dataclass(obj) and obj.__module__ == info.name:
                required = [
                    f.name
                    for f in dataclasses.fields(obj)
                    if f.default is dataclasses.MISSING and f.default_factory is dataclasses.MISSING
                ]
                if not required:  # a config with required fields has no defaults to check
                    found[f"{info.name}.{name}"] = obj
    return [found[k] for k in sorted(found)]


def test_every_default_lies_inside_its_bounds() -> None:
    import dataclasses

    classes = _stage_config_classes()
    assert len(classes) >= 15
    for cls in classes:
        default = cls()
        assert dataclass_from_dict(cls, dataclasses.asdict(default), cls.__name__) == default


@pytest.mark.parametrize(
    ("text", "field_name"),
    [
        ("analysis: {grid_mm: 0}\n", "analysis.grid_mm"),
        ("sfm: {bundle: {max_tracks: -5}}\n", "sfm.bundle.max_tracks"),
        ("sfm: {bundle: {window_keyframes: -3}}\n", "sfm.bundle.window_keyframes"),
        ("laser: {extraction: {min_ring_fraction: 1.5}}\n", "laser.extraction.min_ring_fraction"),
        ("model: {texture_mm_per_px: 0}\n", "model.texture_mm_per_px"),
        ("report: {max_faces: 0}\n", "report.max_faces"),
        ("model: {outliers: {k_mad: 0}}\n", "model.outliers.k_mad"),
        ("model: {outliers: {window: 40}}\n", "model.outliers.window"),
        ("sfm: {features: {elevation_deg: [-95, 15]}}\n", "sfm.features.elevation_deg[0]"),
        ("sfm: {laser_scale: {scale_range_mm: [0.2, 0]}}\n", "sfm.laser_scale.scale_range_mm[1]"),
        ("sfm: {planes: {rotations_deg: [0, 200]}}\n", "sfm.planes.rotations_deg[1]"),
    ],
)
def test_reconstruct_yaml_outside_bounds_is_refused_at_load(
    tmp_path: Path, text: str, field_name: str
) -> None:
    from omnipipe.pipeline.run_config import ReconstructConfig

    path = tmp_path / "bad.yaml"
    path.write_text(text)
    with pytest.raises(ConfigError) as info:
        ReconstructConfig.from_yaml(path)
    message = str(info.value)
    assert field_name + ":" in message and "\n" not in message, message


def test_model_outliers_are_read_from_yaml(tmp_path: Path) -> None:
    from omnipipe.pipeline.run_config import ReconstructConfig

    path = tmp_path / "outliers.yaml"
    path.write_text("model: {outliers: {k_mad: 8.5, max_run: 3}}\n")
    outliers = ReconstructConfig.from_yaml(path).model.outliers
    assert (outliers.k_mad, outliers.max_run, outliers.window) == (8.5, 3, 41)


# Numeric settings still without declared bounds, each with its reason (none today).
UNBOUNDED: dict[str, set[str]] = {}


def test_every_numeric_setting_declares_its_bounds() -> None:
    """Every int / float (or tuple of them) field of every stage config has ``bounded()``
    metadata, so a YAML value outside its range is refused at load, naming the field."""
    import dataclasses
    import typing

    # The simulator's scene settings (omnipipe.sim) are built by its scenarios, not read
    # from a user's YAML.
    classes = [c for c in _stage_config_classes() if not c.__module__.startswith("omnipipe.sim.")]
    missing = []
    for cls in classes:
        hints = typing.get_type_hints(cls)
        for f in dataclasses.fields(cls):
            kinds = typing.get_args(hints[f.name]) or (hints[f.name],)
            numeric = any(k in (int, float) for k in kinds)
            name = f"{cls.__module__}.{cls.__qualname__}"
            if numeric and not f.metadata.get("omnipipe_bounds") and f.name not in UNBOUNDED.get(name, ()):
                missing.append(f"{name}.{f.name}")
    assert not missing, missing
