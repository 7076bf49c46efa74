"""Shared inputs of the bundle-adjustment tests."""

from __future__ import annotations

from collections.abc import Callable

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from omnipipe.camera import OmniCamera
from omnipipe.geometry import apply, invert, make_transform
from omnipipe.sfm.bundle import BundleProblem
from omnipipe.sim.scenario import paper_rig


def _pipe_scene(
    rng: np.random.Generator, keyframes: int, rot_sigma: float, xy_sigma: float, n: int, z_mm: tuple[float, float]
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(K, 4, 4) world_from_rig of ``keyframes`` keyframes 12 mm apart along the z axis
    (rotation vectors and x, y drawn with sigmas ``rot_sigma`` rad and ``xy_sigma`` mm),
    and (n,) angles (rad) and (n, 3) points of a 202 mm pipe's wall around it, z uniform
    in ``z_mm``: the scene of the bundle-adjustment tests."""
    poses = np.array([
        make_transform(Rotation.from_rotvec(rng.normal(0, rot_sigma, 3)).as_matrix(),
                       np.array([rng.normal(0, xy_sigma), rng.normal(0, xy_sigma), 12.0 * k]))
        for k in range(keyframes)
    ])
    th = rng.uniform(-np.pi, np.pi, n)
    pts = np.column_stack([101 * np.cos(th), 101 * np.sin(th), rng.uniform(*z_mm, n)])
    return poses, th, pts


@pytest.fixture
def pipe_scene():
    """``pipe_scene(rng, keyframes, rot_sigma, xy_sigma, n, z_mm) -> (poses, angles, points)``."""
    return _pipe_scene


def _problem(seed: int, fixed: int) -> tuple[OmniCamera, BundleProblem]:
    """A small noisy bundle problem (5 keyframes along a 202 mm pipe, 200 wall points, 80
    laser anchors, 3 of them within one keyframe), seeded; ``fixed`` keyframes held."""
    rng = np.random.default_rng(seed)
    camera = OmniCamera.from_rig(paper_rig(800, 600))
    K, n = 5, 200
    poses, th, pts = _pipe_scene(rng, K, 0.3, 2.0, n, (-200.0, 150.0))
    f, p = np.meshgrid(np.arange(K), np.arange(n), indexing="ij")
    f, p = f.ravel(), p.ravel()
    px, _ = camera.project(np.einsum("nij,nj->ni", np.array([invert(T) for T in poses])[f][:, :3, :3], pts[p])
                           + np.array([invert(T) for T in poses])[f][:, :3, 3])
    px = np.nan_to_num(px) + rng.normal(0, 0.5, px.shape)
    L = 80
    aa = rng.integers(0, K, L)
    ab = (aa + rng.integers(1, K, L)) % K
    ab[:3] = aa[:3]  # anchors within one keyframe: constant residuals
    aq = np.column_stack([101 * np.cos(th[:L]), 101 * np.sin(th[:L]), np.full(L, -82.0)])
    apx = np.array([camera.project(apply(invert(poses[b]) @ poses[a], q[None]))[0][0]
                    for a, b, q in zip(aa, ab, aq, strict=True)])
    apx = np.nan_to_num(apx) + rng.normal(0, 0.5, apx.shape)
    problem = BundleProblem(poses, pts + rng.normal(0, 1.0, pts.shape), f, p, px, aa, ab, aq, apx, fixed=fixed)
    return camera, problem



@pytest.fixture
def bundle_problem():
    """``bundle_problem(seed, fixed) -> (camera, BundleProblem)``."""
    return _problem


def _central_differences(fun: Callable[[np.ndarray], np.ndarray], x: np.ndarray, h: np.ndarray) -> np.ndarray:
    J = np.empty((len(fun(x)), len(x)))
    for i in range(len(x)):
        e = np.zeros(len(x))
        e[i] = h[i]
        J[:, i] = (fun(x + e) - fun(x - e)) / (2 * h[i])
    return J


@pytest.fixture
def central_differences() -> Callable[..., np.ndarray]:
    """``(fun, x, h) -> (m, n)``: the Jacobian of ``fun`` at ``x`` (n,) by central
    differences with steps ``h`` (n,): the reference of the analytic Jacobians."""
    return _central_differences
