"""Array-RQMC uniforms (L'Ecuyer, Lecot & Tuffin, Operations Research 2008): by hand, stratified, and on a toy with
an exact answer the importance-sampling estimate keeps its mean and loses most of its variance."""

from __future__ import annotations

import math

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from pemviz.config import ConfigError, ExperimentConfig
from pemviz.core.detectors import ArrayRQMC, ConstantDetector, StageSamplers, WindowDetector, step_uniforms
from pemviz.core.rng import GOLDEN, array_rqmc_uniforms, ranking_key
from pemviz.estimators.base import weighted_steps_mask
from pemviz.scenarios import simulate
from pemviz.scenarios.toy import ToyBraking, ToyParams
from pemviz.scenarios.toy.problem import toy_problem
from pemviz.scenarios.toy.simulator import simulate_toy, toy_log_failure_probability


def test_uniforms_by_hand_ranked_by_key_then_by_the_next_column():
    # ranks by key: chain 1 (key 1) -> 0, chain 0 (key 2) -> 1, chain 2 (key 3) -> 2; u[0] = 0.3 is the shift
    got = array_rqmc_uniforms(np.array([0.3, 0.5, 0.9]), np.array([2.0, 1.0, 3.0]))
    np.testing.assert_allclose(got, [0.3 + GOLDEN, 0.3, 0.3 + 2 * GOLDEN - 1.0], rtol=0, atol=1e-15)
    # equal first column: the second decides (chain 2 before chain 0), chain 1 last
    got = array_rqmc_uniforms(np.array([0.0, 0.7, 0.1]), np.array([[1.0, 5.0], [2.0, 0.0], [1.0, 4.0]]))
    np.testing.assert_allclose(got, [GOLDEN, 2 * GOLDEN - 1.0, 0.0], rtol=0, atol=1e-15)
    with pytest.raises(ValueError, match=r"u must be \[n\], n >= 1, and key \[n\] or \[n, k\]; got \(3,\) and \(2,\)"):
        array_rqmc_uniforms(np.zeros(3), np.zeros(2))


def test_chains_of_equal_detection_probability_detect_in_their_expected_number():
    # 1,000 chains with q(detect) = 0.3: i.i.d. uniforms give Binomial(1000, 0.3) detections (sd 14.5); the shifted
    # golden-ratio lattice has at most ~2 points too many or too few in any interval (three-distance theorem)
    rng = np.random.default_rng(0)
    counts = [int((array_rqmc_uniforms(rng.random(1000), np.zeros(1000)) < 0.3).sum()) for _ in range(200)]
    assert max(abs(c - 300) for c in counts) <= 2
    iid = [int((rng.random(1000) < 0.3).sum()) for _ in range(200)]
    assert max(abs(c - 300) for c in iid) > 20


def test_every_chain_stays_uniform_over_the_random_shift():
    # chain i's uniform over 20,000 shifts: each decile holds 10 % +- 4 standard errors
    rng = np.random.default_rng(1)
    key = rng.normal(size=7)
    u = np.array([array_rqmc_uniforms(rng.random(7), key) for _ in range(20_000)])
    deciles = np.stack([np.histogram(u[:, i], bins=10, range=(0, 1))[0] for i in range(7)]) / 20_000
    assert np.abs(deciles - 0.1).max() < 4 * math.sqrt(0.1 * 0.9 / 20_000)


def _toy_estimates(sampler, reps: int, n: int, seed: int) -> tuple[np.ndarray, float]:
    params = ToyParams(8, 5, 2, 0.6)  # exact (1 - 0.6)^4 = 0.0256
    pb = toy_problem(params)
    rng = np.random.default_rng(seed)
    est = []
    for _ in range(reps):
        b = pb.simulate(n, sampler, pb.target, rng)
        w = np.exp(((b.log_p - b.log_q) * weighted_steps_mask(pb, b, True)).sum(axis=1)) * pb.failed(b)
        est.append(w.mean())
    return np.array(est), math.exp(toy_log_failure_probability(params))


def test_importance_sampling_with_array_rqmc_is_unbiased_and_varies_far_less_on_a_toy():
    # a state-dependent proposal (q(detect) 0.2 below 4.5, 0.6 above), 400 batches of 200 rollouts each way: the mean
    # is the exact answer within 4 standard errors and 2 %; the standard deviation falls from ~14 % to ~2.4 %
    q = WindowDetector(ConstantDetector(0.2), ConstantDetector(0.6), 4.5)
    iid, exact = _toy_estimates(q, 400, 200, 7)
    rqmc, _ = _toy_estimates(ArrayRQMC(q), 400, 200, 7)
    for est in (iid, rqmc):
        assert abs(est.mean() - exact) < 4 * est.std(ddof=1) / math.sqrt(est.size)
    assert abs(rqmc.mean() / exact - 1) < 0.02
    assert rqmc.var() < 0.1 * iid.var()


