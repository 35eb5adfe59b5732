"""The crossing scenario (pemviz/scenarios/crossing/), built only from the library's perception stack: it passes the
conformance kit, carries its plain Monte Carlo reference where that holds, and a small plain Monte Carlo run agrees
with the reference."""

from __future__ import annotations

import ast
import math

import numpy as np
import pytest
from pemviz.config import ExperimentConfig, scene_defaults
from pemviz.engine.experiment import Experiment
from pemviz.scenarios import registered
from pemviz.scenarios.crossing.problem import MONTE_CARLO_REFERENCE, crossing
from pemviz.scenarios.crossing.scene import BatchedCrossing, CrossingParams
from pemviz.scenarios.registry import get as get_scenario
from pemviz.scenarios.registry import problem_for
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


def test_each_rollout_brakes_by_its_own_trigger_and_deceleration_as_the_scene_at_those_values():
    """Over an ODD each rollout has its own brake_ttc_s and brake_mps2 (BatchedCrossing's per_rollout): stepped with
    the same detections and errors, each rollout is the scene built at its values, to the bit."""
    rng = np.random.default_rng(5)
    ttc, decel = np.array([1.3, 1.5, 2.5, 1.3]), np.array([8.0, 8.0, 6.0, 11.0])
    p = CrossingParams()
    together = BatchedCrossing(p, 4, {"brake_ttc_s": ttc, "brake_mps2": decel})
    alone = [BatchedCrossing(CrossingParams(brake_ttc_s=t, brake_mps2=d), 1) for t, d in zip(ttc, decel, strict=True)]
    for _ in range(p.n_steps):
        detected, noise = rng.random((4, 2)) < 0.6, rng.standard_normal((4, 2, 2))
        np.testing.assert_array_equal(together.observation(), np.concatenate([a.observation() for a in alone]))
        together.step(detected, noise)
        for i, a in enumerate(alone):
            a.step(detected[i : i + 1], noise[i : i + 1])
    assert len({round(float(a.x[0]), 6) for a in alone}) == 4  # each stopped (or not) at its own place
    with pytest.raises(ValueError, match="per_rollout"):
        BatchedCrossing(p, 2, {"walk_speed_mps": np.ones(2)})


def test_the_crossing_over_its_trigger_runs_plain_monte_carlo_with_an_interval():
    """``--param brake_ttc_s~uniform(1.3, 1.5)``: plain Monte Carlo by default (its interval, not a bound, holding
    what p is at the range's ends: 2.98e-4 and 1.29e-4 by plain Monte Carlo, docs/realistic-stack.md), the map over
    the trigger's range; a parameter the scene does not draw per rollout is refused."""
    params = (("brake_ttc_s", "~uniform(1.3, 1.5)"),)
    cfg = ExperimentConfig.of(scenario="crossing", scenario_params=params, **scene_defaults("crossing", params))
    assert cfg.method == "mc" and cfg.n_per_stage == 200_000
    problem = problem_for(cfg)
    assert problem.reference is None and problem.odd.names == ("brake_ttc_s",)
    final = Experiment(cfg.replace(n_per_stage=20_000, seed=1), problem=problem).run().final
    e = final.estimate
    assert e.interval_backed and e.log_ci[0] < math.log(2.98e-4) and e.log_ci[1] > math.log(1.29e-4), e.summary()
    drawn = [b for b in final.odd_map.bins if b.name == "brake_ttc_s"]
    assert len(drawn) == 5 and drawn[0].lo == pytest.approx(1.3) and drawn[-1].hi == pytest.approx(1.5)
    with pytest.raises(ValueError, match="walk_speed_mps"):
        problem_for(ExperimentConfig.of(scenario="crossing", scenario_params=(("walk_speed_mps", "~uniform(1, 2)"),)))
