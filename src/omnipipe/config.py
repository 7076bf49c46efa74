"""Typed configuration from YAML mappings: dataclasses filled and validated field by field.

``dataclass_from_dict(SomeConfig, {"key": value}, "section")`` returns a new
``SomeConfig`` with the given fields replaced; an unknown key, a value of the
wrong type (a float must also be finite: nan and inf are refused) or a value outside
the field's declared bounds (:func:`bounded`) raises a :class:`ConfigError` naming
``section.key``. :func:`deep_merge` layers mappings (defaults, YAML, command line)
key by key, so an override of one nested setting keeps its siblings. YAML is read by
:func:`omnipipe.safe_yaml.load_yaml_file` (bounded size and alias expansion).
"""

from __future__ import annotations

import dataclasses
import math
import types
import typing
from pathlib import Path
from typing import Any, TypeVar

from omnipipe.errors import ConfigError
from omnipipe.safe_yaml import load_yaml_file

T = TypeVar("T")

_BOUNDS = "omnipipe_bounds"


def bounded(
    default: Any = dataclasses.MISSING,
    *,
    default_factory: Any = dataclasses.MISSING,
    ge: float | None = None,
    gt: float | None = None,
    le: float | None = None,
    lt: float | None = None,
) -> Any:
    """A dataclass field with ``default`` (or ``default_factory``; neither: a required
    field) whose configured values must lie in the bounds.

    ``ge``/``gt``/``le``/``lt``: inclusive/exclusive lower and upper bounds (None: open);
    for a tuple, each of its numbers. :func:`dataclass_from_dict` refuses a value outside
    them, naming the field.
    """
    bounds = {"ge": ge, "gt": gt, "le": le, "lt": lt}
    return dataclasses.field(default=default, default_factory=default_factory, metadata={_BOUNDS: bounds})


def _check_bounds(value: Any, bounds: dict[str, float | None], field: str, source: str | None) -> None:
    if isinstance(value, tuple):
        for i, v in enumerate(value):
            _check_bounds(v, bounds, f"{field}[{i}]", source)
        return
    if not isinstance(value, int | float) or isinstance(value, bool):
        return
    tests = {
        "ge": (lambda v, b: v >= b, ">="),
        "gt": (lambda v, b: v > b, ">"),
        "le": (lambda v, b: v <= b, "<="),
        "lt": (lambda v, b: v < b, "<"),
    }
    for key, (ok, sign) in tests.items():
        bound = bounds.get(key)
        if bound is not None and not ok(value, bound):
            raise ConfigError(field, f"must be {sign} {bound:g}, got {value:g}", source)


def deep_merge(base: dict[str, Any], override: dict[str, Any]) -> dict[str, Any]:
    """``base`` with ``override`` laid over it, mapping by mapping (new dict; inputs unchanged).

    A key whose values are mappings on both sides is merged recursively; any other
    value in ``override`` replaces the one in ``base``.
    """
    out = dict(base)
    for key, value in override.items():
        if isinstance(value, dict) and isinstance(out.get(key), dict):
            out[key] = deep_merge(out[key], value)
        else:
            out[key] = value
    return out


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
        if not math.isfinite(value):
            raise ConfigError(field, f"must be a finite number, got {value}", source)
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
    fields = {f.name: f for f in dataclasses.fields(cls)}  # type: ignore[arg-type]
    kwargs = {}
    for key, value in data.items():
        field = f"{prefix}.{key}" if prefix else str(key)
        if key not in fields:
            known = ", ".join(sorted(fields))
            raise ConfigError(field, f"unknown setting (known: {known})", source)
        kwargs[key] = _coerce(value, hints[key], field, source)
        bounds = fields[key].metadata.get(_BOUNDS)
        if bounds:
            _check_bounds(kwargs[key], bounds, field, source)
    try:
        return cls(**kwargs)
    except ConfigError:
        raise
    except (TypeError, ValueError) as exc:
        raise ConfigError(prefix or "config", str(exc), source) from None


def load_yaml_mapping(path: str | Path) -> dict[str, Any]:
    """Read a YAML file holding a mapping of sections (empty file: empty mapping).

    Each section's value must be a mapping or empty (None), so that a section
    written as a list or a number is refused here, naming it.

    Raises:
        ConfigError: the file is missing, too large, an alias bomb, not YAML, not a
            mapping, or a section is not a mapping (field: the section's name).
    """
    path = Path(path)
    data = load_yaml_file(path, "config")
    if data is None:
        return {}
    if not isinstance(data, dict):
        raise ConfigError("config", "must hold a mapping of sections", str(path))
    for section, values in data.items():
        if values is not None and not isinstance(values, dict):
            raise ConfigError(
                str(section),
                f"must be a mapping of settings, got {type(values).__name__}",
                str(path),
            )
    return data


def finite_option(value: float | None, option: str, *, positive: bool = False) -> float | None:
    """A float command-line option checked to be finite (and > 0 with ``positive``).

    argparse's ``type=float`` accepts ``nan`` and ``inf``; this turns them into a
    one-line :class:`ConfigError` naming the option (exit code 1). None passes.
    """
    if value is None:
        return None
    if not math.isfinite(value):
        raise ConfigError(option, f"must be a finite number, got {value}")
    if positive and not value > 0:
        raise ConfigError(option, f"must be > 0, got {value:g}")
    return value
