"""The reconstruction pipeline: dataset in, contract outputs out.

Stages, each a ``run(config, inputs)`` of its own subpackage: ``laser`` (light
section: metric ring points per frame), ``sfm`` (camera motion, metric by the laser),
``model`` (integration, mesh, texture, unrolled wall), ``analysis`` (inner diameter,
ovality, defects) and ``report``. Outputs are written to a temporary directory next
to OUT and moved into place at the end, so a failed or interrupted run never leaves
OUT looking complete.
"""

from __future__ import annotations

import json
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any

from omnipipe.config import dataclass_from_dict, deep_merge, load_yaml_mapping
from omnipipe.errors import ReconstructionError
from omnipipe.memory import release_freed_memory

if TYPE_CHECKING:  # imported inside the functions: `omnipipe --help` stays fast
    from concurrent.futures import Executor

    import numpy as np

    from omnipipe.dataset import Dataset

ProgressFactory = Callable[[str, int], Callable[[int], None]]


def _no_progress(stage: str, total: int) -> Callable[[int], None]:
    return lambda done: None


@dataclass(frozen=True)
class ReconstructConfig:
    """Settings of every stage; ``--config FILE.yaml`` overrides any of them by section.

    ``workers`` (local processes, None: every core, 1: serial) and ``scheduler`` (a Dask
    scheduler address ``tcp://HOST:PORT``, or None) choose the executor of the
    frame-parallel work (:mod:`omnipipe.executor`; ``--workers``, ``--scheduler``).
    """

    laser: Any = None
    sfm: Any = None
    model: Any = None
    analysis: Any = None
    report: Any = None
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
        parts = {}
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
class Reconstruction:
    """Everything a run produced, before it is written.

    Attributes:
        summary: the report.json content.
        timestamps: (N,) seconds of the registered frames.
        world_from_rig: (N, 4, 4) poses of the registered frames.
        model: the model stage result.
        analysis: the analysis stage result.
        report_config: how report.html is drawn (the ``report`` section of the config).
        frame_index: (N,) 0-based frame index of each registered pose.
        survey: the :class:`omnipipe.survey.Survey` header (survey.yaml), or None.
    """

    summary: dict[str, Any]
    timestamps: np.ndarray
    world_from_rig: np.ndarray
    model: Any
    analysis: Any
    report_config: Any = None
    frame_index: np.ndarray | None = None
    survey: Any = None


