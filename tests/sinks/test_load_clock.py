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
