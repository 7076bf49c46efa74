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
from omnipipe.sfm.lagging_tracks import LAG_SHARE, feature_gain, kept, lags, plain_config
from omnipipe.sfm.scale_check import StepCheck, UnreliableStretch
from omnipipe.sfm.types import SfmConfig, SfmResult


def _result(offset: float, registered: int = 10, unreliable: int = 0, feature_gain: float = 1.0) -> SfmResult:
    """A run of 10 frames 2 mm apart along z whose laser runs ``offset`` (relative) over
    its feature depths, keyframe steps 0->3->6->9 whose feature depth lengths are
    ``feature_gain`` / (1 + ``offset``) of the travel."""
    n = 10
    world_from_rig = np.tile(np.eye(4), (n, 1, 1))
    world_from_rig[:, 2, 3] = 2.0 * np.arange(n)
    checks = [
        StepCheck(a, a + 3, 6.0, 0.0, 6.0 * feature_gain / (1.0 + offset), 200, 6.0, "high")
        for a in (0, 3, 6)
    ]
    return SfmResult(
        world_from_rig=world_from_rig,
        registered=np.arange(n) < registered,
        keyframe=np.isin(np.arange(n), [0, 3, 6, 9]),
        stationary=np.zeros(n, bool),
        station=np.arange(n),
        step_checks=checks,
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


def test_the_second_estimate_is_kept_where_its_sources_agree_and_its_feature_depths_lengthened() -> None:
    """The lag undone: the second's feature depths 8 % longer against the same poses."""
    first, second = _result(0.08), _result(-0.017, feature_gain=1 - 0.017)
    assert feature_gain(first, second) == pytest.approx(math.log(1.08), abs=1e-9)
    assert kept(SfmConfig(), first, second) is second
    assert "that estimate is kept" in second.warnings[-1] and "+8 %" in second.warnings[-1]
    assert not first.warnings


def test_a_laser_that_ran_long_on_its_own_keeps_the_first_estimate() -> None:
    """random-features seed 22: the laser +11 % over the feature depths, +3 % on the
    local contrast, the feature depths only 1 % longer: the laser moved, not the tracks."""
    first = _result(0.11)
    second = _result(0.03, feature_gain=1.01 * 1.03 / 1.11)
    assert feature_gain(first, second) < LAG_SHARE * math.log(1.11)
    assert kept(SfmConfig(), first, second) is first
    assert not first.warnings  # as it was: its own warning says how far the sources differ


@pytest.mark.parametrize(
    "second",
    [
        _result(0.07, feature_gain=1.08 * 1.07),  # the sources still differ by 7 %
        _result(-0.09, feature_gain=1.08 * 0.91),  # ... by -9 %
        _result(0.0, registered=9, feature_gain=1.08),  # a frame less registered
        _result(0.0, unreliable=1, feature_gain=1.08),  # a stretch more unreliable
    ],
)
def test_the_first_estimate_is_kept_where_the_second_does_not_agree_or_loses_frames(second: SfmResult) -> None:
    first = _result(0.08)
    assert kept(SfmConfig(), first, second) is first
    assert not first.warnings


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
        return _result(-0.01, feature_gain=0.99 * (1 + offset)) if config.features.flow_plain else _result(offset)

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
