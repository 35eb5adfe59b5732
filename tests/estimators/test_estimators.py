"""The estimators: failure steps, weights up to the failure, elites, the defensive mixture, the CE fit's closed form."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch
from pemviz.config import ExperimentConfig
from pemviz.core.detectors import ConstantDetector, action_log_prob
from pemviz.core.rollouts import RolloutBatch
from pemviz.core.sampling import Proposal
from pemviz.estimators import build_estimator
from pemviz.estimators.base import failure_steps, log_weight
from pemviz.estimators.ce_fit import FitOptions, break_ties, ce_update
from pemviz.estimators.cross_entropy import CrossEntropy, DefensiveDetector
from pemviz.estimators.fallback import PlainFallback
from pemviz.estimators.fixed import FixedSampler
from pemviz.scenarios.problems import build_problem
from pemviz.scenarios.toy import ToyParams
from pemviz.scenarios.toy.problem import toy_problem

SMALL_RUN = dict(n_per_stage=50, n_final=100, ce_epochs=100, pretrain_epochs=100)
"""K x 50 rollouts, N_e = 100, 100 Adam epochs per fit: a run of a second or two."""


def test_failure_steps_are_the_first_step_below_the_safe_distance():
    pb = toy_problem(ToyParams(10, 5, 3, 0.9))
    batch = pb.simulate(200, ConstantDetector(0.3), pb.target, np.random.default_rng(0))
    steps = failure_steps(pb, batch)
    failed = pb.failed(batch)
    assert np.all(steps[failed] == 8) and np.all(steps[~failed] == batch.n_steps)  # distance 2 at step 8


def test_weights_until_failure_sum_the_factors_before_the_failure_step_only():
    pb = toy_problem(ToyParams(10, 5, 3, 0.9))
    batch = pb.simulate(100, ConstantDetector(0.3), pb.target, np.random.default_rng(1))
    failed = pb.failed(batch)
    assert failed.any() and (~failed).any()
    by_hand = np.where(
        failed,
        (batch.log_p - batch.log_q)[:, :8].sum(axis=1),
        (batch.log_p - batch.log_q)[:, : batch.n_steps - 1].sum(axis=1),
    )
    np.testing.assert_allclose(log_weight(pb, batch, until_failure=True), by_hand, rtol=1e-12)
    np.testing.assert_allclose(log_weight(pb, batch, until_failure=False), batch.log_weight(), rtol=0)


def test_defensive_mixture_and_tie_breaking_by_hand():
    d = DefensiveDetector(ConstantDetector(0.99), 0.2)
    p = 1.0 / (1.0 + math.exp(-d.detect_logit(np.zeros((1, 3)))[0]))
    assert p == pytest.approx(0.8 * 0.99 + 0.1, rel=1e-12)
    r = np.array([3.0, 1.0, 1.0, 1.0, 1.0, 1.0, 1.0, 0.5, 2.0, 5.0])
    elite = break_ties(r, 1.0, 0.7, np.random.default_rng(0))  # ceil(0.3 x 10) = 3 elites
    assert elite.sum() == 3 and elite[7] and not elite[[0, 8, 9]].any()


@pytest.mark.parametrize("fit", ["adam", "lbfgs"])
def test_ce_fit_of_a_proposal_with_one_input_is_the_alpha_weighted_detection_rate(fit):
    # with every step at the same gap, q(detect) is one Bernoulli parameter and the CE objective
    # sum_i w_i^alpha sum_t m_it log q(a_it) is maximised at
    # sum_i w_i^alpha sum_t m_it a_it / sum_i w_i^alpha sum_t m_it
    # (the weighted MLE of a Bernoulli), w_i = prod_{t < T-1, m_it} p / q (Innes & Ramamoorthy 2022, eq. 10-11).
    rng = np.random.default_rng(3)
    n, t, alpha = 40, 12, 0.5
    gaps = np.full((n, t), 5.0)
    detected = rng.random((n, t)) < 0.3
    log_p, log_q = np.log(np.where(detected, 0.9, 0.1)), np.log(np.where(detected, 0.3, 0.7))
    elite = rng.random(n) < 0.4
    mask = rng.random((n, t)) < 0.8
    w = np.exp(alpha * ((log_p - log_q)[:, : t - 1] * mask[:, : t - 1]).sum(axis=1))[elite]
    expected = float((w[:, None] * mask[elite] * detected[elite]).sum() / (w[:, None] * mask[elite]).sum())
    torch.manual_seed(0)
    q = Proposal()
    epochs, lr = (1500, 5e-2) if fit == "adam" else (60, 1e-3)
    ce_update(
        q,
        gaps,
        detected,
        log_p,
        log_q,
        elite,
        FitOptions(epochs, lr, fit=fit, tolerance=1e-15 if fit == "lbfgs" else None),
        smoothing=alpha,
        step_mask=mask,
    )
    assert 0.2 < expected < 0.5 and q.curve(np.array([5.0]))[0] == pytest.approx(expected, abs=1e-4)


def test_cross_entropy_plans_pretraining_k_stages_and_the_final_batch():
    pb = build_problem("toy-1e-3")
    cfg = ExperimentConfig.of(
        n_stages=2, n_per_stage=30, n_final=40, pretrain_rollouts=20, pretrain_epochs=20, ce_epochs=20, seed=0
    )
    assert isinstance(
        build_estimator(cfg.replace(plain_fallback=500), pb), PlainFallback
    )  # plain Monte Carlo may follow
    est = build_estimator(cfg.replace(plain_fallback=0), pb)
    assert isinstance(est, CrossEntropy)
    plans, rng = [], np.random.default_rng(0)
    while (plan := est.next_stage()) is not None:
        plans.append((plan.stage, plan.kind, plan.n))
        batch = pb.simulate(plan.n, plan.sampler, pb.target, rng)
        est.observe(batch, pb.failed(batch), pb.robustness(batch, cfg.metric))
        est.finish()
    assert plans == [(0, "pretrain", 20), (1, "ce", 30), (2, "ce", 30), (3, "final", 40)]


def test_a_baseline_is_one_weighted_batch_whose_estimate_is_eq_6():
    pb = build_problem("toy-1e-3")
    est = build_estimator(ExperimentConfig.of(method="naive50", n_per_stage=500, weights_until_failure=False), pb)
    assert isinstance(est, FixedSampler)
    plan = est.next_stage()
    assert (plan.stage, plan.kind, plan.n) == (1, "final", 500) and est.next_stage() is None
    batch = pb.simulate(plan.n, plan.sampler, pb.target, np.random.default_rng(0))
    failed = pb.failed(batch)
    np.testing.assert_array_equal(est.observe(batch, failed, None), batch.log_weight())
    outcome = est.finish()
    mu, used = est.result()
    w = np.exp(batch.log_weight())
    assert used == (1,) and outcome.n_elites == failed.sum() > 0
    assert mu.log_mu_hat == pytest.approx(math.log(np.sum(w * failed) / 500), rel=1e-12)


@pytest.mark.parametrize("seed", range(8))
def test_elite_candidates_keep_exactly_the_rollouts_at_or_below_the_threshold_of_all_n(seed):
    """Chunk by chunk, the pool ends with gamma_kappa of the whole stage and every rollout r <= gamma, in order."""
    from pemviz.core.rollouts import RolloutBatch
    from pemviz.estimators.base import EliteCandidates, quantile_threshold

    rng = np.random.default_rng(seed)
    n = int(rng.integers(50, 400))
    r = rng.integers(-3, 30, n).astype(float) if seed % 2 else rng.normal(5, 3, n)  # ties, or none
    batch = RolloutBatch(
        np.arange(n, dtype=float)[:, None, None], np.zeros((n, 1), bool), np.zeros((n, 1)), np.zeros((n, 1)), ("gap_m",)
    )
    pool = EliteCandidates(n, 0.9, floor=0.0)
    cuts = np.sort(rng.choice(np.arange(1, n), size=int(rng.integers(0, 8)), replace=False))
    settled = []
    for a, b in zip(np.r_[0, cuts], np.r_[cuts, n], strict=False):
        pool.add(batch.select(np.arange(a, b)), r[a:b])
        if seed >= 2:  # failures are handed over once the bound is the floor
            done, index = pool.settle()
            assert done is None or (np.all(r[index] < 0) and pool.bound() == 0.0)
            settled += index.tolist()
    gamma = quantile_threshold(r, 0.9, floor=0.0)
    kept, kept_r, kept_i = pool.candidates()
    assert pool.gamma() == gamma and pool.n_settled == len(settled)
    np.testing.assert_array_equal(np.sort(np.r_[settled, kept_i]), np.flatnonzero(r <= gamma))
    np.testing.assert_array_equal(kept_r, r[kept_i])
    if kept is not None:
        np.testing.assert_array_equal(kept.observations[:, 0, 0], kept_i)
    elite = break_ties(kept_r, gamma, 0.9, np.random.default_rng(7), n=n, settled=len(settled))
    whole = break_ties(r, gamma, 0.9, np.random.default_rng(7))
    np.testing.assert_array_equal(np.sort(np.r_[settled, kept_i[elite]]), np.flatnonzero(whole))


def test_elite_steps_thinned_as_they_come_keep_the_weighted_log_likelihood_in_expectation():
    """Thinning the gathered steps (systematic resampling, repeated as chunks arrive) keeps
    E[sum_s w_s f(h_s, a_s)] for any f: the CE objective's expectation."""
    from pemviz.core.rollouts import RolloutBatch
    from pemviz.estimators.ce_fit import EliteSteps

    rng = np.random.default_rng(0)
    m, t = 60, 5
    h = rng.normal(size=(m, t))
    batch = RolloutBatch(h[:, :, None], rng.random((m, t)) < 0.4, np.zeros((m, t)), np.zeros((m, t)), ("gap_m",))
    mask = rng.random((m, t)) < 0.7
    log_w = rng.normal(0, 2, m)

    def f(x, a):
        return np.sin(3 * x) + a

    exact = float((np.exp(log_w)[:, None] * mask * f(h, batch.detected[..., 0])).sum())
    draws = []
    for seed in range(1500):
        steps = EliteSteps(np.linspace(0, 1, 3), max_rows=12, rng=np.random.default_rng(seed), thin_above=30)
        for a in range(0, m, 15):  # 4 chunks of 15 rollouts: thinned whenever more than 30 steps are held
            sel = np.arange(a, a + 15)
            steps.add(sel, batch.select(sel), h[sel], mask[sel], log_w[sel])
        rows, actions, lw = steps.arrays()
        assert steps.thinned and rows.size <= 2 * 12 + 30
        draws.append(float((np.exp(lw) * f(rows, actions)).sum()))
    draws = np.array(draws)
    assert steps.n_steps == mask.sum() and steps.n_rollouts == m
    assert abs(draws.mean() - exact) < 4 * draws.std() / math.sqrt(draws.size)