def test_toy_twins_draw_the_same_array_rqmc_rollouts():
    params = ToyParams(8, 5, 2, 0.6)
    q = ArrayRQMC(WindowDetector(ConstantDetector(0.2), ConstantDetector(0.6), 4.5))
    target = toy_problem(params).target
    a = simulate_toy(params, 50, q, target, np.random.default_rng(3))
    b = simulate(lambda: ToyBraking(params), 50, q, target, np.random.default_rng(3), params.steps)
    np.testing.assert_array_equal(a.detected, b.detected)
    np.testing.assert_array_equal(a.log_q, b.log_q)


def test_config_names_the_allowed_uniforms():
    assert ExperimentConfig.of().uniforms == "array-rqmc" and ExperimentConfig.of().adaptive.pool_weights == "quadratic"
    with pytest.raises(ConfigError, match="uniforms = 'sobol' is invalid: use one of array-rqmc, iid"):
        ExperimentConfig.of(uniforms="sobol")


def test_blocks_are_ranked_among_themselves_and_shifted_by_their_own_first_uniform():
    from pemviz.core.rng import block_bounds, by_blocks

    rng = np.random.default_rng(4)
    u, logit, key = rng.random(10), rng.normal(size=10), rng.normal(size=(10, 2))  # key: by_blocks' rows
    obs = rng.uniform(2.0, 9.0, size=(10, 1))
    sampler = ArrayRQMC(ConstantDetector(0.5))
    got = step_uniforms(u, sampler, logit, obs, block=4)  # blocks [0, 4), [4, 8), [8, 10)
    for a, b in block_bounds(10, 4):
        np.testing.assert_array_equal(got[a:b], step_uniforms(u[a:b], sampler, logit[a:b], obs[a:b]))
    # block 0 by hand: ranks of the logits then the shift u[0]
    ranks = np.argsort(np.argsort(logit[:4]))
    np.testing.assert_allclose(got[:4], np.remainder(ranks * GOLDEN + u[0], 1.0), rtol=0, atol=1e-15)
    one_block = array_rqmc_uniforms(u, np.column_stack([logit, obs]))  # 10 <= 8,192: one block, every chain ranked
    np.testing.assert_array_equal(step_uniforms(u, sampler, logit, obs), one_block)
    assert block_bounds(10, 4) == [(0, 4), (4, 8), (8, 10)]
    calls = []
    out = by_blocks(lambda x: calls.append(len(x)) or x[:, 0] * 2.0, key, block=4)
    assert calls == [4, 4, 2] and np.array_equal(out, key[:, 0] * 2.0)


def test_batched_array_rqmc_rollouts_do_not_depend_on_the_chunk_size():
    from pemviz.core.rollouts import RolloutBatch
    from pemviz.pem import load_pem
    from pemviz.scenarios.braking.batched import iter_batched, simulate_batched
    from pemviz.scenarios.braking.problem import braking_problem

    pb = braking_problem(load_pem())
    q = ArrayRQMC(WindowDetector(ConstantDetector(0.5), pb.target, 10.0))
    whole = simulate_batched(None, 9000, q, pb.target, np.random.default_rng(1))
    small = simulate_batched(None, 9000, q, pb.target, np.random.default_rng(1), chunk_size=97)
    chunks = list(iter_batched(None, 9000, q, pb.target, np.random.default_rng(1), chunk_size=3000))
    assert [c.n for c in chunks] == [3000, 3000, 2192, 808]  # block 0 (8,192) in chunks of 3,000, then block 1
    for other in (small, RolloutBatch.concatenate(chunks)):
        np.testing.assert_array_equal(whole.detected, other.detected)
        np.testing.assert_array_equal(whole.log_q, other.log_q)


