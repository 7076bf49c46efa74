"""Shared inputs of the recorded-input tests (bags, MCAP)."""

from __future__ import annotations

from pathlib import Path

import pytest

from omnipipe.sim import make_scenario, run


@pytest.fixture(scope="session")
def eight_frames(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """`omnipipe simulate --scenario paper-small --frames 8 --seed 0` (400x300), made once
    per session (tests that change it work on a copy)."""
    out = tmp_path_factory.mktemp("eight") / "images"
    run(make_scenario("paper-small", frames=8, seed=0), out, workers=1)
    return out
