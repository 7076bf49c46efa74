"""Report stage: a self-contained report.html (opens offline, no CDN).

The page: :mod:`.html` (its parts: :mod:`.inputs`, :mod:`.tables`, :mod:`.plots`,
:mod:`.model_view`, :mod:`.encode`); the inspector's deliverable (defects.csv, crops):
:mod:`.deliverable`.
"""

from omnipipe.report.html import render_html, run
from omnipipe.report.inputs import ReportConfig, ReportInputs
from omnipipe.report.tables import value_pm

__all__ = ["ReportConfig", "ReportInputs", "render_html", "run", "value_pm"]
