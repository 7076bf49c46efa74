"""Analysis stage: inner diameter, ovality and defects of the measured pipe (Table I).

The stage is :func:`omnipipe.analysis.stage.run` (its config, inputs and result in
:mod:`.records`); the modules: :mod:`.centreline` and :mod:`.axis_fit` (the axis),
:mod:`.cylinder`, :mod:`.station_profiles` (each station's wall profile),
:mod:`.wall_measure` (the two defect passes), :mod:`.defects`, :mod:`.sizing`,
:mod:`.headline` (the headline diameter and the terms the stations share),
:mod:`.uncertainty`, :mod:`.stations` (cross-sections: mean diameter, ovality, water),
:mod:`.sections` (taper, bend, ovality and water features) and :mod:`.feature_types`
(:class:`Feature`).
"""

from omnipipe.analysis.cylinder import Cylinder, fit_cylinder
from omnipipe.analysis.records import AnalysisConfig, AnalysisInputs, AnalysisResult
from omnipipe.analysis.stage import run
from omnipipe.analysis.uncertainty import report_fields, scaled_defects
from omnipipe.contract import Defect

__all__ = [
    "AnalysisConfig",
    "AnalysisInputs",
    "AnalysisResult",
    "Cylinder",
    "Defect",
    "fit_cylinder",
    "report_fields",
    "run",
    "scaled_defects",
]