def test_mixture_weights_by_hand_are_bounded_by_the_target_share_and_unbiased_on_a_toy():
    from pemviz.estimators.base import mixture_log_weight, weighted_steps_mask
    from pemviz.scenarios.toy.simulator import toy_log_failure_probability

    # p(x) = 1e-6, q1(x) = 0.5, q2(x) = 1e-3, shares (0.1, 0.45, 0.45): w = 1e-6 / (1e-7 + 0.225 + 4.5e-4)
    log_w = mixture_log_weight(np.log([1e-6]), np.log([[1e-6], [0.5], [1e-3]]), np.array([0.1, 0.45, 0.45]))
    assert log_w[0] == pytest.approx(math.log(1e-6 / (1e-7 + 0.225 + 4.5e-4)), rel=1e-12)
    # a rollout q misses entirely: its weight is at most 1 / 0.1
    assert mixture_log_weight(np.log([0.3]), np.array([[math.log(0.3)], [-np.inf]]), np.array([0.1, 0.9]))[
        0
    ] == pytest.approx(math.log(10.0), rel=1e-12)
    # fixed shares of a toy (exact (1 - 0.6)^4): the mean weighted failure indicator is the exact answer within 4
    # standard errors (balance heuristic, Veach & Guibas 1995)
    params = ToyParams(8, 5, 2, 0.6)
    pb = toy_problem(params)
    q_miss = ConstantDetector(0.2)
    rng = np.random.default_rng(0)
    parts = ((2_000, pb.target), (18_000, q_miss))
    batch = RolloutBatch.concatenate([pb.simulate(n, d, pb.target, rng) for n, d in parts])
    mask = weighted_steps_mask(pb, batch, until_failure=True)
    obs = batch.observations.reshape(-1, batch.observations.shape[2])
    log_q = [
        (action_log_prob(d.detect_logit(obs).reshape(mask.shape), batch.detected[..., 0]) * mask).sum(axis=1)
        for _, d in parts
    ]
    log_p = (batch.log_p * mask).sum(axis=1)
    w = np.exp(mixture_log_weight(log_p, np.stack(log_q), np.array([0.1, 0.9]))) * pb.failed(batch)
    exact = math.exp(toy_log_failure_probability(params))
    assert w.max() <= 10.0 + 1e-9
    assert abs(w.mean() - exact) < 4 * w.std() / math.sqrt(w.size)
    assert abs(w.mean() / exact - 1) < 0.05


