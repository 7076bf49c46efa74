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


def test_an_item_left_in_its_own_file_is_read_as_that_files_first_array(tmp_path: Path) -> None:
    """:meth:`ImageStore.append_file`: an item read from a file the store did not write
    (a hand-off frame: the grey plane first, another array after it) is that file's first
    array, by index and by reference, and the file stays when the store is closed."""
    rng = np.random.default_rng(4)
    grey = rng.integers(0, 256, (30, 40)).astype(np.uint8)
    other = rng.integers(0, 256, (15, 20, 2)).astype(np.uint8)
    path = tmp_path / "000007.npy"
    with open(path, "wb") as fh:
        np.save(fh, grey, allow_pickle=False)
        np.save(fh, other, allow_pickle=False)
    own = rng.integers(0, 65535, (30, 40)).astype(np.uint16)
    with ImageStore() as store:
        store.append(own)
        store.append_file(str(path))
        store.append(own + 1)
        assert len(store) == 3
        for got in (store[1], store[-2], load_image(store.ref(1))):
            assert got.dtype == np.uint8 and np.array_equal(got, grey)
        assert np.array_equal(store[0], own) and np.array_equal(store[2], own + 1)
    assert path.exists()


def test_a_handed_planar_frame_is_referred_to_not_copied(tmp_path: Path) -> None:
    """A red laser's 8-bit frame handed on planar has its grey image (the green plane)
    as its file's first array: the keyframe store refers to that file; a frame handed on
    whole (a green laser's colour frame) is not referred to."""
    from omnipipe.handoff import hand_on
    from omnipipe.sfm.tasks import handed_gray, handed_gray_file

    frame = np.random.default_rng(5).integers(0, 256, (24, 32, 3)).astype(np.uint8)
    folder = str(tmp_path)
    hand_on(folder, 3, frame, "red")
    path = handed_gray_file(folder, 3)
    assert path is not None
    with ImageStore() as store:
        store.append_file(path)
        assert np.array_equal(store[0], handed_gray(folder, 3, "red"))
        assert np.array_equal(store[0], frame[:, :, 1])
    hand_on(folder, 4, frame, "green")
    assert handed_gray_file(folder, 4) is None
    assert handed_gray_file(folder, 5) is None  # not handed on
