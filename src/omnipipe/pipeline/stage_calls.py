"""Each stage's call in a reconstruction run, and the records they hand on.

:func:`decode` (the frame pass: every frame's laser ring and stationary test),
:func:`camera_motion` (the sfm stage -> :class:`Motion`), :func:`analyse` (integration of
the stations' rings and the analysis stage -> :class:`Measured` and the model's
:class:`ModelFeed`) and :func:`build_model` (the model stage). Each notes its time
(seconds) and its warnings in the run's :class:`~.run_config.RunLog`; the frame pass and
the camera motion refuse what cannot go on (:class:`~omnipipe.errors.ReconstructionError`).

The ``*_on_disk`` helpers put what grows with the run (per-point and per-sample arrays,
the model's arrays) in the run's scratch (:mod:`omnipipe.spill`): equal values, dtypes
and shapes, resident only while a later step reads them. Points are mm in the world
frame; poses are ``world_from_rig`` (4, 4).
"""

from __future__ import annotations

import time
from collections.abc import Callable
from dataclasses import dataclass, fields, replace
from functools import partial
from typing import TYPE_CHECKING

from omnipipe.errors import ReconstructionError
from omnipipe.memory import release_freed_memory
from omnipipe.progress import ProgressFactory

if TYPE_CHECKING:  # imported inside the functions: `omnipipe --help` stays fast
    from concurrent.futures import Executor

    import numpy as np

    from omnipipe.analysis import AnalysisResult
    from omnipipe.contract import TrajectoryQuality
    from omnipipe.dataset import Dataset
    from omnipipe.handoff import FrameHandoff
    from omnipipe.laser.ring import LaserRing
    from omnipipe.model import ModelResult
    from omnipipe.pipeline.checkpoint import Checkpoints
    from omnipipe.pipeline.frame_pass import FramePassResult
    from omnipipe.pipeline.run_config import ReconstructConfig, RunLog
    from omnipipe.sfm import SfmResult
    from omnipipe.spill import Pack


RING_PASS_DROP_S = 0.02
"""Seconds between two page drops (:func:`omnipipe.spill.dropping_pages`) while the
station rings are integrated: those passes map every ring within a second."""


def decode(
    config: ReconstructConfig,
    dataset: Dataset,
    executor: Executor,
    progress: ProgressFactory,
    log: RunLog,
    checkpoints: Checkpoints | None = None,
    handoff: FrameHandoff | None = None,
) -> FramePassResult:
    """The decoding pass (every frame's ring and stationary test), refused without a ring.
    With ``checkpoints``, it goes on after the parts of it an earlier run saved, and
    saves its own parts as it goes. With ``handoff``, the moving frames are left there
    for the later stages (:func:`omnipipe.pipeline.frame_pass.run`).

    Raises:
        ReconstructionError: no laser ring in any frame.
    """
    import numpy as np

    from omnipipe.pipeline import frame_pass

    n = len(dataset)
    t0 = time.perf_counter()
    tick = progress("laser", n)
    # Each frame decoded once, frame-parallel: its ring and the stationary test's input.
    parts = [] if checkpoints is None else checkpoints.load_parts("frames")
    frames = frame_pass.run(
        config.laser, config.sfm.stations, dataset, executor, progress=tick, parts=parts,
        save_part=None if checkpoints is None else partial(checkpoints.save_part, "frames"),
        handoff=handoff,
    )
    log.timings["laser"] = time.perf_counter() - t0
    # A ring of a handful of samples is noise, not the laser.
    seen = int(np.sum(frames.ring_samples >= 20))
    if seen == 0:
        channel = dataset.rig.laser.channel if dataset.rig.laser is not None else "?"
        raise ReconstructionError(
            f"no laser ring found in any of the {n} frames (laser channel '{channel}' of rig.yaml)"
        )
    if seen < n:
        log.warnings.append(f"laser ring not found in {n - seen} of {n} frames")
    release_freed_memory()
    return frames


