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


def test_handoff_round_trip_budget_and_cleanup() -> None:
    from omnipipe.sfm.image_store import GrayHandoff, hand_on, handoff_path, take_back

    rng = np.random.default_rng(3)
    gray = rng.integers(0, 256, (30, 40)).astype(np.uint8)
    with GrayHandoff(5, budget_bytes=2 * gray.nbytes) as handoff:
        folder = Path(handoff.folder)
        written = hand_on(handoff.folder, 1, gray)
        assert written >= gray.nbytes
        handoff.note(1, written)
        back = take_back(handoff.folder, 1)
        assert back is not None and back.dtype == np.uint8 and np.array_equal(back, gray)
        assert take_back(handoff.folder, 1) is None  # taken once: the file is gone
        assert take_back(handoff.folder, 2) is None  # never handed on
        handoff.note(2, hand_on(handoff.folder, 2, gray))  # the budget is reached now
        assert hand_on(handoff.folder, 3, gray) == 0
        assert not Path(handoff_path(handoff.folder, 3)).exists()
        handoff.discard(2)
        assert not Path(handoff_path(handoff.folder, 2)).exists()
    assert not folder.exists()
