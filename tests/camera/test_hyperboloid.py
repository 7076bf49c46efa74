"""The hyperboloid camera model (paper Eq. 1-3): round trips, geometry, single viewpoint."""

from __future__ import annotations

import numpy as np
import pytest

from omnipipe.camera import OmniCamera
from omnipipe.errors import ShapeError
from omnipipe.rig import CameraIntrinsics, Mirror


@pytest.fixture(params=["paper", "off-centre"])
def camera(request: pytest.FixtureRequest) -> OmniCamera:
    if request.param == "paper":
        intr = CameraIntrinsics(
            1600, 1200, 799.5, 599.5, 1730.14, radius_min=90.0, radius_max=599.0
        )
        return OmniCamera(intr, Mirror(21.57, 32.49))
    # Another mirror, focal length and an off-centre principal point.
    intr = CameraIntrinsics(1280, 1024, 655.3, 498.1, 900.0, radius_min=60.0, radius_max=480.0)
    return OmniCamera(intr, Mirror(20.0, 30.0))


def _valid_pixels(camera: OmniCamera, n: int, seed: int) -> np.ndarray:
    rng = np.random.default_rng(seed)
    px = rng.uniform([-0.5, -0.5], [camera.width - 0.5, camera.height - 0.5], size=(n, 2))
    return px[camera.is_valid_pixel(px)]


def test_round_trip_over_whole_valid_image(camera: OmniCamera) -> None:
    pixels = _valid_pixels(camera, 200_000, seed=1)
    rays = camera.unproject(pixels)
    assert np.allclose(np.linalg.norm(rays, axis=1), 1.0)
    depth = np.random.default_rng(2).uniform(5.0, 5000.0, size=(len(rays), 1))
    back, valid = camera.project(rays * depth)
    assert valid.all()
    assert np.abs(back - pixels).max() < 1e-6


def test_project_then_unproject_recovers_directions(camera: OmniCamera) -> None:
    rng = np.random.default_rng(3)
    dirs = rng.normal(size=(50_000, 3))
    dirs /= np.linalg.norm(dirs, axis=1, keepdims=True)
    px, valid = camera.project(dirs * 250.0)
    assert valid.sum() > 1000
    rays = camera.unproject(px[valid])
    assert np.abs(rays - dirs[valid]).max() < 1e-9


def test_image_centre_looks_along_minus_z(camera: OmniCamera) -> None:
    ray = camera.unproject(np.array([[camera.cx, camera.cy]]))[0]
    assert ray == pytest.approx([0.0, 0.0, -1.0], abs=1e-12)
    # x along columns and y along rows, as the contract's rig frame says.
    right = camera.unproject(np.array([[camera.cx + 200.0, camera.cy]]))[0]
    down = camera.unproject(np.array([[camera.cx, camera.cy + 200.0]]))[0]
    assert right[0] > 0 and abs(right[1]) < 1e-12
    assert down[1] > 0 and abs(down[0]) < 1e-12


