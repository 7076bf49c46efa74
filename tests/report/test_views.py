"""Relief maps, camera views and 3-D markers of defects (omnipipe.report.relief, .views)."""

from __future__ import annotations

import json
import math

import numpy as np
import pytest

from omnipipe.analysis.sizing import plateau
from omnipipe.camera import camera_from_rig
from omnipipe.contract import Defect
from omnipipe.evaluation.stage import _coverage
from omnipipe.report.relief import WallPoints, deviation_grid
from omnipipe.report.views import best_frame, camera_view, centre_point
from omnipipe.sim.scenarios import make_scenario

RADIUS = 100.0


def _wall(gap: tuple[float, float] | None = None) -> tuple[WallPoints, np.ndarray]:
    """Rings every 5 mm, 720 samples each, a 3 mm bulge at 90 deg, 100-150 mm; the
    points' world positions on a cylinder about z."""
    z, ang = np.meshgrid(np.arange(0.0, 300.0, 5.0), np.arange(720) * 0.5, indexing="ij")
    z, ang = z.ravel(), ang.ravel()
    if gap is not None:
        keep = (z < gap[0]) | (z > gap[1])
        z, ang = z[keep], ang[keep]
    du = ((ang - 90.0 + 180.0) % 360.0 - 180.0) * math.pi / 180.0 * RADIUS
    dev = -3.0 * plateau(du, 10.0, 4.0) * plateau(z - 125.0, 50.0, 10.0)
    r = RADIUS + dev
    world = np.column_stack([r * np.cos(np.radians(ang)), r * np.sin(np.radians(ang)), z])
    return WallPoints(z, ang, dev, RADIUS), world


def _bulge(**kw) -> Defect:
    base = dict(kind="bulge", height_mm=3.0, width_mm=10.0, length_mm=50.0, axial_start_mm=100.0, angle_deg=90.0)
    return Defect(**(base | kw))


