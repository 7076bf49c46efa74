"""The mesh shows a lateral's opening as a hole and a joint's gap as a gap."""

from __future__ import annotations

import numpy as np

from omnipipe.model import mesh_unrolled


def test_not_wall_points_leave_a_hole_and_a_gap() -> None:
    r, circ = 100.0, 2 * np.pi * 100.0
    arc, axial = np.meshgrid(np.arange(0.0, circ, 4.0), np.arange(0.0, 200.0, 4.0))
    arc, axial = arc.ravel(), axial.ravel()
    pts = np.stack([r * np.cos(arc / r), r * np.sin(arc / r), axial], axis=1)
    hole = (arc - 300.0) ** 2 + (axial - 60.0) ** 2 < 25.0**2  # an opening
    gap = np.abs(axial - 150.0) < 3.0  # a joint's gap: one ring all round
    faces = mesh_unrolled(arc, axial, pts, circ, 2.0, hole=hole | gap)
    plain = mesh_unrolled(arc, axial, pts, circ, 2.0)
    assert not (hole | gap)[faces].any()
    # Nothing crosses the gap: no triangle has corners on both sides of it.
    z = axial[faces]
    assert not ((z.min(axis=1) < 147.0) & (z.max(axis=1) > 153.0)).any()
    # The rest of the wall is meshed as without the features.
    keep = ~(hole | gap)[plain].any(axis=1)
    assert len(faces) == keep.sum() and len(faces) > 0.8 * len(plain)
