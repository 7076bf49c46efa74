"""The unrolled wall shows a lateral's opening as a hole and a joint's gap as a gap, as the
mesh does (issue 30): cells whose wall is missing are not textured, not smeared over."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
from threadpoolctl import threadpool_limits

from omnipipe.model import ModelConfig, ModelInputs, mesh_unrolled, run
from omnipipe.model.mesh import longest_edges
from omnipipe.model.texture_grid import WallGrid, wall_points_on_grid

R = 100.0
CIRC = 2 * np.pi * R
OPENING = (300.0, 60.0, 25.0)  # arc, axial, radius (mm) of a lateral's opening
GAP_AXIAL, GAP_HALF = 150.0, 3.0  # a joint's gap, all round


@pytest.fixture(autouse=True)
def _one_blas_thread():
    """The interpolation's barycentric transforms with one BLAS thread, as the model stage
    makes them (spinning threads on busy cores stall them for seconds)."""
    with threadpool_limits(limits=1, user_api="blas"):
        yield


def _wall_with_features() -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Jittered points of a R 100 mm wall every ~4 mm; inside the opening the points lie on
    the branch seen through it (20 mm further out), and the gap's points 8 mm deep.
    Returns arc, axial, (N, 3) points (mm) and the (N,) not-wall flag."""
    rng = np.random.default_rng(5)
    arc, axial = np.meshgrid(np.arange(0.0, CIRC - 2.0, 4.0), np.arange(0.0, 200.0, 4.0))
    arc = (arc.ravel() + rng.uniform(-1.0, 1.0, arc.size)) % CIRC
    axial = axial.ravel() + rng.uniform(-1.0, 1.0, axial.size)
    a0, z0, rad = OPENING
    opening = (arc - a0) ** 2 + (axial - z0) ** 2 < rad**2
    gap = np.abs(axial - GAP_AXIAL) < GAP_HALF
    r = np.where(opening, R + 20.0, np.where(gap, R + 8.0, R))
    pts = np.stack([r * np.cos(arc / R), r * np.sin(arc / R), axial], axis=1)
    return arc, axial, pts, opening | gap


def test_cells_of_an_opening_and_a_gap_are_not_wall_and_the_rest_unchanged() -> None:
    arc, axial, pts, hole = _wall_with_features()
    mm = 1.0
    holed, z0 = wall_points_on_grid(arc, axial, pts, CIRC, mm, 6.0, hole=hole)
    plain, z0_plain = wall_points_on_grid(arc, axial, pts, CIRC, mm, 6.0)
    assert z0 == z0_plain and holed.shape == plain.shape
    h, w = holed.shape[:2]
    cu = (np.arange(w) + 0.5) * (CIRC / w)
    cz = z0 + np.arange(h) * mm
    gu, gz = np.meshgrid(cu, cz)
    missing = np.isnan(holed[..., 0])
    # Without the flag the branch's and the gap's points texture the opening (smeared).
    a0, zc, rad = OPENING
    inside = (gu - a0) ** 2 + (gz - zc) ** 2 < (rad - 6.0) ** 2
    in_gap = np.abs(gz - GAP_AXIAL) < GAP_HALF - 1.5
    assert not np.isnan(plain[..., 0][inside | in_gap]).any()
    # With it: the opening is a hole, the gap a gap all round.
    assert missing[inside].all() and missing[in_gap].all()
    # Cells well away from both are wall, and the same bits as without the flag.
    away = ((gu - a0) ** 2 + (gz - zc) ** 2 > (rad + 10.0) ** 2) & (np.abs(gz - GAP_AXIAL) > GAP_HALF + 10.0)
    away &= (gz > 2.0) & (gz < 196.0)
    assert not missing[away].any()
    kept = ~missing
    assert np.array_equal(holed[kept], plain[kept])
    # The hole is no wider than the mesh's: the missing cells near the opening lie within
    # one point spacing (~4 mm, jittered) of it.
    near = (gu - a0) ** 2 + (gz - zc) ** 2 < (rad + 20.0) ** 2
    dist = np.hypot(gu - a0, gz - zc)[missing & near]
    assert dist.max() < rad + 8.0
    # The mesh drops the same region: no kept triangle has a not-wall corner.
    faces = mesh_unrolled(arc, axial, pts, CIRC, 2.5, hole=hole)
    assert not hole[faces].any()