@dataclass(frozen=True)
class Motion:
    """The camera motion and the frames it gives the later stages.

    Attributes:
        result: the sfm stage's result.
        registered_frames: (R,) frames with a pose, increasing.
        stations: (K,) one frame per station that feeds the model (a stationary frame
            repeats its station's ring), increasing.
    """

    result: SfmResult
    registered_frames: np.ndarray
    stations: np.ndarray


def camera_motion(
    config: ReconstructConfig,
    dataset: Dataset,
    frames: FramePassResult,
    executor: Executor,
    progress: ProgressFactory,
    log: RunLog,
    handoff: str | None = None,
) -> Motion:
    """The sfm stage, refused when its motion cannot be trusted or nothing registered.
    ``handoff``: the folder where the decoding pass left the moving frames
    (:class:`~omnipipe.handoff.FrameHandoff`), or None.

    Raises:
        ReconstructionError: see :func:`omnipipe.pipeline.quality.refuse_untrusted_motion`;
            no frame registered.
    """
    import numpy as np

    from omnipipe import sfm
    from omnipipe.pipeline import quality

    n = len(dataset)
    t0 = time.perf_counter()
    # After its last frame, sfm adjusts the bundle window by window: a bar of its own
    # (omnipipe.progress.phase).
    tick = progress("sfm", n)
    motion = sfm.run(
        config.sfm,
        replace(
            sfm.SfmInputs.of_dataset(dataset, frames.rings, frames.moved, frames.motion_ratio),
            handoff=handoff,
        ),
        progress=tick,
        executor=executor,
    )
    log.timings["sfm"] = time.perf_counter() - t0
    quality.refuse_untrusted_motion(motion)
    log.warnings.extend(motion.warnings)
    log.warnings.extend(quality.weak_texture_warnings(motion))
    log.warnings.extend(
        f"frames {u.first_frame}-{u.last_frame}: motion unreliable ({u.reason})"
        for u in motion.unreliable
    )
    reg = np.flatnonzero(motion.registered)
    if len(reg) == 0:
        raise ReconstructionError("camera motion could not be estimated for any frame")
    stations = np.flatnonzero(motion.registered & ~motion.stationary)
    release_freed_memory()  # the features and matches of every frame
    return Motion(motion, reg, stations)


@dataclass(frozen=True)
class Measured:
    """The analysis of the stations' rings.

    Attributes:
        result: the analysis stage's result.
        quality: the camera motion check's findings.
        stations: (K,) the stations' frames.
        station_poses: (K, 4, 4) their poses.
        outliers_removed: stray wall points taken out of the stations' rings
            (:func:`omnipipe.model.outliers.reject_ring_outliers`).
    """

    result: AnalysisResult
    quality: TrajectoryQuality
    stations: np.ndarray
    station_poses: np.ndarray
    outliers_removed: int


@dataclass(frozen=True)
class _ModelFeed:
    """What the model stage reads of the rings: the integrated points (the same
    integration, not done again) and the rings' pixels; the rest of every frame's ring
    is not held through it.

    Attributes:
        points, point_frame: (N, 3) integrated ring points (mm) and (N,) the station of each.
        ring_pixels: K (M_k, 2) arrays, the rings' image positions (col, row).
    """

    points: np.ndarray
    point_frame: np.ndarray
    ring_pixels: list[np.ndarray]


