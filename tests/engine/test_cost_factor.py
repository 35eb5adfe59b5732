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


def test_the_tilt_prices_its_solve_once_and_each_rollout_as_plain_ones_of_its_scene():
    """A tilt run (the cut-in's default): its solve once, on its first stage only, and each tilted rollout (its draw,
    look-ahead and weights) as ``tilt_rollouts`` plain rollouts of the scene, at the scene's cost factor; the console's
    clock and the panel's cost line price it alike (:func:`pemviz.engine.cost.run_cost`)."""
    from pemviz.app.form import run_cost
    from pemviz.estimators import run_plan

    cfg = ExperimentConfig.of(scenario="cut-in", method="tilt", n_per_stage=7_280)
    plain_step = COST.rollout_step_s["batched"] * 6.7  # a plain cut-in rollout's step
    first = stage_cost(cfg, "final", 7_280, stage=1)
    assert first.simulate_s == pytest.approx(
        COST.tilt_solve_s + N_STEPS * (COST.pem_step_s + plain_step * 7_280 * COST.tilt_rollouts), rel=1e-12
    )
    later = stage_cost(cfg, "final", 7_280, stage=2)  # a precision target's added batch: no solve again
    assert first.simulate_s - later.simulate_s == pytest.approx(COST.tilt_solve_s, rel=1e-12)
    assert run_plan(cfg).stages[0].stage == 1  # the solve is priced on the stage the tilt draws first
    cost = run_cost(cfg, slowdown=1.0)  # one figure: the tilt has nothing that may follow
    assert cost.seconds == pytest.approx(first.seconds, rel=1e-12) and cost.then_simulations == 0
    # as measured (calibrate_cost.py --tilt), in plain rollouts held whole against the engine's streamed ones: a
    # tilted rollout 1.87-2.11 of them, the solve 1.25-1.68 model seconds (2.33-2.81 and 2.1-2.5 before, when the
    # plain rollouts the engine streamed were priced as held whole)
    assert 1.5 <= COST.tilt_rollouts <= 2.5 and 1.0 <= COST.tilt_solve_s <= 2.0


def test_a_plain_batch_is_priced_streamed_above_where_the_engine_streams_it_and_the_tilt_s_batch_never():
    """A plain stage above the scene's streaming threshold (:func:`pemviz.engine.experiment.stream_above`: 20,000
    rollouts over the objects a rollout perceives, 4,000 for the cut-in's five cars) costs
    ``streamed_share`` of a held batch's per rollout; the tilt draws its batch whole, whatever its size."""
    from pemviz.engine.experiment import stream_above

    mc = ExperimentConfig.of(scenario="cut-in", method="mc", n_per_stage=10_000)
    assert stream_above(mc, registry.get("cut-in").n_objects) == 4_000
    rollout = COST.rollout_step_s["batched"] * 6.7  # a plain cut-in rollout's step, seconds
    # by hand: 10,000 rollouts in 2 blocks of 8,192 at most, each block its steps' fixed cost
    held = N_STEPS * (2 * COST.pem_step_s + rollout * 10_000)
    streamed = N_STEPS * (2 * COST.pem_step_s + 0.75 * rollout * 10_000)
    assert COST.streamed_share == 0.75
    assert stage_cost(mc, "final", 10_000).simulate_s == pytest.approx(held, rel=1e-12)  # one object: held
    assert stage_cost(mc, "final", 10_000, stream_above=4_000).simulate_s == pytest.approx(streamed, rel=1e-12)
    tilt = ExperimentConfig.of(scenario="cut-in", method="tilt", n_per_stage=10_000)
    whole = N_STEPS * (2 * COST.pem_step_s + rollout * 10_000 * COST.tilt_rollouts)
    assert stage_cost(tilt, "final", 10_000, stage=2, stream_above=4_000).simulate_s == pytest.approx(whole, rel=1e-12)


def test_a_scene_s_declared_parts_price_its_steps_its_fits_and_torch_s_import():
    """``cost_parts``: ``step`` multiplies the fixed cost of a batch's time step (of each block of a large batch),
    ``fit`` a proposal's fit, ``torch`` adds torch's import to the first pretraining of a process that has not
    imported it; the parts leave with the scene."""
    import sys

    from pemviz.settings import SCENARIO_COST_PARTS

    toy = ("pemviz.scenarios.toy:ToyParams", "pemviz.scenarios.builtin:toy")
    register(
        Scenario("parted-toy", "a toy with costly steps and fits", *toy, cost_parts={"step": 2, "fit": 3, "torch": 1})
    )
    try:
        assert SCENARIO_COST_PARTS["parted-toy"] == {"step": 2.0, "fit": 3.0, "torch": 1.0}
        per_rollout = COST.rollout_step_s["batched"] * 1000
        assert simulate_s("parted-toy") == N_STEPS * (2 * COST.pem_step_s + per_rollout)
        # 20,000 rollouts: three blocks of 8,192, each its steps' fixed cost
        assert simulate_s("braking", 20_000) == N_STEPS * (
            3 * COST.pem_step_s + COST.rollout_step_s["batched"] * 20_000
        )
        cfg = ExperimentConfig.of(scenario="parted-toy")
        plain = ExperimentConfig.of(scenario="braking")
        ce = stage_cost(cfg, "ce", 100, stage=5).after_s - COST.stage_s
        assert ce == pytest.approx(3 * (stage_cost(plain, "ce", 100, stage=5).after_s - COST.stage_s), rel=1e-12)
        saved = sys.modules.pop("torch", None)
        try:
            first = stage_cost(cfg, "pretrain", 100, stage=0).after_s
        finally:
            if saved is not None:
                sys.modules["torch"] = saved
        sys.modules.setdefault("torch", saved or type(sys)("torch"))
        try:
            later = stage_cost(cfg, "pretrain", 100, stage=0).after_s
        finally:
            if saved is None:
                del sys.modules["torch"]
        assert first - later == pytest.approx(COST.torch_import_s, rel=1e-12)
        assert COST.torch_import_s > 0
    finally:
        unregister("parted-toy")
    assert "parted-toy" not in SCENARIO_COST_PARTS


@pytest.mark.parametrize("parts", [{"steps": 2.0}, {"step": 0.0}, {"fit": float("inf")}, {"fit": True}, {"step": "2"}])
def test_cost_parts_that_are_no_known_part_or_positive_number_are_refused(parts):
    with pytest.raises(ValueError, match="cost_parts"):
        Scenario("bad", "a scenario", None, "pemviz.scenarios.builtin:toy", cost_parts=parts)
