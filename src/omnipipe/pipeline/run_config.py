"""What a reconstruction run is given and what it notes as it goes.

:class:`ReconstructConfig`: the settings of every stage (``laser``, ``sfm``, ``model``,
``analysis``, ``report``; ``--config FILE.yaml`` overrides any of them by section) and the
executor's choice. :class:`RunLog`: the run's stage times (seconds, by stage name) and
warnings, which every stage call adds to and each checkpoint saves. :func:`no_progress`:
the progress factory that draws nothing (the default of :func:`~.reconstruct.run` and
:func:`~.outputs.write`).
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Any

from omnipipe.config import dataclass_from_dict, deep_merge, load_yaml_mapping

if TYPE_CHECKING:  # imported inside the functions: `omnipipe --help` stays fast
    from omnipipe.analysis import AnalysisConfig
    from omnipipe.laser import LaserConfig
    from omnipipe.model import ModelConfig
    from omnipipe.report import ReportConfig
    from omnipipe.sfm import SfmConfig


def no_progress(stage: str, total: int) -> Callable[[int], None]:
    return lambda done: None


@dataclass(frozen=True)
class ReconstructConfig:
    """Settings of every stage; ``--config FILE.yaml`` overrides any of them by section.

    ``workers`` (local processes, None: every core, 1: serial) and ``scheduler`` (a Dask
    scheduler address ``tcp://HOST:PORT``, or None) choose the executor of the
    frame-parallel work (:mod:`omnipipe.executor`; ``--workers``, ``--scheduler``).
    """

    laser: LaserConfig
    sfm: SfmConfig
    model: ModelConfig
    analysis: AnalysisConfig
    report: ReportConfig
    workers: int | None = None
    scheduler: str | None = None

    @staticmethod
    def default() -> ReconstructConfig:
        from omnipipe.analysis import AnalysisConfig
        from omnipipe.laser import LaserConfig
        from omnipipe.model import ModelConfig
        from omnipipe.report import ReportConfig
        from omnipipe.sfm import SfmConfig

        return ReconstructConfig(
            LaserConfig(), SfmConfig(), ModelConfig(), AnalysisConfig(), ReportConfig()
        )

    @staticmethod
    def from_yaml(
        path: str | Path | None, overrides: dict[str, dict[str, Any]] | None = None
    ) -> ReconstructConfig:
        """Defaults, then the YAML file's sections, then ``overrides`` (CLI options)."""
        base = ReconstructConfig.default()
        data = load_yaml_mapping(path) if path is not None else {}
        source = None if path is None else str(path)
        merged: dict[str, dict[str, Any]] = {}
        for section, values in data.items():
            if section not in ("laser", "sfm", "model", "analysis", "report"):
                from omnipipe.errors import ConfigError

                raise ConfigError(
                    str(section),
                    "unknown section (known: laser, sfm, model, analysis, report)",
                    source,
                )
            merged[section] = dict(values or {})
        merged = deep_merge(merged, overrides or {})
        parts: dict[str, Any] = {}
        for section in ("laser", "sfm", "model", "analysis", "report"):
            default = getattr(base, section)
            values = merged.get(section)
            if values:
                from dataclasses import asdict

                combined = deep_merge(asdict(default), values)
                # Nested dataclasses come back as dicts from asdict: rebuild the whole section.
                parts[section] = dataclass_from_dict(type(default), combined, section, source)
            else:
                parts[section] = default
        return ReconstructConfig(**parts)


@dataclass
class RunLog:
    """What a run notes as it goes: stage times (s) and warnings."""

    t_start: float
    timings: dict[str, float] = field(default_factory=dict)
    warnings: list[str] = field(default_factory=list)
