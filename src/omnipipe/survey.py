"""The survey header of an inspection: ``survey.yaml`` (optional).

Where the survey took place and how, as an inspector states it (docs/inspection_coding.md
maps each field to NASSCO PACP and EN 13508-2). ``omnipipe reconstruct`` reads
``--survey FILE``, else ``survey.yaml`` beside the dataset (in the dataset directory;
for a video or bag file, in its folder), else runs without one. Every field is
optional; a field that is present must be valid, else a :class:`ConfigError` names it::

    site: Main Street, Springfield       # text
    asset_id: SW-1042                    # pipe segment / asset identifier
    pipe_material: PVC                   # text (PACP/EN material code or name)
    nominal_diameter_mm: 200             # > 0, mm (the design size; omnipipe measures the real one)
    start_node: MH-12                    # manhole / launch pit the distances start from
    end_node: MH-13                      # text
    direction: downstream                # downstream | upstream (survey relative to the flow)
    operator: A. Smith                   # text
    date: 2024-05-01                     # ISO date (YYYY-MM-DD)
    start_offset_m: 0.35                 # distance from start_node to the first frame's
                                         # mirror focus along the pipe, m (default 0)
    clock_reference_deg: -90             # omnipipe angle (deg, from the first rig frame's x
                                         # axis towards y) that is 12 o'clock; default: the
                                         # first rig frame's -y axis (image up)

The file is parsed by omnipipe's bounded YAML loader (:mod:`omnipipe.safe_yaml`).
"""

from __future__ import annotations

import datetime as _dt
import math
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Any

from omnipipe.errors import ConfigError
from omnipipe.safe_yaml import load_yaml_file

SURVEY_FILE = "survey.yaml"
DIRECTIONS = ("downstream", "upstream")
_TEXT_FIELDS = ("site", "asset_id", "pipe_material", "start_node", "end_node", "operator")
_MAX_TEXT = 200


@dataclass(frozen=True)
class Survey:
    """The survey header; None where survey.yaml does not say.

    Attributes:
        site, asset_id, pipe_material, start_node, end_node, operator: free text.
        nominal_diameter_mm: design inner diameter, mm.
        direction: "downstream" or "upstream".
        date: ISO date "YYYY-MM-DD".
        start_offset_m: distance from the start node to the first frame's rig origin
            (mirror focus), measured along the pipe in the survey direction, metres.
        clock_reference_deg: the omnipipe angle (degrees from the first rig frame's x axis
            towards y) that is 12 o'clock; None: the first rig frame's -y axis.
        source: the file it came from.
    """

    site: str | None = None
    asset_id: str | None = None
    pipe_material: str | None = None
    nominal_diameter_mm: float | None = None
    start_node: str | None = None
    end_node: str | None = None
    direction: str | None = None
    operator: str | None = None
    date: str | None = None
    start_offset_m: float = 0.0
    clock_reference_deg: float | None = None
    source: str | None = None

    def to_dict(self) -> dict[str, Any]:
        """The fields as JSON-ready values (report.json ``survey``)."""
        return asdict(self)


FIELDS = tuple(f for f in Survey.__dataclass_fields__ if f != "source")


def _number(value: Any, field: str, source: str, *, positive: bool = False) -> float:
    if isinstance(value, bool) or not isinstance(value, int | float):
        raise ConfigError(field, f"must be a number, got {value!r:.60}", source)
    x = float(value)
    if not math.isfinite(x):
        raise ConfigError(field, f"must be a finite number, got {value!r}", source)
    if positive and x <= 0:
        raise ConfigError(field, f"must be > 0, got {value!r}", source)
    return x


def _text(value: Any, field: str, source: str) -> str:
    if isinstance(value, bool) or not isinstance(value, str | int | float):
        raise ConfigError(field, f"must be text, got {type(value).__name__}", source)
    text = str(value).strip()
    if not text or len(text) > _MAX_TEXT or any(c in text for c in "\r\n\x00"):
        raise ConfigError(field, f"must be one line of 1-{_MAX_TEXT} characters", source)
    return text


def _date(value: Any, source: str) -> str:
    if isinstance(value, _dt.datetime):
        return value.date().isoformat()
    if isinstance(value, _dt.date):
        return value.isoformat()
    if isinstance(value, str):
        try:
            return _dt.date.fromisoformat(value.strip()).isoformat()
        except ValueError:
            pass
    raise ConfigError("date", f"must be an ISO date YYYY-MM-DD, got {value!r:.60}", source)


def survey_from_dict(data: dict[str, Any], source: str | None = None) -> Survey:
    """Validate a survey mapping.

    Raises:
        ConfigError: an unknown field, or a field of the wrong type or value (named).
    """
    src = source or "survey"
    values: dict[str, Any] = {}
    for key, value in data.items():
        field = str(key)
        if field not in FIELDS:
            raise ConfigError(field, f"unknown field (known: {', '.join(FIELDS)})", src)
        if value is None:
            continue
        if field in _TEXT_FIELDS:
            values[field] = _text(value, field, src)
        elif field == "nominal_diameter_mm":
            values[field] = _number(value, field, src, positive=True)
        elif field == "start_offset_m":
            values[field] = _number(value, field, src)
        elif field == "clock_reference_deg":
            values[field] = _number(value, field, src) % 360.0
        elif field == "direction":
            text = _text(value, field, src).lower()
            if text not in DIRECTIONS:
                raise ConfigError(field, f"must be one of {', '.join(DIRECTIONS)}, got {value!r}", src)
            values[field] = text
        elif field == "date":
            values[field] = _date(value, src)
    return Survey(**values, source=source)


def load_survey(path: str | Path) -> Survey:
    """Read and validate ``survey.yaml``.

    Raises:
        ConfigError: missing/unreadable/hostile file, not a mapping, or a bad field (named).
    """
    path = Path(path)
    try:
        data = load_yaml_file(path, "survey")
    except ConfigError as exc:
        if "cannot be read" not in str(exc):
            raise
        # PyYAML builds timestamps itself and fails on an impossible date (2024-13-45);
        # the date is the only such value in a survey.
        raise ConfigError("date", "not a valid date (YYYY-MM-DD)", str(path)) from None
    if data is None:
        return Survey(source=str(path))
    if not isinstance(data, dict):
        raise ConfigError("survey", "must hold a mapping of fields", str(path))
    return survey_from_dict(data, str(path))


def find_survey(dataset: str | Path, explicit: str | Path | None = None) -> Survey | None:
    """The survey of a run: ``explicit`` (``--survey``), else ``survey.yaml`` in the dataset
    directory (beside a video, a bag file or a ROS 2 bag folder), else None."""
    if explicit is not None:
        return load_survey(explicit)
    root = Path(dataset)
    # A dataset directory holds it; a video, bag file or ROS 2 bag folder has it beside.
    is_bag_dir = (root / "metadata.yaml").is_file()
    folder = root if root.is_dir() and not is_bag_dir else root.parent
    candidates = [folder / SURVEY_FILE]
    if root.is_file() and (folder / "metadata.yaml").is_file():
        candidates.append(folder.parent / SURVEY_FILE)  # a storage file of a ROS 2 bag
    for candidate in candidates:
        if candidate.is_file():
            return load_survey(candidate)
    return None
