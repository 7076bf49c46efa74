"""Integration and the unrolled Delaunay mesh on simulated rings with true poses."""

from __future__ import annotations

import dataclasses
from pathlib import Path

import numpy as np
import pytest
import trimesh

import omnipipe.model.stage as model_stage
from omnipipe.dataset import open_dataset
from omnipipe.errors import ShapeError
from omnipipe.executor import open_executor
from omnipipe.laser import LaserConfig
from omnipipe.laser import run as laser_run
from omnipipe.model import ModelConfig, ModelInputs, run, write_outputs
from omnipipe.sim import make_scenario, simulate_trajectory


def test_rings_integrate_onto_the_wall_and_mesh_without_crossings(
    rendered_stations, tmp_path: Path
) -> None:
    st = rendered_stations
    scenario, renderer, poses, keep, frames, rings = (
        st.scenario, st.renderer, st.poses, st.keep, st.frames, st.rings
    )
    res = run(
        ModelConfig(),
        ModelInputs(
            scenario.rig,
            poses[keep],
            [r.points_in_rig for r in rings.rings],
            [r.pixels for r in rings.rings],
            lambda k: frames[int(keep[k])],
        ),
    )
    pipe = renderer.pipe
    s, rho, th, *_ = pipe.pipe_coordinates(res.points_in_world)
    err = rho - pipe.wall_radius(s, th)
    assert np.sqrt(np.mean(err**2)) < 0.5  # mm, 400x300 images
    faces = res.mesh_faces
    assert len(faces) > len(res.points_in_world)  # a surface, not a strip
    p = res.points_in_world[faces]
    edges = np.linalg.norm(p - np.roll(p, 1, axis=1), axis=2)
    # No triangle spans across the pipe: every edge is short against the radius.
    assert edges.max() < 0.3 * pipe.radius_mm
    # Triangle normals are radial (the wall), not axial or across.
    n = np.cross(p[:, 1] - p[:, 0], p[:, 2] - p[:, 0])
    n /= np.linalg.norm(n, axis=1, keepdims=True)
    centroid = p.mean(axis=1)
    _, _, _, radial, *_ = pipe.pipe_coordinates(centroid)
    assert np.median(np.abs(np.sum(n * radial, axis=1))) > 0.9
    # ... and wound so they face the axis (the wall is seen from inside); slivers within
    # one ring lie in the laser plane (normal along the axis) and are left out.
    d = np.sum(n * radial, axis=1)
    assert np.mean(d[np.abs(d) > 0.5] < 0) > 0.95
    write_outputs(res, tmp_path)
    cloud = trimesh.load(tmp_path / "points.ply", process=False)
    mesh = trimesh.load(tmp_path / "mesh.ply", process=False)
    assert len(cloud.vertices) == len(res.points_in_world)
    assert len(mesh.faces) == len(faces) and np.allclose(
        mesh.vertices, res.points_in_world, atol=1e-3
    )


def test_frames_decoded_by_two_worker_processes_give_the_serial_model(
    small_dataset: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    dataset = open_dataset(small_dataset)
    sc = make_scenario("paper-small", seed=3)  # small_dataset's scene: its true trajectory
    poses, _, moving = simulate_trajectory(sc.pipe, sc.motion, sc.frames, sc.seed)
    keep = np.flatnonzero(np.r_[True, moving[1:]])  # one frame per station
    rings = laser_run(LaserConfig(), dataset.rig, [dataset.read_frame(int(i)) for i in keep])
    reads: list[int] = []

    def read_frame(k: int) -> np.ndarray:
        reads.append(k)
        return dataset.read_frame(int(keep[k]))

    serial_inputs = ModelInputs(
        dataset.rig,
        poses[keep],
        [r.points_in_rig for r in rings.rings],
        [r.pixels for r in rings.rings],
        read_frame,
    )
    ticks: list[int] = []
    serial = run(ModelConfig(), serial_inputs, progress=ticks.append)
    assert sorted(reads) == sorted(set(reads))  # each keyframe's image read once
    assert ticks == list(range(1, len(keep) + 1))
    reads.clear()
    parallel_inputs = dataclasses.replace(serial_inputs, dataset=dataset, frame_index=keep)
    with open_executor(2) as executor:
        parallel = run(ModelConfig(), parallel_inputs, executor=executor)
    assert not reads  # the workers decoded the frames
    assert serial.unrolled is not None and parallel.unrolled is not None
    assert serial.unrolled.alpha.mean() > 0.5
    # Held once: the unrolled image is the atlas's first columns; faces in 4-byte indices.
    assert np.shares_memory(serial.unrolled.image, serial.texture)
    assert serial.mesh_faces.dtype == np.int32 and serial.textured_faces.dtype == np.int32
    for name in (
        "points_in_world", "colours", "point_frame", "mesh_faces", "textured_vertices",
        "textured_faces", "textured_uvs", "texture",
    ):
        assert np.array_equal(getattr(serial, name), getattr(parallel, name)), name
    for name in ("image", "alpha"):
        assert np.array_equal(getattr(serial.unrolled, name), getattr(parallel.unrolled, name)), name
    # Textured a section of the pipe at a time (here 128 rows): the same model.
    assert serial.unrolled.image.shape[0] > 128  # two sections
    monkeypatch.setattr(model_stage, "SECTION_ROWS", 128)
    with open_executor(2) as executor:
        sections = run(ModelConfig(), parallel_inputs, executor=executor)
    for name in (
        "points_in_world", "colours", "point_frame", "mesh_faces", "textured_vertices",
        "textured_faces", "textured_uvs", "texture",
    ):
        assert np.array_equal(getattr(serial, name), getattr(sections, name)), name
    assert np.array_equal(serial.unrolled.alpha, sections.unrolled.alpha)
    # Given the rings already integrated (as the pipeline passes them), not the rings:
    # the same model.
    points, frame = model_stage.integrate(serial_inputs.world_from_rig, serial_inputs.ring_points_in_rig)
    given = dataclasses.replace(serial_inputs, ring_points_in_rig=[], points_in_world=points, point_frame=frame)
    integrated = run(ModelConfig(), given)
    for name in ("points_in_world", "colours", "point_frame", "mesh_faces", "texture"):
        assert np.array_equal(getattr(serial, name), getattr(integrated, name)), name
    for bad in (frame[:-1], frame + len(keep), frame.astype(float)):
        with pytest.raises(ShapeError, match="point_frame"):
            run(ModelConfig(), dataclasses.replace(given, point_frame=bad))
