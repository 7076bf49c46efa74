"""A run whose tracks lag (laser lengths beyond the bias bar over the feature depths) is
estimated again on the views' local contrast, and that estimate kept only where its two
sources agree."""

from __future__ import annotations

import math
from dataclasses import replace
from types import SimpleNamespace

import numpy as np
import pytest

from omnipipe.sfm import pipeline
from omnipipe.sfm.lagging_tracks import kept, lags, plain_config
from omnipipe.sfm.scale_check import UnreliableStretch
from omnipipe.sfm.types import SfmConfig, SfmResult


def _result(offset: float, registered: int = 10, unreliable: int = 0) -> SfmResult:
    """A run of 10 frames whose laser runs ``offset`` (relative) over its feature depths."""
    n = 10
    reg = np.arange(n) < registered
    return SfmResult(
        world_from_rig=np.tile(np.eye(4), (n, 1, 1)),
        registered=reg,
        keyframe=np.zeros(n, bool),
        stationary=np.zeros(n, bool),
        station=np.arange(n),
        unreliable=[UnreliableStretch(k, k + 1, "flagged") for k in range(unreliable)],
        laser_offset=offset,
    )


@pytest.mark.parametrize(
    ("offset", "expected"),
    [(0.08, True), (0.055, True), (0.04, False), (0.0, False), (-0.10, False), (math.nan, False)],
)
def test_only_a_laser_longer_than_the_feature_depths_beyond_the_bar_shows_a_lag(offset: float, expected: bool) -> None:
    """The bar is ``scale_check.max_bias_log`` (5 %); a laser shorter than the feature
    depths (seeds 8, 11, 13, 20: the laser's own bias) is no lag of the tracks."""
    assert lags(SfmConfig(), _result(offset)) is expected


def test_no_second_estimate_where_the_tracks_already_read_the_local_contrast_or_do_not_track() -> None:
    config = SfmConfig()
    assert plain_config(config).features.flow_plain
    assert not lags(plain_config(config), _result(0.08))
    assert not lags(replace(config, tracking=replace(config.tracking, enabled=False)), _result(0.08))


def test_the_second_estimate_is_kept_where_its_sources_agree() -> None:
    first, second = _result(0.08), _result(-0.017)
    assert kept(SfmConfig(), first, second) is second
    assert "that estimate is kept" in second.warnings[-1] and "+8 %" in second.warnings[-1]
    assert not first.warnings


@pytest.mark.parametrize(
    ("second", "why"),
    [
        (_result(0.07), "still differ by +7.0 %"),
        (_result(-0.09), "still differ by -9.0 %"),
        (_result(0.0, registered=9), "more frames unreliable"),
        (_result(0.0, unreliable=1), "more frames unreliable"),
    ],
)
def test_the_first_estimate_is_kept_where_the_second_does_not_agree_or_loses_frames(second: SfmResult, why: str) -> None:
    first = _result(0.08)
    assert kept(SfmConfig(), first, second) is first
    assert why in first.warnings[-1] and "the first estimate is kept" in first.warnings[-1]


@pytest.mark.parametrize(("offset", "runs"), [(0.08, 2), (0.02, 1), (-0.10, 1)])
def test_run_estimates_a_lagging_run_again_on_the_local_contrast(
    monkeypatch: pytest.MonkeyPatch, offset: float, runs: int
) -> None:
    """:func:`omnipipe.sfm.pipeline.run`: once on the CLAHE'd views; a second time, with
    ``features.flow_plain`` on and no progress callback, only when the first lags."""
    calls: list[bool] = []

    def fake_run(config, inputs, progress, executor) -> SfmResult:
        calls.append(config.features.flow_plain)
        assert (progress is None) == config.features.flow_plain
        return _result(-0.01 if config.features.flow_plain else offset)

    monkeypatch.setattr(pipeline, "_run", fake_run)
    monkeypatch.setattr(pipeline, "_flow_views", lambda config, inputs: config)
    result = pipeline.run(SfmConfig(), SimpleNamespace(n_frames=10), progress=lambda i: None)
    assert calls == [False, True][:runs]
    assert result.laser_offset == (-0.01 if runs == 2 else offset)


def test_a_plain_wall_is_not_estimated_again(monkeypatch: pytest.MonkeyPatch) -> None:
    """Below the texture floor the local contrast is not used (:func:`pipeline._flow_views`
    turns it off): the first estimate stands, with no second run."""
    calls: list[bool] = []

    def fake_run(config, inputs, progress, executor) -> SfmResult:
        calls.append(config.features.flow_plain)
        return _result(0.08)

    monkeypatch.setattr(pipeline, "_run", fake_run)
    monkeypatch.setattr(
        pipeline, "_flow_views", lambda config, inputs: replace(config, features=replace(config.features, flow_plain=False))
    )
    pipeline.run(SfmConfig(), SimpleNamespace(n_frames=10))
    assert calls == [False]


@pytest.mark.slow  # ~30 CPU-s: 24 frames rendered at 640x480 and the motion estimated twice
def test_a_corrugated_run_s_lagging_tracks_are_estimated_again_and_its_motion_improves(
    tmp_path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """random-wide seed 18's scene (corrugated, 254 mm, a 56 mm period), 24 frames at
    640x480: on the CLAHE'd views its laser runs +11 % over its feature depths (the
    tracks lag); estimated again on the local contrast the two agree within 5 % and
    both the ATE and the scale error fall (0.27 -> 0.13 mm, 1.3 -> 0.8 %)."""
    from omnipipe import laser, sfm
    from omnipipe.dataset import open_dataset, read_tum
    from omnipipe.evaluation.trajectory import trajectory_errors
    from omnipipe.pipeline import ReconstructConfig
    from omnipipe.sim import make_scenario
    from omnipipe.sim import run as simulate

    sc = make_scenario("random-wide", frames=24, size=(640, 480), seed=18)
    sc.sensors = replace(sc.sensors, odometry=False, imu=False)
    simulate(sc, tmp_path / "ds", workers=1)
    ds = open_dataset(tmp_path / "ds")
    cfg = ReconstructConfig.default()
    inputs = sfm.SfmInputs.of_dataset(ds, laser.run(cfg.laser, ds.rig, (ds.read_frame(i) for i in range(len(ds)))))
    _, true = read_tum(tmp_path / "ds" / "ground_truth" / "poses.txt")

    def errors(m: SfmResult) -> tuple[float, float]:
        reg = np.flatnonzero(m.registered)
        te = trajectory_errors(m.world_from_rig[reg], true[reg])
        return te.ate_rmse_mm, te.scale_error

    with monkeypatch.context() as mp:
        mp.setattr(pipeline, "lags", lambda config, result: False)
        first = sfm.run(cfg.sfm, inputs)
    assert math.log1p(first.laser_offset) > cfg.sfm.scale_check.max_bias_log
    second = sfm.run(cfg.sfm, inputs)
    assert abs(math.log1p(second.laser_offset)) <= cfg.sfm.scale_check.max_bias_log
    assert any("that estimate is kept" in w for w in second.warnings)
    (ate1, scale1), (ate2, scale2) = errors(first), errors(second)
    assert ate2 < 0.7 * ate1 and scale2 < scale1
    assert len(second.unreliable) <= len(first.unreliable)