def analyse(
    config: ReconstructConfig,
    dataset: Dataset,
    frames: FramePassResult,
    motion: Motion,
    executor: Executor,
    progress: ProgressFactory,
    log: RunLog,
) -> tuple[Measured, _ModelFeed]:
    """Integration and the analysis stage, first: its centreline coordinates unroll the
    mesh and the texture; and the camera motion check's report."""
    import numpy as np

    from omnipipe import analysis, model
    from omnipipe.camera import camera_from_rig
    from omnipipe.laser import extract
    from omnipipe.laser.triangulate import centroid_ring, radial_mm_per_px
    from omnipipe.model.outliers import reject_ring_outliers
    from omnipipe.pipeline import quality
    from omnipipe.spill import Pack, drop_pages, dropping_pages, pieces_on_disk

    rig, stations, sfm_result = dataset.rig, motion.stations, motion.result
    t0 = time.perf_counter()
    # The stage's bars: its centreline's stations and its defect search's passes
    # (omnipipe.progress.phase).
    station_poses = sfm_result.world_from_rig[stations]
    # The analysis's rings: clipped peaks at their centroids (camera motion kept the
    # three-point fit's).
    camera = camera_from_rig(rig)
    # Every station's ring waits in the run's scratch (omnipipe.spill) until integrated:
    # not held in memory at once (80 bytes a sample: 38 MB at 10,000 frames). The passes
    # below read every ring within a second: their pages dropped every few tens of ms.
    with dropping_pages(RING_PASS_DROP_S):
        pack = Pack()
        station_rings = [
            ring_on_disk(pack, centroid_ring(frames.rings.rings[i], camera, rig.laser)) for i in stations
        ]
        # Stray laser peaks (isolated points far off the wall) out before anything uses them.
        station_rings, outliers_removed = reject_ring_outliers(station_rings, config.model.outliers)
        # Not in memory under the rest: written into the run's scratch ring by ring.
        points, point_frame = model.integrate(station_poses, [r.points_in_rig for r in station_rings], in_scratch=True)
        reach, reach_sigma = extract.edge_reach_mm(station_rings)
        ring_reach = extract.station_edge_reach(station_rings)  # at each ring's own cut
        blur, axial_blur = extract.ring_blur_mm(station_rings), extract.axial_blur_mm(station_rings, camera)
        mm_per_px = np.array([radial_mm_per_px(r) for r in station_rings])
    drop_pages()  # every ring's pages were read (omnipipe.spill): not under the copy below
    # What the model stage reads of the rings waits in the run's scratch (omnipipe.spill):
    # not resident under the analysis.
    pixels = pieces_on_disk([r.pixels for r in station_rings])
    # The rings' other per-sample arrays (64 of their 80 bytes a sample: 29 MB at 10,000
    # frames) not held under the analysis: its inputs are the integrated points.
    del station_rings, pack
    release_freed_memory()
    res = analysis.run(
        config.analysis,
        analysis.AnalysisInputs(
            points_in_world=points,
            frame_index=point_frame,
            world_from_rig=station_poses,
            reference_from_world=np.linalg.inv(sfm_result.world_from_rig[motion.registered_frames[0]]),
            ring_blur_mm=blur,
            calibration_sigma_rel=0.0 if rig.laser is None else rig.laser.scale_sigma_rel,
            axial_blur_mm=axial_blur,
            edge_reach_mm=reach,
            edge_reach_sigma_mm=reach_sigma,
            edge_reach_rings_mm=ring_reach[0],
            edge_reach_rings_sigma_mm=ring_reach[1],
            radial_mm_per_px=mm_per_px,
        ),
        executor,
    )
    log.timings["analysis"] = time.perf_counter() - t0
    log.warnings.extend(res.warnings)
    traj_quality = quality.trajectory_quality(
        sfm_result, stations, quality.station_axial_mm(res.point_sigma_mm, point_frame, len(stations))
    )
    feed = _ModelFeed(points, point_frame, pixels)
    return analysis_on_disk(Measured(res, traj_quality, stations, station_poses, outliers_removed), feed)


def ring_on_disk(pack: Pack, ring: LaserRing) -> LaserRing:
    """``ring`` with its per-sample arrays in ``pack`` (the run's scratch,
    :class:`omnipipe.spill.Pack`: equal values, dtypes and shapes; resident only while
    read)."""
    import numpy as np

    arrays = {f.name: getattr(ring, f.name) for f in fields(ring)}
    return replace(ring, **{k: pack.put(a) for k, a in arrays.items() if isinstance(a, np.ndarray)})


