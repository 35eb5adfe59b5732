"""The estimate's interval, Pareto k-hat and verdict against closed forms and known distributions."""

from __future__ import annotations

import math

import numpy as np
import pemviz.core.estimate as estimate_module
import pytest
from pemviz.core.confidence import CI_LEVEL
from pemviz.core.diagnostics import effective_sample_size, fit_generalized_pareto, pareto_khat
from pemviz.core.estimate import KHAT_UNRELIABLE, estimate, relative_error


def _is(log_w: np.ndarray, failed: np.ndarray):
    """The estimate of distinct rollouts (each its own log p) with these weights."""
    return estimate(log_w, failed, -np.arange(log_w.size, dtype=float))


def test_zero_failures_of_plain_monte_carlo_give_the_rule_of_three_bound():
    e = _is(np.zeros(10_000), np.zeros(10_000, bool))
    assert e.verdict == "unreliable" and "rule of three" in e.reason
    assert e.log_ci == (-math.inf, pytest.approx(math.log(3e-4)))
    assert e.covers(math.log(1e-15)) and not e.covers(math.log(1e-3))


def test_zero_failures_under_importance_sampling_bound_nothing():
    e = _is(np.full(100, -3.0), np.zeros(100, bool))
    assert e.verdict == "unreliable" and "bounds nothing" in e.reason
    assert e.log_ci == (-math.inf, 0.0)


def test_a_mean_weight_above_one_is_a_probability_of_one_inside_its_interval():
    """Every rollout fails with weights of mean 1.05 (a scene that always fails, drawn from a proposal): the mean is
    cut at 1, as its interval is; it printed ``mu_hat = 1.008e+00, 95% CI [9.49e-01, 1.00e+00]``."""
    e = _is(np.log([1.2, 1.1, 0.9, 1.0] * 50), np.ones(200, bool))
    assert e.log_mu_hat == 0.0 and e.mu_hat == 1.0 and e.log_ci[1] == 0.0
    assert e.log_ci[0] == pytest.approx(math.log(0.99), abs=0.05) and e.covers(0.0)
    below = _is(np.log([1.0, 0.8] * 50), np.ones(100, bool))  # a mean below 1 is kept as it is: 0.9
    assert below.log_mu_hat == pytest.approx(math.log(0.9), rel=1e-12)


def test_plain_monte_carlo_interval_is_clopper_pearson():
    # 5 failures in 100: the exact binomial interval [0.01643, 0.11284] (Clopper & Pearson 1934 tables)
    failed = np.zeros(100, bool)
    failed[:5] = True
    e = _is(np.zeros(100), failed)
    assert math.exp(e.log_ci[0]) == pytest.approx(0.01643, abs=5e-5)
    assert math.exp(e.log_ci[1]) == pytest.approx(0.11284, abs=5e-5)
    assert e.verdict == "doubtful" and e.reason == "only 5 failures"


def test_clopper_pearson_bad_counts_are_one_clear_error():
    from pemviz.core.confidence import clopper_pearson

    for k, n, level in ((-1, 10, 0.95), (11, 10, 0.95), (0, 0, 0.95), (1, 10, 1.0)):
        with pytest.raises(ValueError, match="clopper_pearson: need n >= 1"):
            clopper_pearson(k, n, level)
    assert clopper_pearson(0, 10) == (0.0, pytest.approx(0.30849710781876, rel=1e-12))  # 1 - 0.025^(1/10)


def test_equal_weights_interval_is_the_log_scale_interval_of_a_binomial_mean():
    # y_i = w 1[fail_i], 30 failures in 100 with weight 1e-20: mean 3e-21, sd/mean = sqrt((1 - 0.3) / 0.3 * 100 / 99)
    failed = np.arange(100) < 30
    e = _is(np.full(100, math.log(1e-20)), failed)
    rel_se = math.sqrt(0.7 / 0.3 * 100 / 99) / 10
    t975 = 1.9842169515086827  # Student t, 99 degrees of freedom
    assert e.mu_hat == pytest.approx(3e-21, rel=1e-12)
    assert e.log_ci[0] == pytest.approx(math.log(3e-21) - t975 * rel_se, abs=1e-9)
    # the upper end: the tail quantile at k-hat 0 (2.01, pemviz.core.confidence.TAIL_QUANTILES), above t_99
    assert e.log_ci[1] == pytest.approx(math.log(3e-21) + 2.01 * rel_se, abs=1e-9)
    assert e.khat == 0.0  # every failure weight equal: a flat tail
    assert e.verdict == "reliable"  # 30 distinct rollouts, equal weights: as a zero-variance proposal draws them


