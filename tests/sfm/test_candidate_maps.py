"""Eq. (17)'s candidate pixels as blocks (:func:`omnipipe.sfm._kernels.candidate_maps`)
against the point-by-point reference (``laser_scale._candidate_maps``)."""

from __future__ import annotations

import numpy as np

from omnipipe.camera import OmniCamera
from omnipipe.rig import CameraIntrinsics, Mirror
from omnipipe.sfm._kernels import candidate_maps
from omnipipe.sfm.laser_scale import _OUTSIDE, _candidate_maps


def test_block_candidates_are_bit_identical_to_point_by_point() -> None:
    camera = OmniCamera(
        CameraIntrinsics(1600, 1200, 799.5, 599.5, 1730.14, radius_min=90.0, radius_max=599.0),
        Mirror(21.57, 32.49),
    )
    proj = camera.compiled_projection()
    rng = np.random.default_rng(17)
    n_pts, n_s, k_len = 9, 13, 169
    # Template samples on a wall about 80 mm away, some far off (leaving the mirror), and
    # some whose pixels lie within ulps of the annulus' radii (the block's slow path).
    phi = rng.uniform(0, 2 * np.pi, (n_pts, 1))
    plane = np.stack(
        [80 * np.cos(phi) + rng.normal(0, 2, (n_pts, k_len)),
         80 * np.sin(phi) + rng.normal(0, 2, (n_pts, k_len)),
         rng.uniform(-60, 40, (n_pts, k_len))], axis=2,
    )
    plane[0] *= 40.0
    edge = np.stack([camera.cx + camera.radius_max * np.cos(phi[:, 0]),
                     camera.cy + camera.radius_max * np.sin(phi[:, 0])], axis=1)
    plane[1, :5] = camera.unproject(edge[:5]) * 70.0
    scales = np.sort(rng.uniform(0.2, 60.0, (n_pts, n_s)), axis=1)
    scales[1, 0] = 0.0  # the edge points unmoved
    direction = np.array([0.1, -0.2, 0.97]) / np.linalg.norm([0.1, -0.2, 0.97])
    step = rng.uniform(0.1, 1.0, n_pts)
    half = rng.uniform(1.0, 4.0, n_pts)
    weight = (rng.random((n_pts, k_len)) > 0.2).astype(float)
    normal = np.array([0.0, 0.05, 1.0]) / np.linalg.norm([0.0, 0.05, 1.0])
    total = n_pts * n_s * k_len
    for with_sheet in (True, False):
        out = []
        for fn, extra in ((_candidate_maps, ()), (candidate_maps, (_OUTSIDE,))):
            map_x = np.full(total + 7, -1.0, np.float32)
            map_y = np.full(total + 7, -1.0, np.float32)
            w = np.empty((n_pts, n_s, k_len)) if with_sheet else np.empty((0, 0, 0))
            fn(plane, scales, direction, proj.kind, proj.params, with_sheet, normal, -3.0,
               step, half, weight, *extra, map_x, map_y, w)
            out.append((map_x, map_y, w))
        for got, want in zip(out[1], out[0], strict=True):
            assert np.array_equal(got.view(np.uint8), want.view(np.uint8))
        seen = out[0][0][:total] != _OUTSIDE
        assert 0.2 < seen.mean() < 1.0  # candidates both in and out of view
