"""The wall points integrated ring by ring into the run's scratch are model.integrate's."""

from __future__ import annotations

import numpy as np

from omnipipe.model import integrate
from omnipipe.pipeline.reconstruct import integrated_on_disk
from omnipipe.spill import is_on_disk


def test_integrated_on_disk_equals_integrate() -> None:
    rng = np.random.default_rng(5)
    poses = np.tile(np.eye(4), (5, 1, 1))
    for t in poses:
        t[:3, :3], t[:3, 3] = np.linalg.qr(rng.normal(size=(3, 3)))[0], rng.normal(0, 50, 3)
    rings = [rng.normal(0, 40, (n, 3)) for n in (5, 0, 7, 3, 0)]
    want = integrate(poses, rings)
    got = integrated_on_disk(poses, rings)
    for a, b in zip(want, got, strict=True):
        assert a.dtype == b.dtype and np.array_equal(a, b)
        assert is_on_disk(b)
    assert got[1].tolist() == [0] * 5 + [2] * 7 + [3] * 3
    empty = integrated_on_disk(poses[:1], [np.zeros((0, 3))])
    assert empty[0].shape == (0, 3) and empty[1].shape == (0,)
