"""The run's scratch folder beside OUT: used by the stores, removed at the end, and a
killed run's left-over removed by the next run (only omnipipe's, only a dead run's)."""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import numpy as np

from omnipipe.laser.ring import LaserRing
from omnipipe.laser.store import RingStore
from omnipipe.scratch import MARKER, scratch_beside
from omnipipe.sfm.image_store import ImageStore


def _ring(n: int) -> LaserRing:
    rng = np.random.default_rng(0)
    return LaserRing(rng.normal(size=(n, 2)), rng.normal(size=n), rng.normal(size=n), rng.normal(size=n))


def test_stores_write_beside_out_and_nothing_is_left(tmp_path: Path) -> None:
    out = tmp_path / "o"
    with scratch_beside(out) as folder:
        assert folder is not None and folder.parent == tmp_path
        assert folder.name.startswith(".o.scratch-")
        rings, images = RingStore(2), ImageStore()
        rings.put(0, _ring(5))
        images.append(np.zeros((3, 4), np.uint16))
        inside = {p.parent.parent for p in folder.rglob("*") if p.is_file() and p.name != MARKER}
        assert inside == {folder}, "both stores' files in the run's scratch folder"
        assert np.array_equal(rings[0].pixels, _ring(5).pixels)
    assert sorted(os.listdir(tmp_path)) == [], "the scratch folder removed at the end"
    rings.close()  # after the folder went: no error
    images.close()


def test_a_killed_runs_folder_is_removed_by_the_next_run_only_if_omnipipes(tmp_path: Path) -> None:
    dead = subprocess.run([sys.executable, "-c", "import os; print(os.getpid())"],
                          capture_output=True, text=True, check=True)
    pid = int(dead.stdout)
    stale, alive, foreign = (tmp_path / f".o.scratch-{s}" for s in ("dead1234", "live1234", "mine1234"))
    for folder, owner in ((stale, pid), (alive, os.getpid())):
        folder.mkdir()
        (folder / MARKER).write_text(json.dumps({"tool": "omnipipe", "kind": "scratch", "pid": owner}))
        (folder / "rings.npy-stream").write_bytes(b"x")
    foreign.mkdir()
    (foreign / "notes.txt").write_text("not omnipipe's")
    with scratch_beside(tmp_path / "o"):
        pass
    assert not stale.exists()
    assert (alive / "rings.npy-stream").is_file()
    assert (foreign / "notes.txt").read_text() == "not omnipipe's"
