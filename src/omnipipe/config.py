"""Typed configuration from YAML mappings: dataclasses filled and validated field by field.

``dataclass_from_dict(SomeConfig, {"key": value}, "section")`` returns a new
``SomeConfig`` with the given fields replaced; an unknown key or a value of the
wrong type raises a :class:`ConfigError` naming ``section.key``.
"""

from __future__ import annotations

import dataclasses
import types
import typing
from pathlib import Path
from typing import Any, TypeVar

import yaml

from omnipipe.errors import ConfigError

T = TypeVar("T")


def _coerce(value: Any, annotation: Any, field: str, source: str | None) -> Any:
    origin = typing.get_origin(annotation)
    args = typing.get_args(annotation)
    if origin in (typing.Union, types.UnionType):
        if value is None and type(None) in args:
            return None
        errors = []
        for arg in args:
            if arg is type(None):
                continue
            try:
                return _coerce(value, arg, field, source)
            except ConfigError as exc:
                errors.append(exc)
        raise errors[0]
    if dataclasses.is_dataclass(annotation):
        if not isinstance(value, dict):
            raise ConfigError(field, f"must be a mapping, got {value!r}", source)
        return dataclass_from_dict(annotation, value, field, source)  # type: ignore[arg-type]
    if annotation is bool:
        if not isinstance(value, bool):
            raise ConfigError(field, f"must be true or false, got {value!r}", source)
        return value
    if annotation is int:
        if isinstance(value, bool) or not isinstance(value, int):
            raise ConfigError(field, f"must be a whole number, got {value!r}", source)
        return value
    if annotation is float:
        if isinstance(value, bool) or not isinstance(value, int | float):
            raise ConfigError(field, f"must be a number, got {value!r}", source)
        return float(value)
    if annotation is str:
        if not isinstance(value, str):
            raise ConfigError(field, f"must be text, got {value!r}", source)
        return value
    if origin is tuple:
        if not isinstance(value, list | tuple):
            raise ConfigError(field, f"must be a list, got {value!r}", source)
        if len(args) == 2 and args[1] is Ellipsis:
            return tuple(_coerce(v, args[0], f"{field}[{i}]", source) for i, v in enumerate(value))
        if len(value) != len(args):
            raise ConfigError(field, f"must have {len(args)} items, got {len(value)}", source)
        return tuple(
            _coerce(v, a, f"{field}[{i}]", source)
            for i, (v, a) in enumerate(zip(value, args, strict=True))
        )
    return value


def dataclass_from_dict(
    cls: type[T], data: dict[str, Any], prefix: str = "", source: str | None = None
) -> T:
    """A ``cls`` instance with defaults replaced by ``data``, validated field by field."""
    if not isinstance(data, dict):
        raise ConfigError(prefix or "config", f"must be a mapping, got {data!r}", source)
    hints = typing.get_type_hints(cls)
    names = {f.name for f in dataclasses.fields(cls)}  # type: ignore[arg-type]
    kwargs = {}
    for key, value in data.items():
        field = f"{prefix}.{key}" if prefix else str(key)
        if key not in names:
            raise ConfigError(field, f"unknown setting (known: {', '.join(sorted(names))})", source)
        kwargs[key] = _coerce(value, hints[key], field, source)
    try:
        return cls(**kwargs)
    except ConfigError:
        raise
    except (TypeError, ValueError) as exc:
        raise ConfigError(prefix or "config", str(exc), source) from None


def load_yaml_mapping(path: str | Path) -> dict[str, Any]:
    """Read a YAML file holding a mapping (empty file: empty mapping)."""
    path = Path(path)
    if not path.is_file():
        raise ConfigError("config", "file not found", str(path))
    try:
        data = yaml.safe_load(path.read_text(encoding="utf-8"))
    except (yaml.YAMLError, UnicodeDecodeError) as exc:
        first = str(exc).strip().splitlines()[0] if str(exc).strip() else type(exc).__name__
        raise ConfigError("config", f"not valid YAML ({first})", str(path)) from None
    if data is None:
        return {}
    if not isinstance(data, dict):
        raise ConfigError("config", "must hold a mapping of sections", str(path))
    return data
