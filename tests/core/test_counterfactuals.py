"""Counterfactuals of a failing rollout: each perception error undone alone, checked against independent replays
(the braking scenario's own single flips; the cut-in's highway-env simulator)."""

from __future__ import annotations

import numpy as np
import pytest
from pemviz import stl
from pemviz.core.counterfactuals import ERROR, MISS, counterfactuals
from pemviz.core.detectors import ConstantDetector
from pemviz.pem import load_pem
from pemviz.scenarios.braking.failures import counterfactual as braking_counterfactual
from pemviz.scenarios.cut_in.highway import CutInScenario
from pemviz.scenarios.cut_in.problem import cut_in_params, cut_in_problem
from pemviz.scenarios.cut_in.scenario import FAILURE_FORMULA, OBSERVATION_NAMES
from pemviz.scenarios.problems import build_problem


def test_braking_single_flips_are_the_braking_scenarios_own():
    problem = build_problem("main")
    batch = problem.simulate(64, ConstantDetector(0.5), problem.target, np.random.default_rng(11))
    failed = np.flatnonzero(problem.failed(batch))
    assert failed.size >= 5
    seen_decisive = 0
    for i in failed[:8]:
        cf = counterfactuals(problem, batch, int(i))
        theirs = braking_counterfactual(batch.detected[i, :, 0])
        assert [x.step for x in cf.decisive] == theirs.decisive.tolist()
        assert all(x.kind == MISS and x.obj == 0 for x in cf.interventions)
        before = np.flatnonzero(~batch.detected[i, : cf.failure_step, 0])
        assert [x.step for x in cf.interventions] == before.tolist()
        seen_decisive += len(cf.decisive)
    assert seen_decisive > 0  # the comparison covered decisive misses, not only empty sets


def test_a_rollout_that_did_not_fail_is_refused():
    problem = build_problem("main")
    batch = problem.simulate(8, problem.target, problem.target, np.random.default_rng(0))
    with pytest.raises(ValueError, match="did not fail"):
        counterfactuals(problem, batch, 0)


@pytest.fixture(scope="module")
def cut_in_failure():
    """A failing cut-in rollout drawn with many misses (a 50 % detector) and the PEMs' errors."""
    problem = cut_in_problem(load_pem(), cut_in_params("moderate"))
    batch = problem.simulate(64, ConstantDetector(0.5), problem.target, np.random.default_rng(2))
    failed = np.flatnonzero(problem.failed(batch))
    assert failed.size
    return problem, batch, int(failed[0])


def test_cut_in_interventions_replayed_on_highway_env_give_the_same_robustness(cut_in_failure):
    problem, batch, i = cut_in_failure
    cf = counterfactuals(problem, batch, i)
    kinds = {x.kind for x in cf.interventions}
    assert kinds == {MISS, ERROR}
    sim = CutInScenario(cut_in_params("moderate"))
    picks = [x for x in cf.interventions if x.decisive][:2] + [x for x in cf.interventions if not x.decisive][:2]
    for x in picks:
        detected, noise = batch.detected[i].copy(), batch.noise[i].copy()
        if x.kind == MISS:
            detected[x.step, x.obj] = True
        noise[x.step, x.obj] = 0.0
        sim.reset()
        obs = np.empty((batch.n_steps, len(OBSERVATION_NAMES)))
        for t in range(batch.n_steps):
            obs[t] = sim.observation()
            sim.step(detected[t], noise[t])
        rho = float(stl.robustness(FAILURE_FORMULA, {n: obs[:, k] for k, n in enumerate(OBSERVATION_NAMES)}))
        assert rho == pytest.approx(x.robustness, abs=1e-9)
    line = cf.summary(dt_s=0.1)
    assert f"before the failure at step {cf.failure_step}" in line


def test_each_objects_p_and_q_of_detection_give_back_the_batchs_own_log_densities():
    """object_detect_probabilities asks the detectors at the rollout's rows; the sum over a step's objects of the log
    probability of each action taken, plus the noise PEM's density of the detected objects' errors, must equal the
    log p the simulator recorded for that step (the batch's own bookkeeping: an independent path)."""
    from pemviz.core.proposal_view import object_detect_probabilities

    problem = cut_in_problem(load_pem())
    batch = problem.simulate(3, problem.target, problem.target, np.random.default_rng(4))
    for i in range(batch.n):
        p, q = object_detect_probabilities(batch, i, problem.target, problem.target)
        d = batch.detected[i]
        assert p.shape == q.shape == d.shape == (100, 5)
        np.testing.assert_array_equal(p, q)
        with np.errstate(divide="ignore"):
            action = np.where(d, np.log(p), np.log1p(-p)).sum(axis=1)
        rows = batch.objects[i].reshape(-1, batch.objects.shape[-1])
        noise = problem.target.noise_log_prob(rows, batch.noise[i].reshape(rows.shape[0], -1)).reshape(d.shape)
        want = action + np.where(d, noise, 0.0).sum(axis=1)
        np.testing.assert_allclose(want, batch.log_p[i], rtol=0, atol=1e-9)
    with pytest.raises(ValueError, match="outside a batch of 3"):
        object_detect_probabilities(batch, 3, problem.target, problem.target)
    braking = build_problem("main")  # one object a step: its batch's log-probabilities are per object already
    one = braking.simulate(2, braking.target, braking.target, np.random.default_rng(0))
    assert object_detect_probabilities(one, 0, braking.target, braking.target) is None


def test_the_summary_counts_one_miss_and_one_error_in_the_singular():
    """``1 misses and 1 measurement errors`` read on a user's scene; zero and several stay plural."""
    from pemviz.core.counterfactuals import ERROR, MISS, Counterfactuals, Intervention

    one = Counterfactuals(0, -0.5, 12, (Intervention(3, 0, MISS, (), 0.2), Intervention(5, 1, ERROR, (0.4, 0.0), -0.1)))
    assert one.summary(("pedestrian", "van")) == (
        "1 miss and 1 measurement error before the failure at step 12; decisive alone: pedestrian missed at step 3"
    )
    none = Counterfactuals(0, -0.5, 12, (Intervention(3, 0, ERROR, (0.4, 0.0), -0.1),) * 2)
    assert none.summary().startswith("0 misses and 2 measurement errors before the failure at step 12; none of them")
