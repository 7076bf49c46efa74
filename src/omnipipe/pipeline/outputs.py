"""Writing a run's contract outputs.

:func:`write`: the trajectory, the model files, report.json, report.html and the
deliverable (defects.csv, defects/*.png, features) of a
:class:`~.reconstruct.Reconstruction`, into a temporary folder moved into place at the end
(:mod:`omnipipe.output`), so a failed or interrupted write never leaves OUT looking
complete. :func:`report_inputs`: what report.html shows; :func:`table_one`: the paper's
Table I rows (measured, 1-sigma, true; mm) from an evaluation.
"""

from __future__ import annotations

import json
from collections.abc import Sequence
from pathlib import Path
from typing import TYPE_CHECKING, Any

from omnipipe.pipeline.run_config import no_progress
from omnipipe.pipeline.summary import wall_points
from omnipipe.progress import ProgressFactory

if TYPE_CHECKING:  # imported inside the functions: `omnipipe --help` stays fast
    from omnipipe.pipeline.reconstruct import Reconstruction
    from omnipipe.report import ReportInputs


def write(
    rec: Reconstruction,
    out: str | Path,
    *,
    force: bool = False,
    evaluation: dict[str, Any] | None = None,
    protect: Sequence[str | Path] = (),
    progress: ProgressFactory = no_progress,
) -> Path:
    """Write the contract outputs of ``rec`` to ``out`` atomically, with a manifest.

    ``force`` replaces only an earlier omnipipe output (see :mod:`omnipipe.output`);
    ``protect`` lists inputs (dataset, config file) that ``out`` may not be or hold.
    ``progress`` draws a bar ``output`` over the files written. Besides the contract's
    files: defects.csv and defects/*.png (:mod:`omnipipe.report.deliverable`).

    Raises:
        OutputError: ``out`` exists (without ``force``), is not omnipipe's, or cannot be
            written.
    """
    import gc

    from omnipipe import model as model_stage
    from omnipipe import report
    from omnipipe.dataset import atomic_output_dir, write_tum
    from omnipipe.memory import release_freed_memory
    from omnipipe.report.clock import clock_reference
    from omnipipe.report.deliverable import write_deliverable
    from omnipipe.report.features_csv import write_features

    # The run's cyclic garbage (freed only when the collector next runs) and the pages
    # it held, not under the writers.
    gc.collect()
    release_freed_memory()
    out = Path(out)
    travel = float(rec.world_from_rig[-1][2, 3] - rec.world_from_rig[0][2, 3]) if len(rec.world_from_rig) else 1.0
    rec.summary["clock_reference"] = clock_reference(
        rec.survey, rec.up_in_rig, travel, rec.up_sigma_rad
    ).to_dict()
    from omnipipe.spill import dropping_pages

    with dropping_pages(), atomic_output_dir(out, force=force, protect=protect) as tmp:
        tick = progress("output", 3)
        write_tum(tmp / "trajectory.txt", rec.timestamps, rec.world_from_rig)
        model_stage.write_outputs(rec.model, tmp)
        tick(1)
        (tmp / "report.json").write_text(json.dumps(rec.summary, indent=1), encoding="utf-8")
        report.run(
            rec.report_config or report.ReportConfig(),
            report_inputs(rec, evaluation),
            tmp / "report.html",
        )
        tick(2)
        write_deliverable(
            tmp,
            rec.summary,
            rec.defects,
            rec.model.unrolled,
            rec.survey,
            travel_along_rig_z=travel,
            views=rec.defect_views,
        )
        write_features(
            tmp, rec.summary, rec.survey,
            travel_along_rig_z=float(rec.world_from_rig[-1][2, 3] - rec.world_from_rig[0][2, 3]),
        )
        tick(3)
    return out


def report_inputs(rec: Reconstruction, evaluation: dict[str, Any] | None = None) -> ReportInputs:
    """What report.html shows, from a reconstruction (and optional evaluation)."""
    from omnipipe.report import ReportInputs

    mdl, res = rec.model, rec.analysis
    truth = None
    if evaluation:
        truth = table_one(rec.summary, evaluation)
    return ReportInputs(
        summary=rec.summary,
        world_from_rig=rec.world_from_rig,
        mesh_vertices=mdl.mesh_vertices if mdl.textured_vertices is None else mdl.textured_vertices,
        mesh_faces=mdl.mesh_faces if mdl.textured_faces is None else mdl.textured_faces,
        mesh_uvs=mdl.textured_uvs,
        texture=mdl.texture,
        unrolled=None if mdl.unrolled is None else mdl.unrolled.image,
        unrolled_extent=None if mdl.unrolled is None else mdl.unrolled.extent,
        unrolled_alpha=None if mdl.unrolled is None else mdl.unrolled.alpha,
        stations_axial_mm=res.stations_axial_mm,
        stations_diameter_mm=res.stations_diameter_mm,
        stations_ovality=res.stations_ovality,
        radius_mm=None if res.inner_diameter_mm is None else res.inner_diameter_mm / 2,
        truth=truth,
        evaluation=evaluation,
        frame_index=rec.frame_index,
        defects=rec.defects,
        trajectory_quality=rec.trajectory_quality,
        wall=wall_points(res),
        defect_views=rec.defect_views,
        wall_points_in_world=mdl.points_in_world,
    )


def table_one(
    summary: dict[str, Any], evaluation: dict[str, Any]
) -> list[tuple[str, float | None, float | None, float | None, str]]:
    """The paper's Table I rows (name, measured, its 1-sigma, true, unit) from an evaluation."""
    rows: list[tuple[str, float | None, float | None, float | None, str]] = []
    d = evaluation.get("diameter", {})
    rows.append(
        (
            "inside diameter",
            d.get("measured_mm"),
            summary.get("inner_diameter_sigma_mm"),
            d.get("true_mm"),
            "mm",
        )
    )
    for k, row in enumerate(evaluation.get("defects", [])):
        t = row.get("true")
        if t is None:
            continue
        m = row.get("measured") or {}
        name = f"{t['kind']} {k + 1}"
        for what in ("height", "width", "length"):
            rows.append(
                (
                    f"{what} of {name}",
                    m.get(f"{what}_mm"),
                    m.get(f"{what}_sigma_mm"),
                    t[f"{what}_mm"],
                    "mm",
                )
            )
    return rows
