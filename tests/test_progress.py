"""Progress: rates from the first tick on, the run's remaining time from the stages'
measured times, and inner steps' bars only within a run (and its process)."""

from __future__ import annotations

import io

import pytest

from omnipipe import progress
from omnipipe.progress import STAGE_WEIGHTS, HonestBar, Rate, RunEstimate


class Clock:
    def __init__(self) -> None:
        self.t = 100.0

    def __call__(self) -> float:
        return self.t


def test_rate_ignores_the_first_items_start_up() -> None:
    """A render of 300 frames whose first frame took 19 s (workers, kernels) and then
    1 s a frame: tqdm's first ETA was 300 x 19 s; the honest one waits for a second
    frame, then says 298 s."""
    clock = Clock()
    rate = Rate(300, clock)
    clock.t += 19.0
    rate.update(1)
    assert rate.per_second() is None and rate.remaining_s() is None
    clock.t += 1.0
    rate.update(2)
    assert rate.per_second() == pytest.approx(1.0)
    assert rate.remaining_s() == pytest.approx(298.0)
    clock.t += 10.0  # no tick for 10 s: the time since the last tick is counted off
    assert rate.remaining_s() == pytest.approx(288.0)
    rate.update(300)
    assert rate.remaining_s() == 0.0


def test_honest_bar_shows_no_eta_before_a_rate() -> None:
    out = io.StringIO()
    bar = HonestBar(total=300, file=out, mininterval=0, smoothing=0)
    bar.update(1)
    assert "<?," in out.getvalue().rsplit("\r", 1)[-1]  # no ETA from one item
    bar.close()


def test_run_estimate_scales_the_stages_to_come_by_those_done() -> None:
    clock = Clock()
    run = RunEstimate(clock)
    assert run.remaining_s(None) is None  # nothing started
    run.bar_started("laser")
    assert run.remaining_s(None) is None  # no rate yet
    clock.t += 10.0
    # Laser half done in 10 s: 20 s for it, the rest by the stages' typical shares.
    expected = 10.0 + 20.0 * sum(w for s, w in STAGE_WEIGHTS.items() if s != "laser")
    assert run.remaining_s(10.0) == pytest.approx(expected)
    clock.t += 10.0
    run.bar_started("sfm")  # laser took 20 s
    clock.t += 5.0
    run.bar_started("bundle")  # an inner step of sfm: the same stage
    later = STAGE_WEIGHTS["analysis"] + STAGE_WEIGHTS["model"] + STAGE_WEIGHTS["output"]
    assert run.remaining_s(3.0) == pytest.approx(3.0 + 20.0 * later)
    # Without the bar's own estimate: the stage's typical share less its time so far.
    assert run.remaining_s(None) == pytest.approx(20.0 * (STAGE_WEIGHTS["sfm"] + later) - 5.0)
    assert run.line(3.0).startswith("run 00:25, ~")


def test_stages_loaded_from_checkpoints_do_not_scale_the_estimate() -> None:
    clock = Clock()
    run = RunEstimate(clock)
    run.bar_started("centreline")  # laser and sfm were loaded: no time of theirs
    clock.t += 2.0
    run.bar_started("mesh")  # analysis took 2 s
    scale = 2.0 / STAGE_WEIGHTS["analysis"]
    assert run.remaining_s(1.0) == pytest.approx(1.0 + scale * STAGE_WEIGHTS["output"])


def test_phase_draws_only_within_a_run() -> None:
    seen: list[tuple[str, int, int]] = []

    def factory(name: str, total: int):
        return lambda done: seen.append((name, total, done))

    progress.phase("bundle", 3)(1)  # outside a run: nothing
    with progress.reporting(factory):
        tick = progress.phase("bundle", 3)
        tick(1)
        tick(3)
    progress.phase("bundle", 3)(2)
    assert seen == [("bundle", 3, 1), ("bundle", 3, 3)]
