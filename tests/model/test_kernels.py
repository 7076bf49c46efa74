"""The texture's compiled view scores by blocks (:func:`omnipipe.model._kernels.score_strip`)
against their cell-by-cell reference (``score_strip_by_cell``)."""

from __future__ import annotations

from unittest import mock

import numpy as np
import pytest
from test_texture_sources import MM_PER_PX, _pipe, _rig

from omnipipe.camera import camera_from_rig
from omnipipe.model import _kernels
from omnipipe.model.texture_sources import _choose_in_strip, elevation_bounds, magnification_table


@pytest.mark.parametrize("bend_mm", [None, 1000.0])
@pytest.mark.parametrize("skip", [False, True])
def test_block_scores_are_bit_identical_to_cell_by_cell(bend_mm: float | None, skip: bool) -> None:
    """The same keyframe, pixel and light for every cell, bit for bit, with and without
    the bound that skips views, laser bands in mm and px included."""
    import omnipipe.model.texture_sources as ts

    grid, poses = _pipe(300.0, 12.0, bend_mm, seed=3)
    rig = _rig("hyperboloid")
    camera = camera_from_rig(rig)
    rig_from_world = np.linalg.inv(poses)
    mag = magnification_table(camera) if skip else None
    args = (rig, camera, rig_from_world, grid, 0, grid.shape[0], elevation_bounds(camera), MM_PER_PX, 3.0, True, 4.0)
    blocks = _choose_in_strip(*args, compiled=True, magnification=mag)
    with mock.patch.object(ts, "score_strip", _kernels.score_strip_by_cell):
        cells = _choose_in_strip(*args, compiled=True, magnification=mag)
    for a, b in zip(blocks, cells, strict=True):
        assert np.array_equal(a.view(np.uint8), b.view(np.uint8))
    assert (blocks[0] >= 0).mean() > 0.9 and len(np.unique(blocks[0])) > 10