def run(
    config: ReconstructConfig,
    dataset: Dataset,
    progress: ProgressFactory = _no_progress,
    executor: Executor | None = None,
) -> Reconstruction:
    """Run every stage on ``dataset``.

    ``executor`` does the frame-parallel work (default: one opened from
    ``config.workers`` / ``config.scheduler`` for this run, :mod:`omnipipe.executor`).

    Raises:
        OmnipipeError: bad input (named file or field) or a stage that cannot proceed.
    """
    if executor is None:
        from omnipipe.executor import open_executor

        with open_executor(config.workers, config.scheduler) as pool:
            return run(config, dataset, progress, pool)
    if dataset.rig.laser is None:  # a camera-only rig (rig.yaml without a laser section)
        raise ReconstructionError(
            "rig.yaml has no laser section: a camera-only rig cannot reconstruct "
            "(add laser.plane, e.g. from omnipipe calibrate laser)"
        )
    import numpy as np

    from omnipipe import analysis, model, sfm
    from omnipipe.camera import camera_from_rig
    from omnipipe.dataset import validate_frames
    from omnipipe.executor import describe as describe_executor
    from omnipipe.inputs.lossy import assess_input
    from omnipipe.laser.extract import axial_blur_mm, ring_blur_mm
    from omnipipe.model.export import model_files
    from omnipipe.model.outliers import reject_ring_outliers
    from omnipipe.pipeline import frame_pass, quality

    timings: dict[str, float] = {}
    warnings: list[str] = []
    t_start = time.perf_counter()
    validate_frames(dataset)
    rig = dataset.rig
    n = len(dataset)
    warnings.extend(dataset.warnings)  # e.g. a truncated video
    input_quality = assess_input(dataset)  # lossy (JPEG/MPEG) input degrades everything
    if input_quality.warning:
        warnings.append(input_quality.warning)
    # The compiled kernels and per-rig tables of the decoding pass, made here once
    # rather than in every worker (the local pool's workers are forked from this process).
    frame_pass.warm_up(config.laser, config.sfm.stations, rig)
    timings["startup"] = time.perf_counter() - t_start

    t0 = time.perf_counter()
    tick = progress("laser", n)
    # Each frame decoded once, frame-parallel: its ring and the stationary test's input.
    frames = frame_pass.run(config.laser, config.sfm.stations, dataset, executor, progress=tick)
    rings = frames.rings
    timings["laser"] = time.perf_counter() - t0
    # A ring of a handful of samples is noise, not the laser.
    seen = int(np.sum(frames.ring_samples >= 20))
    if seen == 0:
        raise ReconstructionError(
            f"no laser ring found in any of the {n} frames (laser channel '{rig.laser.channel}' of rig.yaml)"
        )
    if seen < n:
        warnings.append(f"laser ring not found in {n - seen} of {n} frames")
    release_freed_memory()

    t0 = time.perf_counter()
    sfm_tick = progress("sfm", n)
    # After its last frame, sfm adjusts the bundle and checks the scale: a bar of its own.
    after_frames: list[Callable[[int], None]] = []

    def tick(done: int) -> None:
        sfm_tick(done)
        if done >= n and not after_frames:
            after_frames.append(progress("bundle", 1))

    motion = sfm.run(
        config.sfm,
        sfm.SfmInputs(
            rig=rig, read_frame=dataset.read_frame, n_frames=n, rings=rings,
            moved=frames.moved, dataset=dataset,
        ),
        progress=tick,
        executor=executor,
    )
    if not after_frames:
        after_frames.append(progress("bundle", 1))
    after_frames[0](1)
    timings["sfm"] = time.perf_counter() - t0
    quality.refuse_untrusted_motion(motion)
    warnings.extend(motion.warnings)
    warnings.extend(
        f"frames {u.first_frame}-{u.last_frame}: motion unreliable ({u.reason})"
        for u in motion.unreliable
    )
    reg = np.flatnonzero(motion.registered)
    if len(reg) == 0:
        raise ReconstructionError("camera motion could not be estimated for any frame")
    # One frame per station feeds the model: a stationary frame repeats its station's ring.
    stations = np.flatnonzero(motion.registered & ~motion.stationary)
    release_freed_memory()  # the features and matches of every frame

    # Analysis first: its centreline coordinates unroll the mesh and the texture.
    t0 = time.perf_counter()
    tick = progress("analysis", 2)
    station_poses = motion.world_from_rig[stations]
    station_rings = [rings.rings[i] for i in stations]
    # Stray laser peaks (isolated points far off the wall) out before anything uses them.
    station_rings, outliers_removed = reject_ring_outliers(station_rings)
    points, point_frame = model.integrate(station_poses, [r.points_in_rig for r in station_rings])
    tick(1)
    res = analysis.run(
        config.analysis,
        analysis.AnalysisInputs(
            points_in_world=points,
            frame_index=point_frame,
            world_from_rig=station_poses,
            reference_from_world=np.linalg.inv(motion.world_from_rig[reg[0]]),
            ring_blur_mm=ring_blur_mm(station_rings),
            calibration_sigma_rel=rig.laser.scale_sigma_rel,
            axial_blur_mm=axial_blur_mm(station_rings, camera_from_rig(rig)),
        ),
        executor,
    )
    timings["analysis"] = time.perf_counter() - t0
    tick(2)
    warnings.extend(res.warnings)
    traj_quality = quality.trajectory_quality(
        motion, stations, quality.station_axial_mm(res.point_sigma_mm, point_frame, len(stations))
    )
    # What the model stage reads of the rings: the integrated points (the same
    # integration, not done again) and the rings' pixels. The rest of every frame's ring
    # is not held through it.
    ring_pixels = [r.pixels for r in station_rings]
    del frames, rings, station_rings
    release_freed_memory()

    t0 = time.perf_counter()
    tick = progress("model", len(stations))
    circ = 2 * np.pi * res.radius_mm
    model_inputs = model.ModelInputs(
        camera_rig=rig,
        world_from_rig=station_poses,
        ring_points_in_rig=[],
        ring_pixels=ring_pixels,
        read_frame=lambda k: dataset.read_frame(int(stations[k])),
        unrolled_mm=np.column_stack(
            [(res.point_theta_rad % (2 * np.pi)) * res.radius_mm, res.point_sigma_mm]
        ),
        circumference_mm=circ,
        dataset=dataset,
        frame_index=stations,
        points_in_world=points,
        point_frame=point_frame,
    )
    del ring_pixels, points, point_frame
    mdl = model.run(config.model, model_inputs, progress=tick, executor=executor)
    del model_inputs
    timings["model"] = time.perf_counter() - t0
    timings["total"] = time.perf_counter() - t_start
    # Every measurement with its 1-sigma (lengths along the pipe: the motion's scale sigma).
    measured, measure_warnings = analysis.report_fields(
        res, getattr(motion, "scale_sigma_rel", float("nan")), config.analysis
    )
    warnings.extend(measure_warnings)
    if len(measured.get("stations", [])) == len(stations):
        for entry, frame in zip(measured["stations"], stations, strict=True):
            entry["frame"] = int(frame)  # the frame whose ring this station is
    warnings.extend(quality.flag_defects(measured.get("defects", []), traj_quality))
    warnings.extend(quality.widen_for_unreliable(measured, traj_quality))
    summary = {
        "frames": n,
        "frames_registered": len(reg),
        **measured,
        "timings_s": {k: round(v, 3) for k, v in timings.items()},
        # Frames of the run per second of each stage (and of the whole run).
        "frames_per_s": {
            k: round(n / v, 3) if v > 0 else None for k, v in timings.items() if k != "startup"
        },
        "executor": describe_executor(executor),
        "warnings": warnings,
        "stationary_frames": int(np.sum(motion.stationary)),
        "wall_outliers_removed": outliers_removed,
        "files": model_files(mdl),  # each 3-D file's unit and axes
        "mesh": {
            "vertices": int(len(mdl.mesh_vertices)),
            "faces": int(len(mdl.mesh_faces)),
            "flips_per_pass": [] if mdl.flip_stats is None else mdl.flip_stats.flips,
            "photo_inconsistency_before": None if mdl.flip_stats is None else round(mdl.flip_stats.cost_before, 3),
            "photo_inconsistency_after": None if mdl.flip_stats is None else round(mdl.flip_stats.cost_after, 3),
        },
        "keyframes": int(np.sum(motion.keyframe)),
        "tracked_frames": 0 if motion.tracked is None else int(np.sum(motion.tracked)),
        "trajectory_quality": traj_quality,
        "input_quality": input_quality.to_dict(),
    }
    return Reconstruction(
        summary=summary,
        timestamps=dataset.timestamps[reg],
        world_from_rig=motion.world_from_rig[reg],
        model=mdl,
        analysis=res,
        report_config=config.report,
        frame_index=reg,
    )


def write(
    rec: Reconstruction,
    out: str | Path,
    *,
    force: bool = False,
    evaluation: dict | None = None,
    protect: Sequence[str | Path] = (),
    progress: ProgressFactory = _no_progress,
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
    from omnipipe import model as model_stage
    from omnipipe import report
    from omnipipe.dataset import atomic_output_dir, write_tum
    from omnipipe.report.deliverable import write_deliverable

    out = Path(out)
    with atomic_output_dir(out, force=force, protect=protect) as tmp:
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
            rec.model.unrolled,
            rec.survey,
            travel_along_rig_z=float(rec.world_from_rig[-1][2, 3] - rec.world_from_rig[0][2, 3]),
        )
        tick(3)
    return out


def report_inputs(rec: Reconstruction, evaluation: dict | None = None):
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
        stations_axial_mm=res.stations_axial_mm,
        stations_diameter_mm=res.stations_diameter_mm,
        stations_ovality=res.stations_ovality,
        radius_mm=None if res.inner_diameter_mm is None else res.inner_diameter_mm / 2,
        truth=truth,
        evaluation=evaluation,
        frame_index=rec.frame_index,
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