def test_relief_grid_shows_the_bulge_and_leaves_gaps_blank() -> None:
    wall, _ = _wall(gap=(180.0, 240.0))
    grid = deviation_grid(wall, (0.0, 300.0), (0.0, 360.0), cell_mm=2.0)
    cell_deg = math.degrees(2.0 / RADIUS)
    row, col = int(125 // 2), int(90 // cell_deg)
    assert abs(grid[row, col] + 3.0) < 0.2  # the crest, mm (negative: into the pipe)
    assert abs(grid[row, int(270 // cell_deg)]) < 0.05  # the sound wall opposite
    assert np.isnan(grid[int(210 // 2), col])  # the unmeasured stretch stays blank
    assert np.isfinite(grid[int(52 // 2), col])  # between rings 5 mm apart: filled


def test_camera_view_of_a_defect_through_the_camera_model() -> None:
    """The paper rig 150 mm up a 202 mm pipe from the defect: the centre point is found on
    the wall, the frame that sees it is chosen, and the view shows it where the rays say."""
    wall, world = _wall()
    d = _bulge()
    p = centre_point(d, wall, world)
    assert p is not None and abs(p[2] - 125.0) <= 2.5 and abs(math.atan2(p[1], p[0]) - math.pi / 2) < 0.01
    rig = make_scenario("paper-small").rig
    camera = camera_from_rig(rig)
    poses = np.repeat(np.eye(4)[None], 3, axis=0)
    poses[:, 2, 3] = [-2000.0, 125.0 + 82.0, 125.0 + 150.0]  # far away / laser ring on it / ahead
    found = best_frame(p, poses, camera)
    assert found is not None
    k, p_rig = found
    _, valid = camera.project(p_rig[None])
    assert valid[0] and k in (1, 2)
    image = np.zeros((camera.height, camera.width, 3), np.uint8)
    px, _ = camera.project(p_rig[None])
    c, r = np.round(px[0]).astype(int)
    image[r - 2 : r + 3, c - 2 : c + 3] = 255  # a bright spot where the defect centre is imaged
    view = camera_view(image, camera, d, p_rig)
    assert view.shape == (320, 320, 3) and view.dtype == np.uint8
    bright = np.argwhere(view.max(axis=2) == 255)
    assert len(bright)
    # The spot lands at the view's centre (the view looks at the defect's centre).
    assert np.all(np.abs(bright.mean(axis=0) - 159.5) < 12)


def test_3d_view_has_a_marker_per_defect() -> None:
    from omnipipe.report import ReportConfig
    from omnipipe.report.inputs import ReportInputs
    from omnipipe.report.model_view import _model_json

    wall, world = _wall()
    faces = np.array([[0, 1, 2]])
    inputs = ReportInputs(
        summary={}, world_from_rig=np.eye(4)[None], mesh_vertices=world, mesh_faces=faces,
        defects=[_bulge(truncated=True)], wall=wall, wall_points_in_world=world,
    )
    model = json.loads(_model_json(inputs, ReportConfig()))
    (marker,) = model["markers"]
    assert marker["label"] == "#1 bulge (truncated)" and marker["href"] == "#defect-1"
    assert abs(marker["position"][2] - 125.0) <= 2.5


def test_evaluation_says_where_a_true_defect_lies() -> None:
    report = {"stations": [{"axial_mm": -82.0}, {"axial_mm": 33.7}]}
    assert _coverage(_bulge(axial_start_mm=-50.0, length_mm=100.0), report) == "partly"
    assert _coverage(_bulge(axial_start_mm=-60.0, length_mm=40.0), report) == "inside"
    assert _coverage(_bulge(axial_start_mm=150.0, length_mm=40.0), report) == "outside"
    assert _coverage(_bulge(), {}) == "unknown"


def test_distance_axis_ticks_round_metres_and_wraps_its_label() -> None:
    """The inspector's distance axis: ticks at round metres from the origin (not round
    axial mm shifted by its offset), every label exact, no "-0.00", and a long label
    wrapped to a short axes (no blank band in the saved figure)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from omnipipe.report.relief import distance_axis

    fig, ax = plt.subplots(figsize=(6, 1.2))
    ax.set_ylim(84.0, -82.0)  # an image's inverted axis: axial mm
    distance_axis(ax, 0.0821, "first measured ring (no survey.yaml)")
    fig.canvas.draw()
    labels = [t.get_text() for t in ax.get_yticklabels()]
    assert labels == ["0.025", "0.050", "0.075", "0.100", "0.125", "0.150"]
    assert all(abs(float(t) - (0.0821 + z / 1000.0)) < 1e-9 for t, z in zip(labels, ax.get_yticks(), strict=True))
    assert ax.get_ylabel().count("\n") >= 1
    fig, ax = plt.subplots()
    ax.set_ylim(-0.2, 300.0)
    distance_axis(ax, 0.0, "start node MH-1")
    fig.canvas.draw()
    assert "-0.00" not in [t.get_text() for t in ax.get_yticklabels()]
    plt.close("all")


def test_3d_view_thinned_to_max_faces_keeps_only_their_vertices() -> None:
    """Thinned to max_faces, the view holds at most max_faces triangles and only their
    vertices, each one of the mesh's own with its own position and UV
    (:mod:`omnipipe.report.thin`), so its size does not grow with the run's vertices."""
    from dataclasses import replace

    from omnipipe.report import ReportConfig
    from omnipipe.report.inputs import ReportInputs
    from omnipipe.report.model_view import _model_json

    rng = np.random.default_rng(2)
    verts = rng.normal(0.0, 100.0, (400, 3))
    uvs = rng.random((400, 2))
    faces = rng.integers(0, 400, (300, 3))
    inputs = ReportInputs(summary={}, world_from_rig=np.eye(4)[None], mesh_vertices=verts,
                          mesh_faces=faces, mesh_uvs=uvs)
    model = json.loads(_model_json(inputs, replace(ReportConfig(), max_faces=100)))
    pos = np.array(model["positions"]).reshape(-1, 3)
    uv = np.array(model["uvs"]).reshape(-1, 2)
    tri = np.array(model["indices"]).reshape(-1, 3)
    assert 0 < len(tri) <= 100 and len(pos) == len(np.unique(tri)) == len(uv)
    # Each view vertex is a mesh vertex ("%.2f" mm), with that vertex's UV (v flipped).
    nearest = np.argmin(np.linalg.norm(verts[None] - pos[:, None], axis=2), axis=1)
    assert np.allclose(pos, verts[nearest], atol=0.005)
    assert np.allclose(uv, np.stack([uvs[:, 0], 1 - uvs[:, 1]], axis=1)[nearest], atol=5e-6)


def test_joints_and_laterals_are_marked_in_3d_and_on_the_unrolled_wall() -> None:
    """A lateral's marker sits on the wall at its clock and distance; a joint without an
    offset direction at 12:00 (image up here: no gravity); both link to the features table.
    (Their labels on the unrolled wall are pixels: the page renders with them, the
    screenshots of issue 31's closing note show them.)"""
    from omnipipe.report import ReportConfig
    from omnipipe.report.html import render_html
    from omnipipe.report.inputs import ReportInputs
    from omnipipe.report.model_view import _model_json

    wall, world = _wall()
    feats = [
        {"kind": "lateral", "axial_mm": 200.0, "angle_deg": 30.0, "diameter_mm": 50.0},
        {"kind": "joint", "axial_mm": 60.0, "gap_mm": 6.0, "offset_mm": 0.2, "offset_sigma_mm": 0.3},
        {"kind": "water", "axial_from_mm": 0.0, "axial_to_mm": 300.0, "depth_mm": 10.0},
    ]
    inputs = ReportInputs(
        summary={"features": feats}, world_from_rig=np.eye(4)[None], mesh_vertices=world,
        mesh_faces=np.array([[0, 1, 2]]), wall=wall, wall_points_in_world=world,
        unrolled=np.full((300, 360, 3), 90, np.uint8), unrolled_extent=(0.0, 360.0, 0.0, 300.0),
        radius_mm=RADIUS,
    )
    # The branch seen through the opening (points 30 mm outside the wall) is not wall.
    branch = np.hypot((wall.angle_deg - 30.0) * math.pi / 180.0 * RADIUS, wall.axial_mm - 200.0) < 20.0
    wall.deviation_mm[branch] = 30.0
    world[branch, :2] *= (RADIUS + 30.0) / RADIUS
    model = json.loads(_model_json(inputs, ReportConfig()))
    lateral, joint = model["markers"]
    # On the wall at the opening's rim, not on the branch behind it.
    assert abs(np.hypot(lateral["position"][0], lateral["position"][1]) - RADIUS) < 3.5
    assert lateral["label"] == "lateral" and joint["label"] == "joint"
    assert lateral["href"] == joint["href"] == "#features"
    rim = np.hypot(
        (math.degrees(math.atan2(lateral["position"][1], lateral["position"][0])) - 30.0) * math.pi / 180.0 * RADIUS,
        lateral["position"][2] - 200.0,
    )
    assert 19.0 <= rim <= 22.0
    # 12:00 without gravity is image up: omnipipe angle 270 deg (-y) for travel along +z.
    assert abs(joint["position"][2] - 60.0) <= 2.5
    assert abs(math.degrees(math.atan2(joint["position"][1], joint["position"][0])) % 360.0 - 270.0) <= 0.5
    assert "id='features'" in render_html(inputs)


def test_deviation_grid_a_chunk_of_points_at_a_time_is_the_one_pass_grid(monkeypatch) -> None:
    """Binned a chunk of points at a time (bounded temporaries), the grid is bit for bit
    the one the whole run's points binned at once give (same sums in the same order)."""
    import omnipipe.report.relief as relief

    rng = np.random.default_rng(11)
    n = 5000
    dev = rng.normal(0.0, 0.3, n)
    dev[rng.integers(0, n, 40)] = np.nan  # unmeasured deviations are left out
    wall = WallPoints(rng.uniform(-20, 320, n), rng.uniform(0, 360, n), dev, radius_mm=100.0)
    whole = deviation_grid(wall, (0.0, 300.0), (30.0, 390.0), cell_mm=2.0)
    monkeypatch.setattr(relief, "_POINTS_AT_ONCE", 333)  # many chunks, a ragged last one
    chunked = deviation_grid(wall, (0.0, 300.0), (30.0, 390.0), cell_mm=2.0)
    assert np.array_equal(whole, chunked, equal_nan=True)
    # The one-pass binning written out (the grid before its gaps are filled).
    cell_deg = np.degrees(2.0 / 100.0)
    rows, cols = 150, int(np.ceil(360.0 / cell_deg))
    r = np.floor(wall.axial_mm / 2.0).astype(np.int64)
    c = np.floor(((wall.angle_deg - 30.0) % 360.0) / cell_deg).astype(np.int64)
    keep = (r >= 0) & (r < rows) & (c < cols) & np.isfinite(dev)
    total = np.bincount(r[keep] * cols + c[keep], dev[keep], rows * cols)
    count = np.bincount(r[keep] * cols + c[keep], None, rows * cols)
    measured = count > 0
    assert np.array_equal(chunked.reshape(-1)[measured], total[measured] / count[measured])


def test_3d_view_texture_written_in_pieces_is_the_whole_data_uri(monkeypatch) -> None:
    """The texture's data URI goes into the 3-D view's JSON a piece of base64 at a time
    (never held whole, nor copied by the JSON's escaping): the same text as the whole
    URI in the JSON, "</" in a label still escaped."""
    import omnipipe.report.encode as E
    import omnipipe.report.model_view as M
    from omnipipe.report import ReportConfig, ReportInputs

    rng = np.random.default_rng(3)
    texture = rng.integers(0, 256, (61, 47, 3), dtype=np.uint8)  # noisy: a PNG of many pieces
    verts = rng.normal(0.0, 10.0, (5, 3))
    inputs = ReportInputs(
        summary={"features": [{"kind": "joint", "axial_mm": 1.0, "gap_mm": 1.0, "offset_mm": 0.1,
                               "offset_sigma_mm": 0.1}]},
        world_from_rig=np.eye(4)[None], mesh_vertices=verts, mesh_faces=np.array([[0, 1, 2], [2, 3, 4]]),
        mesh_uvs=rng.random((5, 2)), texture=texture,
    )
    monkeypatch.setattr(E, "_BASE64_PIECE", 3 * 11)
    parts = list(M._model_json_parts(inputs, ReportConfig()))
    text = "".join(parts)
    assert len(parts) > 100  # the URI in pieces
    uri = E.png_data_uri(texture)
    model = json.loads(text)
    assert model["texture"] == uri
    # Byte for byte the JSON of the whole URI (json.dumps as before, "</" escaped).
    tail = {k: model[k] for k in ("markers", "texture", "centre", "radius")}
    whole = json.dumps(tail, separators=(",", ":"))[1:].replace("</", "<\\/")
    assert text.endswith(whole)


def _nearest_reference(axial: float, angle: float, wall: WallPoints, pts: np.ndarray, on_wall: float | None):
    """nearest_wall_point as it was: the distances of every point at once, one np.argmin."""
    du = ((wall.angle_deg - angle + 180.0) % 360.0 - 180.0) * np.pi / 180.0 * wall.radius_mm
    dz = wall.axial_mm - axial
    d2 = du * du + dz * dz
    if on_wall is not None:
        d2 = np.where(np.abs(wall.deviation_mm) <= on_wall, d2, np.inf)
        if not np.isfinite(d2).any():
            return None
    return pts[int(np.argmin(d2))]


@pytest.mark.parametrize("chunk", [7, 1000, 1 << 16])
def test_nearest_wall_point_a_chunk_at_a_time_is_the_one_pass_argmin(monkeypatch, chunk: int) -> None:
    """The first nearest point, as one argmin over every point: ties to the first, a NaN
    distance first of all, points off the wall left out (None when all are)."""
    import omnipipe.report.views as views

    monkeypatch.setattr(views, "_POINTS_AT_ONCE", chunk)
    rng = np.random.default_rng(12)
    n = 3000
    axial = np.round(rng.uniform(0, 300, n), 0)  # many ties
    angle = np.round(rng.uniform(0, 360, n), 0)
    dev = rng.normal(0.0, 2.0, n)
    pts = rng.normal(0.0, 50.0, (n, 3))
    wall = WallPoints(axial, angle, dev, radius_mm=100.0)
    for z, a in [(150.0, 20.0), (0.0, 359.0), (299.0, 181.0)]:
        for on_wall in (None, 1.0, -1.0):
            want = _nearest_reference(z, a, wall, pts, on_wall)
            got = views.nearest_wall_point(z, a, wall, pts, on_wall)
            assert (got is None) == (want is None)
            assert got is None or np.array_equal(got, want)
    axial[2500] = np.nan  # a NaN distance: argmin's first NaN
    assert np.array_equal(views.nearest_wall_point(10.0, 10.0, wall, pts), pts[2500])


@pytest.mark.parametrize("max_px", [40, 23, 61])
def test_3d_view_texture_resized_into_the_scratch_is_cv2s_resize(max_px: int) -> None:
    """A texture larger than ``texture_max_px`` is area-averaged into an array in the
    run's scratch: the same PNG as cv2's resize into a new array."""
    import cv2

    import omnipipe.report.encode as E
    import omnipipe.report.model_view as M
    from omnipipe.report import ReportConfig, ReportInputs

    rng = np.random.default_rng(16)
    from omnipipe.spill import on_disk

    texture = on_disk(rng.integers(0, 256, (61, 47, 3), dtype=np.uint8))
    inputs = ReportInputs(
        summary={}, world_from_rig=np.eye(4)[None], mesh_vertices=rng.normal(0.0, 10.0, (5, 3)),
        mesh_faces=np.array([[0, 1, 2], [2, 3, 4]]), mesh_uvs=rng.random((5, 2)), texture=texture,
    )
    model = json.loads("".join(M._model_json_parts(inputs, ReportConfig(texture_max_px=max_px))))
    scale = max_px / 61
    want = texture if scale >= 1 else cv2.resize(np.array(texture), None, fx=scale, fy=scale, interpolation=cv2.INTER_AREA)
    assert model["texture"] == E.png_data_uri(want)


def test_3d_view_frames_the_meshed_wall_not_the_points_no_face_uses() -> None:
    """The mesh's vertex array is the whole point cloud; points no face uses (a lateral's
    branch, a stray point a metre off) neither reach the view nor move its camera: the
    view's centre and radius are the faces' own."""
    from omnipipe.report import ReportConfig
    from omnipipe.report.inputs import ReportInputs
    from omnipipe.report.model_view import _model_json

    rng = np.random.default_rng(5)
    angle = rng.uniform(0.0, 2.0 * math.pi, 60)
    z = rng.uniform(0.0, 100.0, 60)
    wall = np.column_stack([RADIUS * np.cos(angle), RADIUS * np.sin(angle), z])
    stray = np.array([[1130.0, 808.0, -92.0], [1025.0, 746.0, -93.0]])
    verts = np.concatenate([wall[:30], stray, wall[30:]])
    used = np.delete(np.arange(len(verts)), [30, 31])
    # Every wall point in some face, then random triangles.
    faces = np.concatenate([used.reshape(-1, 3), used[rng.integers(0, len(used), (40, 3))]])
    uvs = rng.random((len(verts), 2))
    inputs = ReportInputs(summary={}, world_from_rig=np.eye(4)[None], mesh_vertices=verts,
                          mesh_faces=faces, mesh_uvs=uvs)
    model = json.loads(_model_json(inputs, ReportConfig()))
    pos = np.array(model["positions"]).reshape(-1, 3)
    tri = np.array(model["indices"]).reshape(-1, 3)
    assert len(pos) == len(np.unique(faces)) and tri.max() == len(pos) - 1
    # The same triangles, corner for corner.
    assert np.allclose(pos[tri], verts[faces], atol=0.005)
    lo, hi = verts[np.unique(faces)].min(axis=0), verts[np.unique(faces)].max(axis=0)
    assert np.allclose(model["centre"], (lo + hi) / 2) and abs(model["radius"] - np.linalg.norm(hi - lo) / 2) < 1e-6
