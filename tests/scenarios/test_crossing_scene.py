"""The crossing scenario (pemviz/scenarios/crossing/), built only from the library's perception stack: it passes the
conformance kit, carries its plain Monte Carlo reference where that holds, and a small plain Monte Carlo run agrees
with the reference."""

from __future__ import annotations

import ast
import math

import numpy as np
import pytest
from pemviz.config import ExperimentConfig
from pemviz.engine.experiment import Experiment
from pemviz.scenarios import registered
from pemviz.scenarios.crossing.problem import MONTE_CARLO_REFERENCE, crossing
from pemviz.scenarios.crossing.scene import BatchedCrossing, CrossingParams
from pemviz.scenarios.registry import get as get_scenario
from pemviz.testing import check_scenario

from conftest import REPO


def test_crossing_is_registered_and_passes_the_conformance_kit(tmp_path):
    assert "crossing" in registered()
    report = check_scenario("crossing", folder=tmp_path)
    assert report.passed == ("schema", "problem", "determinism", "features", "rollout-file", "recording")


def test_crossing_carries_its_monte_carlo_reference_only_at_its_defaults():
    failures, n = MONTE_CARLO_REFERENCE
    assert failures >= 400 and 1e-4 <= failures / n <= 1e-3  # relative standard error <= 5 %, p in [1e-4, 1e-3]
    problem = get_scenario("crossing").problem()
    assert (problem.reference.n_failures, problem.reference.n) == (failures, n)
    assert crossing(None, CrossingParams(brake_ttc_s=1.1)).reference is None


def test_a_small_plain_monte_carlo_run_agrees_with_the_reference():
    problem = crossing(None, None)
    est = Experiment(ExperimentConfig.of(method="mc", n_per_stage=40_000, seed=2), problem=problem).run().final.estimate
    failures, n = MONTE_CARLO_REFERENCE
    expected = 40_000 * failures / n  # about 12
    assert abs(est.n_failures - expected) < 4.5 * math.sqrt(expected)


def test_the_brake_acts_on_confirmed_tracks_only():
    """Every pedestrian detected exactly at every step: the ego stops before the crossing; never detected: it never
    brakes and runs into pedestrian 0."""
    p = CrossingParams()
    for seen in (True, False):
        sim = BatchedCrossing(p, 1)
        clearance = []
        for _ in range(p.n_steps):
            clearance.append(sim.observation()[0, 1])
            sim.step(np.full((1, 2), seen), np.zeros((1, 2, 2)))
        assert bool(sim.braking[0]) is seen
        assert bool(min(clearance) > 0.5) is seen


def test_the_scene_imports_the_stack_and_no_other_scene():
    for name in ("scene.py", "problem.py"):
        tree = ast.parse((REPO / "pemviz" / "scenarios" / "crossing" / name).read_text())
        modules = {n.module for n in ast.walk(tree) if isinstance(n, ast.ImportFrom) and n.module}
        assert not {m for m in modules if m.startswith("pemviz.scenarios.") and "crossing" not in m}, modules
    assert "pemviz.stack" in (REPO / "pemviz" / "scenarios" / "crossing" / "scene.py").read_text()


@pytest.mark.parametrize("bad", [{"brake_ttc_s": 0.0}, {"n_pedestrians": 3}, {"ego_speed_mps": 50.0}])
def test_crossing_parameters_out_of_range_raise(bad):
    with pytest.raises(ValueError, match="CrossingParams"):
        CrossingParams(**bad)
