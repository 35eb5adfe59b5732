"""The stage clock on a loaded machine: before anything is measured, its predictions are the model's times the load's
slowdown (:func:`pemviz.engine.resources.load_slowdown`, given here as a number)."""

from __future__ import annotations

import pytest
from pemviz.engine.resources import Competition, LoadReading
from pemviz.sinks import StageClock

from .synthetic import PLAN, SIMPLE, run_started


def test_the_first_predictions_scale_by_the_load_and_what_is_measured_replaces_it():
    idle, loaded = StageClock(lambda: 0.0, SIMPLE, lambda: 1.0), StageClock(lambda: 0.0, SIMPLE, lambda: 1.5)
    for clock in (idle, loaded):
        clock(run_started(plan=PLAN))
    assert loaded.load == 1.5 and idle.load == 1.0
    assert loaded.run_left_s() == pytest.approx(1.5 * idle.run_left_s()) and idle.run_left_s() > 0.0


def test_the_console_and_the_panel_read_the_speed_and_the_load_through_one_function(monkeypatch):
    """Both price a run by :func:`pemviz.engine.cost.start_reading`: a reading of 1.5 and 3.0 there is the clock's speed
    and load, and the panel's slowdown."""
    from pemviz.app import form
    from pemviz.engine import cost

    load = LoadReading(2, Competition(((1.0, 1.0), (1.0, 1.0))))  # two other busy sessions on 2 CPUs

    def reading(*args, **kwargs):
        return 1.5, 3.0, load

    monkeypatch.setattr(cost, "start_reading", reading)
    monkeypatch.setattr("pemviz.sinks.start_reading", reading)
    clock = StageClock(lambda: 0.0, SIMPLE)
    clock(run_started(plan=PLAN))
    assert (clock.speed, clock.load, clock.reading) == (1.5, 3.0, load)
    form._LOAD.clear()
    cfg = run_started().config
    assert form.run_cost(cfg).slowdown == 3.0
    assert form.run_cost(cfg).seconds == pytest.approx(3.0 * form.run_cost(cfg, slowdown=1.0).seconds)


def test_the_console_and_the_panel_price_a_pooled_batch_by_the_same_load(monkeypatch):
    """A million plain rollouts on 2 workers: the clock's first prediction and the panel's cost line move alike, by the
    pool's speed-up at the load :func:`pemviz.engine.cost.start_reading` read (2 idle, 1 beside two busy sessions on
    2 CPUs: the model's simulation once over COST.pool_share / 2, once over COST.pool_share), the slowdown held
    at 1."""
    from pemviz.app import form
    from pemviz.core.plan import RunPlan
    from pemviz.engine import cost

    cfg = {"method": "mc", "n_per_stage": 10**6, "workers": 2}
    plan = RunPlan.of([(1, "final", 10**6)])
    clock_s, panel_s = {}, {}
    for name, load in (("idle", LoadReading(2)), ("busy", LoadReading(2, Competition(((1.0, 1.0), (1.0, 1.0)))))):
        monkeypatch.setattr(cost, "start_reading", lambda *a, _load=load, **k: (1.0, 1.0, _load))
        monkeypatch.setattr("pemviz.sinks.start_reading", lambda *a, _load=load, **k: (1.0, 1.0, _load))
        clock = StageClock(lambda: 0.0)
        clock(run_started(plan=plan, **cfg))
        clock_s[name] = clock.run_left_s()
        form._LOAD.clear()
        panel_s[name] = form.run_cost(run_started(**cfg).config).seconds
    one = cost.stage_cost(run_started(**{**cfg, "workers": 1}).config, "final", 10**6)  # one process's seconds
    added = one.simulate_s * cost.COST.pool_share * (1.0 - 0.5)  # busy less idle
    assert clock_s["busy"] - clock_s["idle"] == pytest.approx(added, rel=1e-9)
    assert panel_s["busy"] - panel_s["idle"] == pytest.approx(added, rel=1e-9)