def test_failures_that_are_few_rollouts_drawn_again_and_again_are_not_reliable():
    # a proposal collapsed onto 2 paths (the paper's sampler, seed 0): 91 failures, equal weights within each path,
    # an ESS of 80, k-hat 0 -- and a number 10^9 too low; the weights alone look perfect
    log_w = np.where(np.arange(100) % 2 == 0, -57.3, -54.9)
    log_p = np.where(np.arange(100) % 2 == 0, -60.1, -58.2)
    failed = np.arange(100) < 91
    e = estimate(log_w, failed, log_p)
    assert e.ess > 50 and e.khat == 0.0
    assert e.verdict == "doubtful" and e.reason.startswith("the 91 failures are 2 distinct rollouts")
    assert estimate_module.distinct_failures(log_w[failed], log_p[failed]) == 2
    # the same weights on 91 distinct rollouts (their log p differ) are what a good proposal draws
    assert estimate(log_w, failed, -np.arange(100.0)).verdict == "reliable"


def test_a_nan_weight_is_never_reliable():
    log_w = np.full(100, math.log(1e-20))
    log_w[5] = math.nan  # -inf x 0: an event the PEM cannot make, masked by a product
    e = estimate(log_w, np.arange(100) < 40, -np.arange(100.0))
    assert e.verdict == "unreliable" and "nan" in e.reason


def test_interval_covers_a_known_probability_in_about_95_percent_of_repetitions():
    # Proposal q = Bernoulli(0.3) for a failure of probability p = 1e-6 under the target: log w = log(p / q) for
    # failures; 2,000 repetitions of N = 200.
    rng = np.random.default_rng(0)
    p, q, n = 1e-6, 0.3, 200
    covered = sum(_is(np.full(n, math.log(p / q)), rng.random(n) < q).covers(math.log(p)) for _ in range(2000))
    assert 0.93 <= covered / 2000 <= 0.97, covered


def test_khat_recovers_the_shape_of_a_generalized_pareto_tail():
    # GPD(k) samples by inversion: x = ((1 - u)^(-k) - 1) / k; PSIS fits the tail of 10,000 of them.
    rng = np.random.default_rng(1)
    for k in (0.3, 0.9):
        x = ((1.0 - rng.random(10_000)) ** (-k) - 1.0) / k
        assert pareto_khat(np.log(x)) == pytest.approx(k, abs=0.12)


def test_a_tail_of_a_few_repeated_weights_is_bounded_and_reliable():
    # Pooled stages on a problem where each stage gives all its failures one weight (the toy under its
    # zero-variance proposal): 900 failures in 3 clusters of weights 1e-21 * (1.2, 1.0, 0.9). The variance is
    # finite; a Pareto fit to repeated values gives a meaningless k-hat (-4.7 here, +4.4 on a pooled toy run).
    rng = np.random.default_rng(3)
    w = np.repeat([1.2e-21, 1.0e-21, 0.9e-21], [40, 400, 1360])  # the top 127 span two clusters
    log_w = np.log(w) + rng.normal(0.0, 1e-12, 1800)
    failed = np.arange(1800) < 900
    assert pareto_khat(np.where(failed, log_w, -np.inf)) == 0.0
    e = _is(log_w, failed)
    assert e.verdict == "reliable" and e.ess > 800


def test_heavy_tailed_weights_are_unreliable_with_their_khat():
    rng = np.random.default_rng(2)
    x = ((1.0 - rng.random(400)) ** -1.2 - 1.0) / 1.2  # k = 1.2: infinite mean
    e = _is(np.log(x) - 40.0, np.ones(400, bool))
    assert e.khat > KHAT_UNRELIABLE
    assert e.verdict == "unreliable" and e.reason.startswith(f"k-hat {e.khat:.2f} > 0.7")


def test_a_low_ess_is_doubtful_and_weights_far_above_one_on_average_are_unreliable():
    log_w = np.full(100, -40.0)
    log_w[:3] = -30.0  # three weights carry everything: ESS ~ 3
    e = _is(log_w, np.ones(100, bool))
    assert e.verdict in ("doubtful", "unreliable") and e.verdict != "reliable"
    bad = _is(np.full(100, math.log(1e8)), np.arange(100) < 50)  # mean weight 1e8: not a proposal's weights
    assert bad.verdict == "unreliable" and "mean importance weight" in bad.reason
    assert bad.log_mu_hat == 0.0  # a mean of 5e7 cut at 1: the reason names the mean weight