def analysis_on_disk(measured: Measured, feed: _ModelFeed) -> tuple[Measured, _ModelFeed]:
    """The analysis' per-point results and the model's feed in the run's scratch
    (:mod:`omnipipe.spill`: equal values, resident only while a later step reads them)."""
    from omnipipe.spill import is_on_disk, on_disk, pieces_on_disk

    res = measured.result
    res = replace(
        res,
        point_sigma_mm=on_disk(res.point_sigma_mm),
        point_theta_rad=on_disk(res.point_theta_rad),
        point_deviation_mm=on_disk(res.point_deviation_mm),
        point_not_wall=on_disk(res.point_not_wall),
    )
    pixels = feed.ring_pixels if all(map(is_on_disk, feed.ring_pixels)) else pieces_on_disk(feed.ring_pixels)
    feed = _ModelFeed(on_disk(feed.points), on_disk(feed.point_frame), pixels)
    return replace(measured, result=res), feed


def build_model(
    config: ReconstructConfig,
    dataset: Dataset,
    measured: Measured,
    feed: _ModelFeed,
    executor: Executor,
    progress: ProgressFactory,
    log: RunLog,
    handoff: str | None = None,
) -> ModelResult:
    """The model stage on the stations, unrolled by the analysis' centreline (``handoff``:
    as in :func:`camera_motion`)."""
    import numpy as np

    from omnipipe import model
    from omnipipe.spill import zeros_on_disk

    res, stations = measured.result, measured.stations
    t0 = time.perf_counter()
    # The bar of the stations' texture opens at its first station: before it the mesh's
    # edge flips read the stations' images (a bar ``mesh`` of their own).
    bar: list[Callable[[int], None]] = []

    def tick(done: int) -> None:
        if not bar:
            bar.append(progress("model", len(stations)))
        bar[0](done)

    # The points' unrolled coordinates, in the run's scratch (omnipipe.spill) a column at
    # a time.
    unrolled_mm = zeros_on_disk((len(res.point_sigma_mm), 2), float)
    unrolled_mm[:, 0] = (res.point_theta_rad % (2 * np.pi)) * res.radius_mm
    unrolled_mm[:, 1] = res.point_sigma_mm
    model_inputs = model.ModelInputs(
        camera_rig=dataset.rig,
        world_from_rig=measured.station_poses,
        ring_points_in_rig=[],
        ring_pixels=feed.ring_pixels,
        read_frame=lambda k: dataset.read_frame(int(stations[k])),
        unrolled_mm=unrolled_mm,
        circumference_mm=2 * np.pi * res.radius_mm,
        dataset=dataset,
        frame_index=stations,
        handoff=handoff,
        points_in_world=feed.points,
        point_frame=feed.point_frame,
        not_wall=res.point_not_wall if len(res.point_not_wall) == len(feed.points) else None,
    )
    mdl = model.run(config.model, model_inputs, progress=tick, executor=executor)
    del model_inputs, unrolled_mm
    log.timings["model"] = time.perf_counter() - t0
    return model_on_disk(mdl)  # before its checkpoint: not held twice


def model_on_disk(mdl: ModelResult) -> ModelResult:
    """``mdl`` with its arrays in the run's scratch (:mod:`omnipipe.spill`: equal values,
    resident only while a later step reads them); the unrolled image stays a view of the
    texture atlas."""
    import numpy as np

    from omnipipe.spill import on_disk

    def opt(a: np.ndarray | None) -> np.ndarray | None:
        return None if a is None else on_disk(a)

    points = on_disk(mdl.points_in_world)
    texture, unrolled = opt(mdl.texture), mdl.unrolled
    if unrolled is not None:
        w = unrolled.image.shape[1]
        shares = texture is not None and np.may_share_memory(mdl.texture, unrolled.image)
        image = texture[:, :w] if shares else on_disk(unrolled.image)
        unrolled = replace(unrolled, image=image, alpha=on_disk(unrolled.alpha))
    return replace(
        mdl,
        points_in_world=points,
        colours=on_disk(mdl.colours),
        point_frame=on_disk(mdl.point_frame),
        mesh_vertices=points if mdl.mesh_vertices is mdl.points_in_world else on_disk(mdl.mesh_vertices),
        mesh_faces=on_disk(mdl.mesh_faces),
        textured_vertices=opt(mdl.textured_vertices),
        textured_faces=opt(mdl.textured_faces),
        textured_uvs=opt(mdl.textured_uvs),
        texture=texture,
        unrolled=unrolled,
    )
