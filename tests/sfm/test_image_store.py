"""Keyframe images kept on disk: what goes in comes out, and the folder goes at the end."""

from __future__ import annotations

import pickle
from pathlib import Path

import numpy as np
import pytest

from omnipipe.sfm.image_store import ImageStore, load_image


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


def test_a_worker_reads_an_item_by_reference() -> None:
    """A local pool's worker reads an item through its :class:`StoredImage` (a path in
    the pipe, not the pixels) as the same array."""
    from omnipipe.executor import open_executor

    image = np.random.default_rng(3).integers(0, 65535, (120, 160)).astype(np.uint16)
    with ImageStore() as store, open_executor(workers=2) as executor:
        store.append(image)
        ref = store.ref(-1)
        assert len(pickle.dumps(ref)) < 1000 < image.nbytes
        back = executor.submit(load_image, ref).result()
        assert back.dtype == image.dtype and np.array_equal(back, image)
        assert load_image(image) is image  # arrays pass through
        with pytest.raises(IndexError):
            store.ref(1)