def test_linear_pool_weights_by_hand_and_unbiased_over_stages_of_different_proposals():
    from pemviz.estimators.base import StageRollouts, pooled_estimate
    from pemviz.scenarios.toy.simulator import toy_log_failure_probability

    params = ToyParams(8, 5, 2, 0.6)  # exact (1 - 0.6)^4 = 0.0256
    pb = toy_problem(params)
    exact = math.exp(toy_log_failure_probability(params))
    grid = pb.curve_grid
    # by hand: stage 1 (2 rollouts, one fails with w = 0.5), stage 2 (4 rollouts, one fails with w = 0.02); linear
    # weights (1 * 2, 2 * 4) / 10 -> mu_hat = 0.2 * 0.25 + 0.8 * 0.005 = 0.054 (the pool of rollouts alike: 0.52 / 6)
    one, two = StageRollouts(grid), StageRollouts(grid)
    one.parts.append((np.log([0.5, 1.0]), np.array([True, False]), np.zeros(2)))
    two.parts.append((np.log([0.02, 1.0, 1.0, 1.0]), np.array([True, False, False, False]), np.zeros(4)))
    lam = np.array([1 * 2, 2 * 4], dtype=np.float64) / 10
    assert math.exp(pooled_estimate([one, two], lam).log_mu_hat) == pytest.approx(0.054, rel=1e-12)
    assert math.exp(pooled_estimate([one, two]).log_mu_hat) == pytest.approx(0.52 / 6, rel=1e-12)
    # unbiased: stages of 40 rollouts from q(miss) = 0.3 and 120 from q(miss) = 0.7, linear weights (1/7, 6/7);
    # the mean of mu_hat over 400 repetitions is the exact answer within 4 standard errors and 5 %
    rng = np.random.default_rng(1)
    lam = np.array([1 * 40, 2 * 120], dtype=np.float64)
    lam /= lam.sum()
    est = []
    for _ in range(400):
        stages = []
        for n, q in ((40, ConstantDetector(0.7)), (120, ConstantDetector(0.3))):
            batch = pb.simulate(n, q, pb.target, rng)
            s = StageRollouts(grid)
            s.add(pb, batch, pb.failed(batch), until_failure=True)
            stages.append(s)
        est.append(math.exp(pooled_estimate(stages, lam).log_mu_hat))
    est = np.array(est)
    assert abs(est.mean() - exact) < 4 * est.std(ddof=1) / math.sqrt(est.size)
    assert abs(est.mean() / exact - 1) < 0.05


