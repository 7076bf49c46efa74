"""Analysis stage: inner diameter, ovality and defects of the measured pipe (Table I).

The stage is :func:`omnipipe.analysis.stage.run`; the modules: :mod:`.centreline`,
:mod:`.cylinder`, :mod:`.defects`, :mod:`.sizing`.
"""

from omnipipe.analysis.cylinder import Cylinder, fit_cylinder
from omnipipe.analysis.stage import (
    AnalysisConfig,
    AnalysisInputs,
    AnalysisResult,
    report_fields,
    run,
)

__all__ = [
    "AnalysisConfig",
    "AnalysisInputs",
    "AnalysisResult",
    "Cylinder",
    "fit_cylinder",
    "report_fields",
    "run",
]
