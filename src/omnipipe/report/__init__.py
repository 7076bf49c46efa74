"""Report stage: a self-contained report.html (opens offline, no CDN).

The page: :mod:`.html`; the inspector's deliverable (defects.csv, crops):
:mod:`.deliverable`.
"""

from omnipipe.report.html import ReportConfig, ReportInputs, render_html, run, value_pm

__all__ = ["ReportConfig", "ReportInputs", "render_html", "run", "value_pm"]
