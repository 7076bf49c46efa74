"""Shared fixtures: small rigs and simulated scenes made at run time."""

from __future__ import annotations

from pathlib import Path

import pytest

from omnipipe.camera import OmniCamera
from omnipipe.rig import Rig
from omnipipe.sim import make_scenario, paper_rig, run


@pytest.fixture(scope="session")
def small_rig() -> Rig:
    """The paper-like rig at 400x300 px."""
    return paper_rig(400, 300)


@pytest.fixture(scope="session")
def small_camera(small_rig: Rig) -> OmniCamera:
    return OmniCamera.from_rig(small_rig)


@pytest.fixture(scope="session")
def small_dataset(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """A paper-small simulated dataset (400x300, 24 frames) on disk, made once per session."""
    out = tmp_path_factory.mktemp("datasets") / "paper-small"
    run(make_scenario("paper-small", seed=3), out)
    return out


@pytest.fixture(scope="session")
def tiny_dataset(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """4 simulated paper-small frames of 64x48 px with timestamps.txt and ground truth,
    made once per session (tests that change it work on a copy)."""
    out = tmp_path_factory.mktemp("tiny") / "ds"
    run(make_scenario("paper-small", frames=4, size=(64, 48), seed=2), out, workers=1)
    return out