def test_single_viewpoint_rays_pass_through_focus(camera: OmniCamera) -> None:
    """Each pixel's lens ray hits the mirror at a point on the pixel's ray from the focus
    (Eq. 1), and the reflection law holds there: the mirror normal bisects both rays."""
    pixels = _valid_pixels(camera, 2000, seed=4)
    a, b, c, f = camera.a, camera.b, camera.c, camera.f
    u = pixels[:, 0] - camera.cx
    v = pixels[:, 1] - camera.cy
    lens_dir = np.stack([u, v, np.full_like(u, f)], axis=1)
    lens_dir /= np.linalg.norm(lens_dir, axis=1, keepdims=True)
    lens = np.array([0.0, 0.0, -2.0 * c])
    # Intersect the lens ray with the mirror sheet (X^2+Y^2)/a^2 - (Z+c)^2/b^2 = -1 numerically.
    ts = np.linspace(1.0, 400.0, 400001)
    mirror_pts = []
    for d in lens_dir[:50]:
        p = lens + ts[:, None] * d
        g = (p[:, 0] ** 2 + p[:, 1] ** 2) / a**2 - (p[:, 2] + c) ** 2 / b**2 + 1.0
        k = np.flatnonzero((np.sign(g[:-1]) != np.sign(g[1:])) & (p[:-1, 2] + c > 0))[0]
        t0 = ts[k] - g[k] * (ts[k + 1] - ts[k]) / (g[k + 1] - g[k])
        mirror_pts.append(lens + t0 * d)
    mirror_pts = np.array(mirror_pts)
    rays = camera.unproject(pixels[:50])
    cross = np.cross(mirror_pts / np.linalg.norm(mirror_pts, axis=1, keepdims=True), rays)
    assert np.abs(cross).max() < 1e-6
    # Reflection law: incoming scene direction -ray reflects into the lens direction.
    grad = np.stack(
        [
            2 * mirror_pts[:, 0] / a**2,
            2 * mirror_pts[:, 1] / a**2,
            -2 * (mirror_pts[:, 2] + c) / b**2,
        ],
        axis=1,
    )
    n = grad / np.linalg.norm(grad, axis=1, keepdims=True)
    incoming = -rays
    reflected = incoming - 2 * np.sum(incoming * n, axis=1, keepdims=True) * n
    to_lens = lens - mirror_pts
    to_lens /= np.linalg.norm(to_lens, axis=1, keepdims=True)
    assert np.abs(reflected - to_lens).max() < 1e-6


def test_valid_region(camera: OmniCamera) -> None:
    mask = camera.valid_mask()
    assert mask.shape == (camera.height, camera.width)
    assert not mask[int(round(camera.cy)), int(round(camera.cx))]  # blind centre
    assert not mask[0, 0]  # outside the rim
    px, valid = camera.project(np.array([[0.0, 0.0, -1.0], [0.0, 0.0, 1.0], [1.0, 0.0, -0.5]]))
    assert not valid[0]  # the camera's own reflection
    assert np.isnan(px[1]).all() and not valid[1]  # straight ahead: no mirror there
    assert valid[2]


def test_shape_errors(camera: OmniCamera) -> None:
    with pytest.raises(ShapeError, match=r"\(N, 2\)"):
        camera.unproject(np.zeros((4, 3)))
    with pytest.raises(ShapeError, match=r"\(N, 3\)"):
        camera.project(np.zeros((4, 2)))


