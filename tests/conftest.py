"""Shared fixtures: small rigs and simulated scenes made at run time."""

from __future__ import annotations

import pytest

from omnipipe.camera import OmniCamera
from omnipipe.rig import Rig
from omnipipe.sim import paper_rig


@pytest.fixture(scope="session")
def small_rig() -> Rig:
    """The paper-like rig at 400x300 px."""
    return paper_rig(400, 300)


@pytest.fixture(scope="session")
def small_camera(small_rig: Rig) -> OmniCamera:
    return OmniCamera.from_rig(small_rig)
