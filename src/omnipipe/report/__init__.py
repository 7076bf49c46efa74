"""Report stage: a self-contained report.html (opens offline, no CDN).

The page: :mod:`.html`; the inspector's deliverable (defects.csv, crops):
:mod:`.deliverable`.
"""

from omnipipe.report.html import render_html, run, value_pm
from omnipipe.report.inputs import ReportConfig, ReportInputs

__all__ = ["ReportConfig", "ReportInputs", "render_html", "run", "value_pm"]
