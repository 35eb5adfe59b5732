"""The cost model scales a scenario's simulation seconds by the cost factor the scenario declares
(:attr:`pemviz.scenarios.registry.Scenario.cost_factor`), read from :data:`pemviz.settings.SCENARIO_COST_FACTORS`:
the engine names no scenario."""

from __future__ import annotations

import pytest

from pemviz.config import ExperimentConfig
from pemviz.engine.cost import COST, N_STEPS, stage_cost
from pemviz.scenarios import registry
from pemviz.scenarios.registry import Scenario, register, unregister
from pemviz.settings import SCENARIO_COST_FACTORS


def simulate_s(scenario: str, n: int = 1000) -> float:
    return stage_cost(ExperimentConfig.of(scenario=scenario, method="mc", n_per_stage=n), "final", n).simulate_s


def test_the_cut_in_scenarios_declare_their_factor_and_the_cost_is_the_one_measured():
    assert registry.get("cut-in").cost_factor == registry.get("cut-in-rare").cost_factor == 6.7
    assert registry.get("braking").cost_factor == 1.0
    braking = N_STEPS * (COST.pem_step_s + COST.rollout_step_s["batched"] * 1000)
    cut_in = N_STEPS * (COST.pem_step_s + COST.rollout_step_s["batched"] * 6.7 * 1000)
    assert simulate_s("braking") == braking
    assert simulate_s("cut-in") == simulate_s("cut-in-rare") == cut_in


def test_a_registered_scenario_s_factor_scales_its_cost_and_leaves_with_it():
    register(
        Scenario(
            "costly-toy",
            "a toy whose steps cost three braking ones",
            "pemviz.scenarios.toy:ToyParams",
            "pemviz.scenarios.builtin:toy",
            cost_factor=3.0,
        )
    )
    try:
        assert SCENARIO_COST_FACTORS["costly-toy"] == 3.0
        per_rollout = COST.rollout_step_s["batched"] * 1000
        assert simulate_s("costly-toy") == N_STEPS * (COST.pem_step_s + per_rollout * 3.0)
    finally:
        unregister("costly-toy")
    assert "costly-toy" not in SCENARIO_COST_FACTORS


@pytest.mark.parametrize("factor", [0.0, -1.0, float("inf"), float("nan"), True, "2"])
def test_a_cost_factor_that_is_no_positive_number_is_refused(factor):
    with pytest.raises(ValueError, match="cost_factor must be a finite number > 0"):
        Scenario("bad", "a scenario", None, "pemviz.scenarios.builtin:toy", cost_factor=factor)
