"""Perspective projection conversion (Sec. V-A, Fig. 11)."""

from __future__ import annotations

import numpy as np

from omnipipe.camera import OmniCamera, PerspectiveView
from omnipipe.sim import make_scenario
from omnipipe.sim.writer import build_renderer


def test_view_pixels_map_to_their_rays(small_camera: OmniCamera) -> None:
    view = PerspectiveView.looking_at(
        np.array([1.0, 0.3, -0.6]), width=64, height=48, focal_px=60.0
    )
    grid = view.grid()
    rays = view.rays(grid)
    back, front = view.pixels_of_rays(rays)
    assert front.all() and np.abs(back - grid).max() < 1e-9
    # The centre pixel looks along the requested direction.
    centre = view.rays(np.array([[(64 - 1) / 2, (48 - 1) / 2]]))[0]
    d = np.array([1.0, 0.3, -0.6]) / np.linalg.norm([1.0, 0.3, -0.6])
    assert np.allclose(centre, d)
    map_x, map_y, valid = view.omni_maps(small_camera)
    omni_rays = small_camera.unproject(np.stack([map_x[valid], map_y[valid]], axis=1).astype(float))
    assert np.abs(omni_rays - rays[valid.ravel()]).max() < 1e-5  # float32 maps


def _ncc(a: np.ndarray, b: np.ndarray) -> float:
    a = a - a.mean()
    b = b - b.mean()
    return float((a * b).sum() / np.sqrt((a * a).sum() * (b * b).sum()))


def test_perspective_view_matches_pinhole_rendering() -> None:
    """A view converted from a rendered omni image equals a pinhole rendering of the scene."""
    scenario = make_scenario("paper", frames=1, size=(800, 600))
    renderer, poses, _, _ = build_renderer(scenario)
    omni, _ = renderer.render(poses[0], seed=0, laser=False, noise=False)
    cam = renderer.camera
    # A view of the wall ahead and to the side, coarser than the omni image there.
    view = PerspectiveView.looking_at(
        np.array([1.0, 0.2, 0.15]), width=120, height=90, focal_px=110.0
    )
    converted, valid = view.render(omni.astype(np.float32), cam)
    rays = view.rays(view.grid())
    hits = renderer.hit(poses[0], rays)
    flat = np.arange(len(rays))
    footprint = renderer.footprint(hits.points_in_rig, flat, (view.height, view.width))
    pinhole = renderer.shade(poses[0], hits, footprint).reshape(view.height, view.width, 3) * 255.0
    pinhole *= renderer.vignette.mean()  # rough vignetting level; NCC ignores gain
    assert valid.mean() > 0.95
    inner = np.s_[5:-5, 5:-5]
    g1 = converted[..., 1][inner]
    g2 = pinhole[..., 1][inner]
    ncc = _ncc(g1, g2)
    shifted = _ncc(converted[..., 1][7:-3, 5:-5], g2)
    assert ncc > 0.97, ncc
    assert shifted < ncc - 0.05  # the match is specific: a 2-px shift is visibly worse
