"""The unrolled wall's sample maps compiled (:func:`omnipipe.sfm._kernels.wall_maps`)
against the NumPy reference through ``CameraModel.project`` (``wall_shift._wall_maps``),
and its band-pass against four Gaussian blurs."""

from __future__ import annotations

import cv2
import numpy as np

from omnipipe.camera import OmniCamera
from omnipipe.rig import CameraIntrinsics, Mirror
from omnipipe.sfm._kernels import wall_maps
from omnipipe.sfm.scale_check import WallCylinder
from omnipipe.sfm.wall_shift import (
    ANGULAR_BLUR_SAMPLES,
    BAND_SAMPLES,
    _wall_maps,
    axial_band_pass,
    unrolled_wall,
    wall_grid,
)


class _NotCompiled:
    """``camera`` without a compiled projection (the NumPy path of ``unrolled_wall``)."""

    def __init__(self, camera: OmniCamera) -> None:
        self._camera = camera

    def __getattr__(self, name: str):
        return getattr(self._camera, name)

    def compiled_projection(self) -> None:
        return None


def _camera() -> OmniCamera:
    return OmniCamera(
        CameraIntrinsics(1600, 1200, 799.5, 599.5, 1730.14, radius_min=90.0, radius_max=599.0),
        Mirror(21.57, 32.49),
    )


def test_compiled_maps_are_bit_identical_to_the_projection() -> None:
    camera = _camera()
    proj = camera.compiled_projection()
    rng = np.random.default_rng(5)
    for radius in (60.0, 101.0, 480.0):
        wall = WallCylinder(np.array(rng.normal(0, 3, 2)), radius, -82.0)
        grid = wall_grid(camera, radius)
        assert grid is not None
        shape = (len(grid.z_mm), len(grid.theta))
        col, row, ok = np.empty(shape, np.float32), np.empty(shape, np.float32), np.empty(shape, bool)
        wall_maps(
            proj.kind, proj.params,
            wall.centre_xy[0] + wall.radius_mm * np.cos(grid.theta),
            wall.centre_xy[1] + wall.radius_mm * np.sin(grid.theta),
            grid.z_mm, col, row, ok,
        )
        ref_col, ref_row, ref_ok = _wall_maps(camera, wall, grid)
        assert ok.any() and not ok.all()  # the mirror's view ends inside the grid's rows
        np.testing.assert_array_equal(ok, ref_ok)
        np.testing.assert_array_equal(col, ref_col)
        np.testing.assert_array_equal(row, ref_row)
        assert np.all(col[~ok] == -10.0)


def test_the_unrolled_wall_is_the_same_with_and_without_the_compiled_maps() -> None:
    camera = _camera()
    rng = np.random.default_rng(8)
    gray = rng.uniform(1, 255, (1200, 1600)).astype(np.float32)
    wall = WallCylinder(np.array([1.5, -0.7]), 101.0, -82.0)
    grid = wall_grid(camera, 101.0)
    image, valid = unrolled_wall(camera, gray, wall, grid)
    ref_image, ref_valid = unrolled_wall(_NotCompiled(camera), gray, wall, grid)
    np.testing.assert_array_equal(valid, ref_valid)
    np.testing.assert_array_equal(image, ref_image)
    assert valid.mean() > 0.3


def _band_pass_reference(image: np.ndarray, valid: np.ndarray) -> np.ndarray:
    """``axial_band_pass`` as four ``cv2.GaussianBlur`` calls (the reference)."""
    v = valid.astype(np.float32)
    u = np.where(valid, np.log(np.maximum(image, 1.0)), 0.0).astype(np.float32)

    def blur(x: np.ndarray, s_z: float) -> np.ndarray:
        return cv2.GaussianBlur(x, (0, 0), sigmaX=ANGULAR_BLUR_SAMPLES, sigmaY=s_z)

    fine, wide = BAND_SAMPLES
    w_fine, w_wide = blur(v, fine), blur(v, wide)
    band = blur(u, fine) / np.maximum(w_fine, 1e-6) - blur(u, wide) / np.maximum(w_wide, 1e-6)
    return np.where(valid & (w_wide > 0.9), band, 0.0).astype(np.float32)


def test_the_band_pass_sharing_its_angular_pass_is_bit_identical_to_four_gaussian_blurs() -> None:
    rng = np.random.default_rng(3)
    for shape in ((567, 2010), (120, 181), (301, 644), (40, 2048)):
        image = rng.uniform(0, 300, shape).astype(np.float32)
        valid = rng.random(shape) > 0.01
        valid[: shape[0] // 5] = False  # beyond the mirror's view
        image[~valid & (rng.random(shape) > 0.5)] = 0.0
        got = axial_band_pass(image, valid)
        ref = _band_pass_reference(image, valid)
        assert np.count_nonzero(ref) > 0.2 * ref.size
        np.testing.assert_array_equal(got, ref)