def test_summary_line_names_the_exact_answer_and_whether_it_is_covered():
    failed = np.arange(100) < 30
    e = _is(np.full(100, math.log(1e-20)), failed)
    line = e.summary(math.log(3.3e-21))
    assert f"{CI_LEVEL:.0%} CI" in line and "reliable" in line
    assert "exact 3.300e-21 (relative error 0.0909, inside the interval)" in line
    assert relative_error(-math.inf, 0.0) == 1.0


def test_effective_sample_size_counts_equal_weights_and_ignores_the_scale_of_the_logs():
    assert effective_sample_size(np.full(8, -700.0)) == pytest.approx(8.0, rel=1e-12)  # 8 equal weights
    # weights 1, 1, 2 (times e^-900): (1 + 1 + 2)^2 / (1 + 1 + 4) = 16 / 6
    assert effective_sample_size(np.log([1.0, 1.0, 2.0]) - 900.0) == pytest.approx(16.0 / 6.0, rel=1e-12)
    assert effective_sample_size(np.array([0.0, -np.inf, -np.inf])) == 1.0  # zero weights count for nothing
    assert effective_sample_size(np.full(3, -np.inf)) == 0.0  # no weight: nothing counts (was nan)
    assert math.isnan(effective_sample_size(np.array([0.0, np.nan])))


def test_failures_that_all_weigh_zero_are_unreliable_with_ess_0_and_the_reason():
    from pemviz.core.estimate import estimate

    log_w = np.array([-np.inf, -np.inf, 0.0, -1.0])
    e = estimate(log_w, np.array([True, True, False, False]), np.full(4, -np.inf))
    assert e.ess == 0.0 and e.mu_hat == 0.0 and e.n_failures == 2
    assert e.verdict == "unreliable" and e.reason.startswith("every one of the 2 failures weighs 0")


@pytest.mark.parametrize("k", [-0.4, 0.0, 0.3, 0.9, 1.6])
@pytest.mark.parametrize("n", [5, 60, 900])
def test_the_generalized_pareto_fit_is_pyros(k, n):
    # pemviz's numpy fit (Zhang & Stephens 2009 with PSIS's prior) against pyro's, the oracle, on GPD(k) samples
    torch = pytest.importorskip("torch")
    from pyro.ops.stats import fit_generalized_pareto as pyro_fit

    rng = np.random.default_rng(int(10 * k) + n)
    u = rng.random(n)
    x = -np.log1p(-u) if k == 0.0 else ((1.0 - u) ** (-k) - 1.0) / k
    np.testing.assert_allclose(fit_generalized_pareto(x), pyro_fit(torch.as_tensor(x)), rtol=1e-9, atol=1e-12)
    with pytest.raises(ValueError, match="x must be 1-D with at least one value"):
        fit_generalized_pareto(np.zeros(0))


def test_markov_lower_bound_by_hand_and_its_coverage_under_a_heavy_tail():
    """One run of 20 p gives p >= 0.05 x 20 = 1 (hand); two runs alpha^(1/2) x their geometric mean. Over 20,000
    replicates of 10 runs of a lognormal estimator of mean 1 whose sd of logs is 2.5 (heavy: a few runs carry the
    mean), the bound exceeds the true mean 1 in at most 5 % (Markov's inequality makes it conservative: measured in
    none of the 20,000), while a normal interval on the same runs misses the mean in 60 %."""
    from pemviz.core.confidence import markov_lower_bound

    assert markov_lower_bound(np.log([20.0])) == pytest.approx(0.0, abs=1e-12)  # log 1
    assert markov_lower_bound(np.log([2.0, 8.0])) == pytest.approx(math.log(math.sqrt(0.05) * 4.0), rel=1e-12)
    assert markov_lower_bound(np.array([-1.0, -np.inf])) == -math.inf and markov_lower_bound(np.array([])) == -math.inf
    with pytest.raises(ValueError, match="alpha must be in"):
        markov_lower_bound(np.zeros(2), alpha=1.0)
    rng = np.random.default_rng(0)
    s = 2.5
    logs = rng.normal(-s * s / 2, s, size=(20_000, 10))  # E[exp] = 1
    bounds = np.array([markov_lower_bound(row) for row in logs])
    assert np.mean(bounds > 0.0) <= 0.05
    x = np.exp(logs)
    lower = x.mean(axis=1) - 1.96 * x.std(axis=1, ddof=1) / math.sqrt(10)
    upper = x.mean(axis=1) + 1.96 * x.std(axis=1, ddof=1) / math.sqrt(10)
    assert np.mean((lower > 1.0) | (upper < 1.0)) > 0.2  # the normal interval does not hold here
