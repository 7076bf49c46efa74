"""model.integrate: ring points moved into the world ring by ring, in memory or in the
run's scratch, equal to the concatenation of each ring moved."""

from __future__ import annotations

import numpy as np
import pytest

from omnipipe.geometry import apply
from omnipipe.model import integrate
from omnipipe.spill import is_on_disk


@pytest.mark.parametrize("in_scratch", [False, True])
def test_integrate_equals_each_ring_moved_and_concatenated(in_scratch: bool) -> None:
    rng = np.random.default_rng(5)
    poses = np.tile(np.eye(4), (5, 1, 1))
    for t in poses:
        t[:3, :3], t[:3, 3] = np.linalg.qr(rng.normal(size=(3, 3)))[0], rng.normal(0, 50, 3)
    rings = [rng.normal(0, 40, (n, 3)) for n in (5, 0, 7, 3, 0)]
    want_points = np.concatenate([apply(t, r) for t, r in zip(poses, rings, strict=True) if len(r)])
    points, frame = integrate(poses, rings, in_scratch=in_scratch)
    assert points.dtype == np.float64 and np.array_equal(points, want_points)
    assert frame.tolist() == [0] * 5 + [2] * 7 + [3] * 3
    assert is_on_disk(points) == in_scratch and is_on_disk(frame) == in_scratch
    empty = integrate(poses[:1], [np.zeros((0, 3))], in_scratch=in_scratch)
    assert empty[0].shape == (0, 3) and empty[1].shape == (0,)
