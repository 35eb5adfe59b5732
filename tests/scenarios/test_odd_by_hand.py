"""A scenario of one's own over an operating design domain, built the way docs/odd.md first showed it: a factory
``(config, params, odd) -> Problem`` whose rollouts come from :func:`pemviz.core.odd_rollouts.odd_rollout_functions`
and which sets nothing else. The registry marks such a problem as over its ODD, so that it runs as pemviz's own: a
batch of more than one block of rollouts simulated in this process (the parameters are drawn before the events: the
blocks cannot be drawn apart), the map, the proposal over the parameters and the verdict's cap where a bin of the
map has no failure."""

from __future__ import annotations

import dataclasses
import math

import numpy as np
import pytest
from pemviz.config import ExperimentConfig
from pemviz.core.odd_rollouts import odd_rollout_functions
from pemviz.core.rng import RQMC_BLOCK
from pemviz.engine.experiment import Experiment
from pemviz.scenarios.registry import Scenario, problem_for, register, unregister
from pemviz.scenarios.toy.odd import _PerRollout
from pemviz.scenarios.toy.problem import toy_problem
from pemviz.scenarios.toy.simulator import ToyParams

ODD_PARAMS = (("total", 10), ("safe", 3), ("braking", "~choice(5, 6, 7)"))
EXACT = (1e-3 + 1e-4 + 1e-5) / 3  # the toy (10, b, 3, p = 0.9): (1 - 0.9)^(b - 2), b = 5, 6, 7 alike


def by_hand(config, params, odd):
    """The toy over ``odd`` as a user writes it from the guide: the rollouts over the ODD, and nothing else set."""
    p = params or ToyParams()
    simulate, stream, branch = odd_rollout_functions(lambda n, values: _PerRollout(p, n, values[:, 0]), odd, p.steps)
    base = toy_problem(dataclasses.replace(p, braking=7))
    return dataclasses.replace(base, simulate=simulate, stream=stream, branch=branch, exact_log_p=None)


@pytest.fixture
def scenario():
    register(
        Scenario(
            "toy-odd-by-hand",
            "the toy, its ODD by hand",
            ToyParams,
            lambda c, p: toy_problem(p),
            random_params=("braking",),
            odd=by_hand,
        )
    )
    yield "toy-odd-by-hand"
    unregister("toy-odd-by-hand")


def test_a_problem_over_an_odd_by_hand_runs_more_than_a_block_as_pemvizs_own(scenario):
    n = RQMC_BLOCK + 1  # two blocks: before the registry marked it, the pool's block draw raised a RuntimeError
    problem = problem_for(ExperimentConfig.of(scenario=scenario, scenario_params=ODD_PARAMS))
    assert problem.odd is not None and problem.odd.names == ("braking",)
    assert problem.verdict_cap == toy_problem(ToyParams()).verdict_cap  # its own: the map's empty bins cap it
    run = Experiment(
        ExperimentConfig.of(scenario=scenario, scenario_params=ODD_PARAMS, method="mc", n_per_stage=n), problem=problem
    ).run()
    toy = ExperimentConfig.of(scenario="toy", scenario_params=ODD_PARAMS, method="mc", n_per_stage=n)
    shipped = Experiment(toy, problem=problem_for(toy)).run()
    assert run.final.estimate.log_mu_hat == shipped.final.estimate.log_mu_hat  # the same rollouts as the toy's own
    e = run.final.estimate
    assert e.log_ci[0] <= math.log(EXACT) <= e.log_ci[1]
    rollouts = problem.simulate(300, problem.target, problem.target, np.random.default_rng(0))
    assert set(np.unique(rollouts.observations[:, 0, rollouts.observation_names.index("braking")])) == {5.0, 6.0, 7.0}
