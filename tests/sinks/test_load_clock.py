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
