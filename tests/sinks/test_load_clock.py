"""The stage clock on a loaded machine: before anything is measured, its predictions are the model's times the load's
slowdown (:func:`pemviz.engine.resources.load_slowdown`, given here as a number)."""

from __future__ import annotations

import pytest
from pemviz.sinks import StageClock

from .synthetic import PLAN, SIMPLE, run_started


def test_the_first_predictions_scale_by_the_load_and_what_is_measured_replaces_it():
    idle, loaded = StageClock(lambda: 0.0, SIMPLE, lambda: 1.0), StageClock(lambda: 0.0, SIMPLE, lambda: 1.5)
    for clock in (idle, loaded):
        clock(run_started(plan=PLAN))
    assert loaded.load == 1.5 and idle.load == 1.0
    assert loaded.run_left_s() == pytest.approx(1.5 * idle.run_left_s()) and idle.run_left_s() > 0.0


def _first_stage_of_plain_rollouts(n: int, workers: int, block_wall_s: float):
    """A ``--method mc`` run of ``n`` rollouts on ``workers`` (constants :data:`SIMPLE`: n x 1e-5 model seconds in
    one process, nothing after), its first block of 8,192 taking ``block_wall_s``: the clock, its console's lines
    after the stage's start and after the block."""
    import dataclasses
    import io

    import numpy as np
    from pemviz.engine.events import RolloutChunk, StageStarted
    from pemviz.estimators import run_plan
    from pemviz.sinks.console import ConsoleSink

    from .synthetic import batch

    cfg = run_started().config.replace(method="mc", n_per_stage=n, workers=workers)
    plan = run_plan(cfg)
    (stage,) = plan.stages
    ticks = [0.0]
    progress = io.StringIO()
    console = ConsoleSink(io.StringIO(), progress)
    console.clock = StageClock(lambda: ticks[0], SIMPLE, lambda: 1.0)
    started = run_started(plan=plan)
    console(dataclasses.replace(started, config=cfg))
    console(StageStarted(stage.stage, stage.kind, n, streamed=True))
    at_start = progress.getvalue()
    ticks[0] = block_wall_s
    block = batch(np.full((8192, 3), 5.0))
    console(RolloutChunk(stage.stage, stage.kind, 0, block, np.zeros(block.n)))
    return console.clock, at_start, progress.getvalue()


def test_a_first_stage_of_plain_rollouts_is_priced_by_its_first_block_and_said_after_it():
    """200,000 plain rollouts on one worker, the first block of 8,192 taking 0.2 s of wall: the stage takes
    0.2 x 200,000 / 8,192 = 4.88 s (the pilot and the load at the start, 1.0 here, said 2.0 s), 4.68 s left; the
    progress line waits for that block."""
    clock, at_start, after = _first_stage_of_plain_rollouts(200_000, 1, 0.2)
    assert clock.block_scale == pytest.approx(0.2 / (8192 * 1e-5), rel=1e-12)
    assert clock.run_left_s() == pytest.approx(0.2 * 200_000 / 8192 - 0.2, rel=1e-9)
    assert at_start == "" and after.count("\n") == 1 and "200000 rollouts" in after


def test_the_first_block_s_speed_decides_the_pool_as_the_engine_does():
    """1,000,000 plain rollouts on 2 workers: 10 model seconds in one process, under the pool's 20 at the pilot's
    speed (1) but 24.4 at the block's (0.2 s for 8,192 rollouts: 2.44 times the model's), so the pool is counted:
    each worker after the first adds a process's speed here (``pool_gain`` 1 in :data:`SIMPLE`), 24.4 / 2 s."""
    clock, _, _ = _first_stage_of_plain_rollouts(1_000_000, 2, 0.2)
    assert SIMPLE.pool_gain == 1.0
    assert clock.run_left_s() == pytest.approx(0.2 * 1_000_000 / 8192 / 2.0 - 0.2, rel=1e-9)
    idle, _, _ = _first_stage_of_plain_rollouts(1_000_000, 2, 8192 * 1e-5)  # the model's speed: no pool
    assert idle.run_left_s() == pytest.approx(10.0 - 8192 * 1e-5, rel=1e-9)


def test_the_console_and_the_panel_read_the_speed_and_the_load_through_one_function(monkeypatch):
    """Both price a run by :func:`pemviz.engine.cost.start_reading`: a reading of 1.5 and 3.0 there is the clock's speed
    and load, and the panel's slowdown."""
    from pemviz.app import form
    from pemviz.engine import cost

    def reading(*args, **kwargs):
        return 1.5, 3.0

    monkeypatch.setattr(cost, "start_reading", reading)
    monkeypatch.setattr("pemviz.sinks.start_reading", reading)
    clock = StageClock(lambda: 0.0, SIMPLE)
    clock(run_started(plan=PLAN))
    assert (clock.speed, clock.load) == (1.5, 3.0)
    form._LOAD.clear()
    cfg = run_started().config
    assert form.run_cost(cfg).slowdown == 3.0
    assert form.run_cost(cfg).seconds == pytest.approx(3.0 * form.run_cost(cfg, slowdown=1.0).seconds)