def test_a_sampler_with_a_window_couples_only_the_chains_inside_it():
    # a stage's sampler draws from its proposal inside the window (2 m <= gap < 10 m: chains 1, 3, 4) and is the
    # target outside it: those three are ranked by their logits among themselves and shifted by the first one's
    # uniform; the others keep their i.i.d. uniforms (where a detection cannot matter, coupling buys nothing)
    samplers = StageSamplers(ConstantDetector(0.3), ConstantDetector(0.6), radius_m=10.0, floor_m=2.0, eps=0.2)
    obs = np.array([[1.0], [5.0], [12.0], [7.0], [3.0], [20.0]])
    u = np.array([0.11, 0.22, 0.33, 0.44, 0.55, 0.66])
    logit = np.array([5.0, 2.0, 0.0, 2.0, -1.0, 9.0])  # ranks among chains 1, 3, 4: 4 -> 0, then 1 (gap 5) before 3 (7)
    got = step_uniforms(u, ArrayRQMC(samplers.defensive), logit, obs)
    inside = np.array([1, 3, 4])
    np.testing.assert_array_equal(np.delete(got, inside), np.delete(u, inside))
    np.testing.assert_allclose(got[[4, 1, 3]], np.remainder(u[1] + np.arange(3) * GOLDEN, 1.0), rtol=0, atol=1e-15)
    # without a window every chain is coupled, ranked by its logit and then its state; an i.i.d. sampler keeps every
    # uniform
    np.testing.assert_array_equal(
        step_uniforms(u, ArrayRQMC(ConstantDetector(0.5)), logit, obs),
        array_rqmc_uniforms(u, np.column_stack([logit, obs])),
    )
    np.testing.assert_array_equal(step_uniforms(u, samplers.defensive, logit, obs), u)


@settings(max_examples=300, deadline=None)
@given(
    st.lists(
        st.tuples(
            st.sampled_from([-np.inf, -3.5, -1e-40, -0.0, 0.0, 2.0, 2.0 + 1e-12, 7.25, np.inf, np.nan]),
            st.floats(-50.0, 50.0),
        ),
        min_size=1,
        max_size=40,
    )
)
def test_the_ranking_key_orders_chains_by_their_float32_logit_then_by_their_gap(pairs):
    # numpy's lexicographic order of (logit rounded to float32, gap) is the order of the packed keys, ties included;
    # -0.0 ranks before +0.0, and a NaN logit last
    logit, gap = (np.array(c, dtype=np.float64) for c in zip(*pairs, strict=False))
    key = ranking_key(logit, gap)
    p32 = logit.astype(np.float32).astype(np.float64)
    sign = np.signbit(p32).astype(float)  # -0.0 before +0.0
    expected = np.lexsort((gap, -sign, np.nan_to_num(p32, nan=np.inf), np.isnan(p32)))
    got = np.argsort(key, kind="stable")
    np.testing.assert_array_equal(key[got], key[expected])  # equal keys may come in either order only where tied
    np.testing.assert_array_equal(got, np.lexsort((np.arange(gap.size), key)))


def test_plain_monte_carlo_draws_the_same_iid_rollouts_whatever_the_uniforms():
    # its Clopper-Pearson interval counts independent trials: coupled plain rollouts of a toy of p ~ 1e-3 counted 5
    # failures in 5,000 where the i.i.d. ones count 3 (seed 3), and a memory controller's tied chains over-dispersed
    from pemviz.engine.experiment import Experiment
    from pemviz.scenarios.registry import problem_for

    found = []
    for uniforms in ("array-rqmc", "iid"):
        cfg = ExperimentConfig.of(
            scenario="toy", scenario_params=(("braking", 32),), method="mc", n_per_stage=5000, seed=3, uniforms=uniforms
        )
        est = Experiment(cfg, problem=problem_for(cfg)).run().final.estimate
        found.append((est.n_failures, est.log_mu_hat))
    assert found[0] == found[1] == (3, math.log(3 / 5000))


def test_a_scene_couples_its_rollouts_only_where_it_says_so():
    # a controller with a memory the rows do not show misses together when coupled (a user's confirming brake: 3 of 8
    # intervals held p coupled, 8 of 8 i.i.d.): a problem couples only with array_rqmc=True (braking, the toy)
    import dataclasses

    from pemviz.engine.experiment import Experiment

    def run(opt_in: bool, uniforms: str) -> float:
        cfg = ExperimentConfig.of(scenario="toy", n_stages=2, n_per_stage=200, n_final=300, seed=2, uniforms=uniforms)
        problem = dataclasses.replace(toy_problem(ToyParams(30, 8, 3, 0.9)), array_rqmc=opt_in)
        return Experiment(cfg, problem=problem).run().final.estimate.log_mu_hat

    assert math.isfinite(run(False, "iid"))
    assert run(False, "array-rqmc") == run(False, "iid")
    assert run(True, "array-rqmc") != run(True, "iid")