def test_fit_weights_of_the_stage_mixture_reduce_to_each_samplers_own_weights_for_one_stage(monkeypatch):
    """Right after the failure level is reached the pool holds one stage: the balance heuristic over its samplers
    (``fit_weights = "mixture"``) is then each sampler's own weight, so the fits and the proposals they give are those
    of ``fit_weights = "sampler"`` bit for bit; from the second pooled stage on they differ. With two stages of equal
    size the reweighted steps obey p / (c_1 q_1 + c_2 q_2) <= p / (c_j q_j) = 2 w_own for the stage j that drew a
    rollout."""
    from pemviz.engine.experiment import Experiment
    from pemviz.estimators import ce_fit as ce

    def in_order(steps):  # the held steps' log-weights, rollout by rollout
        order = np.concatenate([part[0] for part in steps.parts])
        return np.concatenate([part[3] for part in steps.parts])[np.argsort(order, kind="stable")]

    calls = []
    reweight = ce.EliteSteps.reweight

    def recorded(self, log_weight):
        before = in_order(self)
        changed = reweight(self, log_weight)
        calls.append((before, in_order(self)))
        return changed

    def run(fit_weights):
        config = ExperimentConfig.of(
            n_stages=4,
            n_per_stage=100,
            n_final=10,
            ce_epochs=50,
            pretrain_epochs=50,
            smoothing_at_failure=1.0,
            final_smoothing=None,
            fit_weights=fit_weights,
        )
        return Experiment(config, problem=build_problem("main")).run().stages

    sampler = run("sampler")
    monkeypatch.setattr(ce.EliteSteps, "reweight", recorded)
    mixture = run("mixture")
    first = next(s.stage for s in mixture if s.kind == "ce" and s.gamma == 0.0)  # the pool's first stage
    np.testing.assert_array_equal([s.gamma for s in mixture[: first + 1]], [s.gamma for s in sampler[: first + 1]])
    assert first == 2
    for a, b in zip(mixture[: first + 1], sampler[: first + 1], strict=False):  # one stage in the pool: the same fits
        np.testing.assert_array_equal(a.proposal_curve, b.proposal_curve)
    assert np.nanmax(np.abs(mixture[first + 1].proposal_curve - sampler[first + 1].proposal_curve)) > 1e-3
    before, after = calls[0]  # the first reweight: two pooled stages of 100 rollouts
    assert after.size > 100 and np.isfinite(after).all() and np.isfinite(before).all()
    assert np.all(after <= before + math.log(2.0) + 1e-9)
    assert np.max(np.abs(after - before)) > 0.1  # the second stage's samplers change the weights