def _project_numpy(camera: OmniCamera, pts: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The NumPy expressions ``project`` had before it was compiled (the reference)."""
    a, b, c, f = camera.a, camera.b, camera.c, camera.f
    norm = np.linalg.norm(pts, axis=1)
    with np.errstate(invalid="ignore", divide="ignore"):
        d = pts / norm[:, None]
        t = a * a / (b - c * d[:, 2])
        mz = t * d[:, 2] + 2.0 * c
        u = f * t * d[:, 0] / mz
        v = f * t * d[:, 1] / mz
    seen = (norm > 0) & (d[:, 2] < b / c) & (mz > 0)
    pixels = np.stack([u + camera.cx, v + camera.cy], axis=1)
    pixels[~seen] = np.nan
    valid = seen & camera.is_valid_pixel(np.where(seen[:, None], pixels, 0.0))
    return pixels, valid


def test_compiled_project_is_bit_identical_to_numpy(camera: OmniCamera) -> None:
    rng = np.random.default_rng(7)
    pts = rng.normal(size=(200_000, 3)) * rng.lognormal(size=(200_000, 1)) * 50.0
    pts[::3, 2] = -np.abs(pts[::3, 2]) * 0.3 - 20.0  # most of these in view
    pts[::500] = 0.0
    pts[1::500, 0] = np.nan
    pts[2::500, 1] = np.inf
    pts[3::500, 2] = -np.inf
    # Rays whose pixels lie within a few ulp of the valid annulus' radii.
    phi = rng.uniform(0.0, 2.0 * np.pi, 2000)
    edge = []
    for radius in (camera.radius_min, camera.radius_max):
        for k in range(-8, 9):
            r = radius * (1.0 + k * 2.2e-16)
            px = np.stack([camera.cx + r * np.cos(phi), camera.cy + r * np.sin(phi)], axis=1)
            edge.append(camera.unproject(px))
    edge_rays = np.concatenate(edge)
    for p in (pts, edge_rays, np.asfortranarray(pts[:1000]), pts[:0]):
        got, got_valid = camera.project(p)
        want, want_valid = _project_numpy(camera, np.asarray(p, float))
        assert np.array_equal(got, want, equal_nan=True)
        assert np.array_equal(got_valid, want_valid)
    _, edge_valid = camera.project(edge_rays)
    assert 0 < edge_valid.mean() < 1  # the annulus' edges were really probed


def test_project_jacobian_matches_finite_differences(camera: OmniCamera) -> None:
    pixels = _valid_pixels(camera, 2000, seed=7)
    depth = np.random.default_rng(8).uniform(20.0, 2000.0, size=(len(pixels), 1))
    q = camera.unproject(pixels) * depth
    J = camera.project_jacobian(q)
    assert J.shape == (len(q), 2, 3)
    h = 1e-6 * np.linalg.norm(q, axis=1)
    fd = np.empty_like(J)
    for i in range(3):
        e = np.zeros(3)
        e[i] = 1.0
        plus, _ = camera.project(q + h[:, None] * e)
        minus, _ = camera.project(q - h[:, None] * e)
        fd[:, :, i] = (plus - minus) / (2 * h[:, None])
    scale = np.abs(fd).max(axis=(1, 2))[:, None, None]
    assert (np.abs(J - fd) / scale).max() < 1e-5
    # Only the direction matters: no derivative along the point's own ray.
    assert np.abs(np.einsum("nij,nj->ni", J, q)).max() < 1e-6 * np.abs(J).max()


def test_block_projection_is_bit_identical_to_point_by_point(camera: OmniCamera) -> None:
    """``project_block`` (the branch-free loop the compiler vectorises) gives every
    point's pixel and validity bit for bit as ``project_point``, shifted points, points
    off the mirror and points within a few ulp of the annulus' radii included."""
    from omnipipe.camera._kernels import project_block, project_point

    proj = camera.compiled_projection()
    rng = np.random.default_rng(11)
    pts = rng.normal(size=(3000, 3)) * rng.lognormal(size=(3000, 1)) * 50.0
    pts[::3, 2] = -np.abs(pts[::3, 2]) * 0.3 - 20.0
    pts[::97] = 0.0
    pts[1::97, 0] = np.nan
    phi = rng.uniform(0.0, 2.0 * np.pi, 40)
    edge = []
    for radius in (camera.radius_min, camera.radius_max):
        for k in range(-8, 9):
            r = radius * (1.0 + k * 2.2e-16)
            px = np.stack([camera.cx + r * np.cos(phi), camera.cy + r * np.sin(phi)], axis=1)
            edge.append(camera.unproject(px) * 40.0)
    edge_pts = np.concatenate(edge)
    edge_valid = None
    for p, shift in ((pts, (0.0, 0.0, 0.0)), (pts, (3.5, -1.25, 7.0)), (edge_pts, (0.0, 0.0, 0.0))):
        n = len(p)
        col, row, valid = np.empty(n), np.empty(n), np.empty(n, bool)
        x, y, z = (np.ascontiguousarray(p[:, i]) for i in range(3))
        for lo in range(0, n, 169):  # blocks of a template's size, the last one shorter
            m = min(169, n - lo)
            c, r, v = np.empty(m), np.empty(m), np.empty(m, bool)
            project_block(proj.kind, proj.params, x[lo : lo + m].copy(), y[lo : lo + m].copy(), z[lo : lo + m].copy(), shift, m, c, r, v)
            col[lo : lo + m], row[lo : lo + m], valid[lo : lo + m] = c, r, v
        want = [project_point(proj.kind, proj.params, *(q + np.array(shift))) for q in p]
        assert np.array_equal(col, [w[0] for w in want], equal_nan=True)
        assert np.array_equal(row, [w[1] for w in want], equal_nan=True)
        assert np.array_equal(valid, [w[2] for w in want])
        edge_valid = valid
    assert 0 < edge_valid.mean() < 1  # the annulus' edges were really probed