def test_wall_the_mesh_bridges_with_long_triangles_is_no_wall() -> None:
    """A sector with no points (the wall under standing water): the mesh drops the long
    triangles across it; with the mesh's longest kept edge the grid leaves every cell
    there NaN, where the distance rule alone painted a band ``max_gap_mm`` wide along
    each side of it."""
    arc, axial, _, _ = _wall_with_features()
    dry = (arc < 500.0) | (arc > 560.0)  # 60 mm of wall unmeasured all along
    arc, axial = arc[dry], axial[dry]
    pts = np.stack([R * np.cos(arc / R), R * np.sin(arc / R), axial], axis=1)  # plain wall
    faces = mesh_unrolled(arc, axial, pts, CIRC, 2.5)
    longest = float(longest_edges(pts, faces).max())
    assert longest < 15.0  # the gap's triangles are not in the mesh
    plain, _ = wall_points_on_grid(arc, axial, pts, CIRC, 1.0, 6.0)
    masked, _ = wall_points_on_grid(arc, axial, pts, CIRC, 1.0, 6.0, max_edge_mm=longest)
    w = plain.shape[1]
    cu = (np.arange(w) + 0.5) * (CIRC / w)
    rows = slice(5, plain.shape[0] - 5)
    inside = (cu > 503.0) & (cu < 557.0)
    assert np.isfinite(plain[rows][:, inside, 0]).any()  # painted into the gap before
    assert np.isnan(masked[rows][:, inside, 0]).all()
    kept = np.isfinite(masked[..., 0])
    assert np.array_equal(masked[kept], plain[kept])
    away = (cu < 480.0) | (cu > 580.0)
    assert np.isfinite(masked[rows][:, away, 0]).all()


def test_a_chunked_grid_holes_the_same_cells() -> None:
    arc, axial, pts, hole = _wall_with_features()
    whole = WallGrid(arc, axial, pts, CIRC, 1.0, 6.0, hole=hole, max_edge_mm=12.0)
    chunked = WallGrid(arc, axial, pts, CIRC, 1.0, 6.0, chunk_points=1500, hole=hole, max_edge_mm=12.0)
    h = whole.shape[0]
    a = np.concatenate([whole.rows(r, min(r + 64, h)) for r in range(0, h, 64)])
    b = np.concatenate([chunked.rows(r, min(r + 64, h)) for r in range(0, h, 64)])
    assert np.array_equal(np.isnan(a), np.isnan(b))
    assert np.allclose(a[~np.isnan(a)], b[~np.isnan(b)], atol=1e-9)


def test_the_model_stage_leaves_not_wall_cells_untextured(rendered_stations) -> None:
    """End to end on rendered rings: points flagged not wall (a patch of the wall standing
    for an opening) leave the unrolled image's cells there unseen and black (transparent in
    unrolled.png), the mesh holed the same, the rest of the wall textured as before."""
    st = rendered_stations
    keep = st.keep
    inputs = ModelInputs(
        st.scenario.rig,
        st.poses[keep],
        [r.points_in_rig for r in st.rings.rings],
        [r.pixels for r in st.rings.rings],
        lambda k: st.frames[int(keep[k])],
    )
    from omnipipe.model.stage import integrate, unrolled_coordinates

    points, frame = integrate(inputs.world_from_rig, inputs.ring_points_in_rig)
    arc, axial, circ = unrolled_coordinates(points, inputs.world_from_rig)
    given = dataclasses.replace(inputs, ring_points_in_rig=[], points_in_world=points, point_frame=frame)
    zc = float(np.median(axial))
    ac = 0.25 * circ
    patch = np.hypot(arc - ac, axial - zc) < 20.0
    assert patch.sum() > 20
    plain = run(ModelConfig(), given)
    holed = run(ModelConfig(), dataclasses.replace(given, not_wall=patch))
    assert plain.unrolled is not None and holed.unrolled is not None
    u = holed.unrolled
    h, w = u.alpha.shape
    gu, gz = np.meshgrid((np.arange(w) + 0.5) * (circ / w), u.axial_min_mm + np.arange(h) * u.mm_per_px)
    centre = np.hypot(gu - ac, gz - zc) < 10.0
    assert plain.unrolled.alpha[centre].mean() > 0.9  # textured without the flag
    assert not u.alpha[centre].any()  # a hole with it
    assert (u.image[~u.alpha] == 0).all()  # not painted
    assert not patch[holed.mesh_faces].any()
    far = np.hypot(gu - ac, gz - zc) > 40.0
    assert np.array_equal(u.alpha[far], plain.unrolled.alpha[far])