@pytest.mark.parametrize("n_stages, field, alpha", [(3, "smoothing_at_failure", 1.5), (3, "final_smoothing", 0.5)])
def test_the_first_fit_at_the_failure_level_raises_its_weights_to_its_alpha(monkeypatch, n_stages, field, alpha):
    """The fits at the failure level weigh each failure w^alpha: alpha = ``smoothing_at_failure`` (Renyi order), or
    ``final_smoothing`` when the stage is the last. Until the first fit that uses it every rollout is the same as
    with alpha = 1, so with the same seed the fits before it see the same weights and it sees alpha times theirs (up
    to the constant the held weights are relative to)."""
    from pemviz.engine.experiment import Experiment
    from pemviz.estimators import ce_fit as ce

    def fitted_log_weights(**fields):
        calls = []
        fit = ce.EliteSteps.fit

        def recorded(self, proposal, options):
            log_w = self.arrays()[2]
            calls.append(log_w - log_w.max())
            return fit(self, proposal, options)

        monkeypatch.setattr(ce.EliteSteps, "fit", recorded)
        config = ExperimentConfig.of(**{**SMALL_RUN, "n_stages": n_stages, **fields})
        Experiment(config, problem=build_problem("main")).run()
        monkeypatch.undo()
        return calls

    plain = fitted_log_weights(smoothing_at_failure=1.0, final_smoothing=None)
    other = {"final_smoothing": None} if field == "smoothing_at_failure" else {"smoothing_at_failure": 1.0}
    raised = fitted_log_weights(**{field: alpha, **other})
    # alpha's first fit
    first = next(k for k, (a, b) in enumerate(zip(raised, plain, strict=False)) if not np.array_equal(a, b))
    assert first >= 1  # stage 1 is below the failure level: alpha = smoothing in both runs
    assert plain[first].size > 50 and np.ptp(plain[first]) > 1.0
    np.testing.assert_allclose(raised[first], alpha * plain[first], rtol=0, atol=1e-9)


def test_fit_weights_are_checked():
    from pemviz.config import ConfigError

    with pytest.raises(ConfigError, match="fit_weights = 'bogus' is invalid: use one of mixture, sampler"):
        ExperimentConfig.of(fit_weights="bogus")
    with pytest.raises(ConfigError, match="'mixture' weighs the failures of fit_all_failures"):
        ExperimentConfig.of(fit_all_failures=False)
    sampler = ExperimentConfig.of(fit_all_failures=False, fit_weights="sampler", final_smoothing=None)
    assert sampler.adaptive.fit_weights == "sampler"
    with pytest.raises(ConfigError, match="final_smoothing = 1.0 is invalid: a last fit of its own needs fit_weights"):
        ExperimentConfig.of(fit_all_failures=False, fit_weights="sampler")
    with pytest.raises(
        ConfigError, match=r"smoothing_at_failure = 2.5 is invalid: .* must be none or a number in \(0, 2\]"
    ):
        ExperimentConfig.of(smoothing_at_failure=2.5)
    with pytest.raises(ConfigError, match=r"final_smoothing = 0 is invalid: .* must be none or a number in \(0, 2\]"):
        ExperimentConfig.of(final_smoothing=0)


@pytest.mark.parametrize("pool_weights, power", [("quadratic", 2), ("linear", 1), ("rollouts", 0)])
def test_pool_weights_count_the_jth_pooled_stage_by_j_to_the_power_times_its_rollouts(pool_weights, power):
    # K = 4 stages of 50 and N_e = 100 on main: the pool starts once a stage reaches gamma = 0; the run's mu_hat must
    # be sum_j lambda_j mu_hat_j over the pooled stages' own estimates, lambda_j = j^power n_j / sum_i i^power n_i
    # (Portier & Delyon 2018), with the final batch's n_j = 100
    from pemviz.engine.experiment import Experiment

    cfg = ExperimentConfig.of(**{**SMALL_RUN, "n_stages": 4, "seed": 0, "pool_weights": pool_weights})
    done = Experiment(cfg, problem=build_problem("main")).run()
    by_stage = {s.stage: s.estimate for s in done.stages}
    used = done.final.stages_used
    n = np.array([by_stage[k].n for k in used], dtype=np.float64)
    assert len(used) >= 2 and n[-1] == 100 and done.final.estimate.n == n.sum()
    lam = np.arange(1, n.size + 1) ** power * n
    mu = sum(w / lam.sum() * by_stage[k].mu_hat for w, k in zip(lam, used, strict=False))
    assert done.final.estimate.mu_hat == pytest.approx(mu, rel=1e-12)
