"""Bundle adjustment in windows on long runs: every keyframe adjusted once, accuracy kept."""

from __future__ import annotations

from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest

from omnipipe import sfm
from omnipipe.dataset import open_dataset, read_tum
from omnipipe.errors import ConfigError
from omnipipe.evaluation.trajectory import trajectory_errors
from omnipipe.executor import open_executor
from omnipipe.laser import LaserConfig
from omnipipe.pipeline import frame_pass
from omnipipe.sfm.bundle import keyframe_windows
from omnipipe.sfm.stations import StationConfig


@pytest.mark.parametrize("n", [3, 10, 80, 81, 239, 1000])
def test_every_keyframe_is_adjusted_in_exactly_one_window(n: int) -> None:
    windows = keyframe_windows(n, 64, 8)
    owner = np.zeros(n, int)
    for w, (start, end, fixed) in enumerate(windows):
        assert 0 <= start < end <= n and 1 <= fixed < end - start
        if w == 0:
            assert (start, fixed) == (0, 1)
        else:  # held: the last keyframes the window before adjusted
            assert start == windows[w - 1][1] - fixed and fixed == 8
        owner[start + (fixed if w else 0) : end] += 1
    assert np.all(owner[1:] == 1) and windows[-1][1] == n
    assert len(windows) == 1 if n <= 80 else len(windows) >= 2
    assert max(e - s for s, e, _ in windows) <= 64 + 16  # bounded: linear in the run


def test_overlap_must_leave_a_keyframe_free() -> None:
    with pytest.raises(ConfigError, match="window_overlap"):
        keyframe_windows(100, 10, 9)


@pytest.fixture(scope="module")
def long_run(tmp_path_factory: pytest.TempPathFactory) -> Path:
    from omnipipe.sim import make_scenario, run

    out = tmp_path_factory.mktemp("windows") / "ds"
    run(make_scenario("paper-small", frames=48, size=(480, 360), seed=6), out, workers=2)
    return out


@pytest.mark.slow  # 5 s: two sfm runs of 48 frames; the sfm stage stays covered by tests/sfm/test_pipeline.py
def test_windowed_adjustment_keeps_the_trajectory(long_run: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    from omnipipe.sfm import adjust, schur

    solved: list[int] = []  # the windows go to Levenberg-Marquardt on the reduced system
    solve = schur.solve
    monkeypatch.setattr(schur, "solve", lambda *a, **k: solved.append(1) or solve(*a, **k))
    released: list[int] = []  # each window's transient handed back before the next
    release = adjust.release_freed_memory
    monkeypatch.setattr(adjust, "release_freed_memory", lambda: released.append(1) or release())
    dataset = open_dataset(long_run)
    _, true = read_tum(long_run / "ground_truth" / "poses.txt")
    config = sfm.SfmConfig()
    with open_executor(2) as ex:
        frames = frame_pass.run(LaserConfig(), StationConfig(), dataset, ex)
        inputs = sfm.SfmInputs(
            dataset.rig, dataset.read_frame, len(dataset), frames.rings, moved=frames.moved, dataset=dataset
        )
        whole = sfm.run(config, inputs, executor=ex)
        assert not solved  # a global adjustment: SciPy's trf
        small = replace(config, bundle=replace(config.bundle, window_keyframes=5, window_overlap=2))
        windowed = sfm.run(small, inputs, executor=ex)
    n_kf = int(whole.keyframe.sum())
    assert len(keyframe_windows(n_kf, 5, 2)) >= 3  # the run really is cut into windows
    assert len(solved) >= 3
    assert len(released) >= 1 + len(keyframe_windows(n_kf, 5, 2))  # the global run's, then each window's
    e_whole = trajectory_errors(whole.world_from_rig, true)
    e_win = trajectory_errors(windowed.world_from_rig, true)
    print(n_kf, e_whole.to_dict(), e_win.to_dict())
    assert e_win.ate_rmse_mm < 1.0 and e_win.scale_error < 0.05  # the short-run band
    assert e_win.ate_rmse_mm < 1.5 * e_whole.ate_rmse_mm + 0.1
    assert not np.array_equal(windowed.world_from_rig, whole.world_from_rig)  # it did adjust apart


def test_unknown_solver_is_refused() -> None:
    from omnipipe.sfm.bundle import BundleConfig

    with pytest.raises(ConfigError, match=r"sfm\.bundle\.solver"):
        BundleConfig(solver="ceres")
