"""Keyframe images kept on disk: what goes in comes out, and the folder goes at the end."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from omnipipe.sfm.image_store import ImageStore


def test_round_trip_and_cleanup() -> None:
    rng = np.random.default_rng(2)
    images = [rng.integers(0, 65535, (30, 40)).astype(np.uint16), rng.random((30, 40), np.float32)]
    with ImageStore() as store:
        for image in images:
            store.append(image)
        folder = Path(store._dir.name)
        assert len(store) == 2 and folder.is_dir()
        for k, image in enumerate(images):
            back = store[k]
            assert back.dtype == image.dtype and np.array_equal(back, image)
        assert np.array_equal(store[-1], images[-1])
        with pytest.raises(IndexError):
            store[2]
    assert not folder.exists()
