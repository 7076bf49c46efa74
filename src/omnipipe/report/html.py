"""Report stage: a self-contained report.html (opens offline, no CDN).

It holds an interactive 3-D view of the textured model (a small WebGL viewer shipped
with omnipipe), the inner diameter and ovality along the pipe, the unrolled wall
image with the defects outlined, the trajectory, the defect table, and the
measured-vs-true table (the paper's Table I) when ground truth exists.

The page is ``templates/report.html`` (a :class:`string.Template`: its style sheet,
headings and notes) filled here with its sections: the tables (:mod:`.tables`), the
figures (:mod:`.plots`) and the 3-D view (:mod:`.model_view`), made from the stage's
inputs and config (:mod:`.inputs`); the images and long texts are written a piece at a
time (:mod:`.encode`). Printed (A4 or Letter, whichever the printer uses) it has no 3-D
view, keeps headings with what follows them and never splits tables and figures across
pages.
"""

from __future__ import annotations

import html
from collections.abc import Iterator
from importlib import resources
from pathlib import Path
from string import Template

import numpy as np

from omnipipe.memory import release_freed_memory
from omnipipe.report.encode import text_file_parts
from omnipipe.report.inputs import ReportConfig, ReportInputs, travel_sign
from omnipipe.report.model_view import model_view_file
from omnipipe.report.plots import draw_plots
from omnipipe.report.tables import (
    calibration_row,
    defects_section,
    features_section,
    figures,
    files_table,
    motion_rows,
    summary_rows,
    survey_html,
    trajectory_note,
    truth_table,
)


def render_html(inputs: ReportInputs, config: ReportConfig | None = None) -> str:
    """The report page as one self-contained HTML string (``templates/report.html``)."""
    return "".join(_page_parts(inputs, config or ReportConfig()))


_MODEL_SLOT = "\x00omnipipe-model-view\x00"
"""Stands for the 3-D view in the filled template until the page is written out."""


def _page_parts(inputs: ReportInputs, config: ReportConfig) -> Iterator[str]:
    """The report page in pieces: the template filled in, with the 3-D view's JSON
    (the page's longest part) written a chunk at a time into it."""
    s = inputs.summary
    # The 3-D view first, into the run's scratch: the mesh's thinning and the texture's
    # PNG (a long run's largest temporaries here) not on top of what drawing the figures
    # leaves resident (matplotlib, its fonts and caches).
    view = model_view_file(inputs, config)
    release_freed_memory()
    plots = draw_plots(inputs)
    template = resources.files("omnipipe.report").joinpath("templates", "report.html")
    page = Template(template.read_text(encoding="utf-8"))
    filled = page.substitute(
        title=html.escape(config.title),
        survey=survey_html(s.get("survey")),
        summary_rows=summary_rows(s) + motion_rows(s, inputs.trajectory_quality) + calibration_row(s),
        warnings="".join(f"<p class='warn'>warning: {html.escape(str(w))}</p>" for w in s.get("warnings", [])),
        truth=truth_table(inputs.truth),
        trajectory_note=trajectory_note(inputs.evaluation),
        model_view=_MODEL_SLOT,
        defects=defects_section(inputs) + features_section(s, travel_sign(inputs)),
        figures=figures(
            plots, inputs.unrolled_alpha is not None and not np.asarray(inputs.unrolled_alpha).all()
        ),
        files=files_table(s.get("files")),
    )
    del plots
    release_freed_memory()  # the defects' relief maps read every wall point
    before, after = filled.split(_MODEL_SLOT, 1)
    del filled
    yield before
    del before
    yield from text_file_parts(view)
    yield after


def run(config: ReportConfig, inputs: ReportInputs, out_path: Path) -> Path:
    """Write report.html to ``out_path`` and return it (a piece at a time: the page is
    not held whole)."""
    out_path = Path(out_path)
    with out_path.open("w", encoding="utf-8") as fh:
        for part in _page_parts(inputs, config):
            fh.write(part)
    return out_path
