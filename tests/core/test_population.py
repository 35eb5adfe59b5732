"""The failure population: each failure's share of mu_hat against the estimate it comes from, the groups' shares,
and the braking scenario's last saving step against the one-rollout counterfactual."""

from __future__ import annotations

import math

import numpy as np
import pytest
from pemviz.core.population import failure_groups, failure_shares
from pemviz.estimators.pooling import pool
from pemviz.scenarios.braking.failures import counterfactual, last_saving_steps


def test_shares_by_hand_one_stage():
    # weights 1, 3 (failures) and 10 (safe): mu_hat = 4 / 3, shares 1/4 and 3/4, the larger first
    lw = np.log([1.0, 10.0, 3.0])
    s = failure_shares([(5, lw, np.array([True, False, True]), np.zeros(3))])
    assert s.stage.tolist() == [5, 5] and s.index.tolist() == [2, 0]
    np.testing.assert_allclose(s.share(), [0.75, 0.25], rtol=1e-15)
    assert s.position(5, 0) == 1 and s.position(5, 1) is None


def test_shares_reproduce_the_pooled_estimate_with_stage_weights():
    # two stages of 4 and 2 rollouts, lambda = (0.3, 0.7): each term is w lambda_k N / n_k, mu_hat their mean
    rng = np.random.default_rng(3)
    parts = [
        (1, rng.normal(-30, 2, 4), np.array([True, True, False, True]), np.zeros(4)),
        (2, rng.normal(-30, 2, 2), np.array([True, False]), np.zeros(2)),
    ]
    lam = np.array([0.3, 0.7])
    s = failure_shares(parts, lam)
    mu = pool([p[1:] for p in parts], lam)
    by_hand = (0.3 * 6 / 4 * np.exp(parts[0][1][[0, 1, 3]]).sum() + 0.7 * 6 / 2 * np.exp(parts[1][1][0])) / 6
    assert math.isclose(math.exp(mu.log_mu_hat), by_hand, rel_tol=1e-12)
    from scipy.special import logsumexp

    assert math.isclose(float(logsumexp(s.log_weight)) - math.log(6), mu.log_mu_hat, rel_tol=1e-13)
    assert math.isclose(float(s.share().sum()), 1.0, rel_tol=1e-14)
    assert np.all(np.diff(s.log_share) <= 0)


def test_no_failure_gives_an_empty_population_and_bad_input_is_named():
    s = failure_shares([(0, np.zeros(3), np.zeros(3, bool), np.zeros(3))])
    assert s.n == 0 and failure_groups(s, []) == []
    with pytest.raises(ValueError, match="stage 0 has arrays of shapes"):
        failure_shares([(0, np.zeros(3), np.zeros(2, bool), np.zeros(3))])
    with pytest.raises(ValueError, match="2 stage weights for 1 stages"):
        failure_shares([(0, np.zeros(3), np.ones(3, bool), np.zeros(3))], np.array([0.5, 0.5]))
    with pytest.raises(ValueError, match="1 keys for 3 failures"):
        failure_groups(failure_shares([(0, np.zeros(3), np.ones(3, bool), np.zeros(3))]), ["a"])


def test_groups_sum_their_members_shares_and_come_largest_first():
    lw = np.log([1.0, 2.0, 3.0, 5.0])  # shares 1/11, 2/11, 3/11, 5/11
    s = failure_shares([(0, lw, np.ones(4, bool), np.zeros(4))])  # ranks: 3, 2, 1, 0
    keys = ["a" if i in (3, 0) else "b" for i in s.index.tolist()]
    g = failure_groups(s, keys, {"a": "first and last"})
    assert [(x.key, x.label, x.count) for x in g] == [("a", "first and last", 2), ("b", "b", 2)]
    assert math.isclose(g[0].share, 6 / 11, rel_tol=1e-14) and math.isclose(g[1].share, 5 / 11, rel_tol=1e-14)
    assert g[0].first == 0 and g[1].first == 1  # each group's largest failure


def test_last_saving_steps_is_the_counterfactual_s_for_failures_and_safe_rollouts():
    rng = np.random.default_rng(0)
    t = 100
    detected = rng.random((60, t)) < 0.9
    for i in range(40):  # long runs of misses that start at different steps: failures of different kinds
        a = 25 + i
        detected[i, a : a + 30 + (i % 7)] = False
    got = last_saving_steps(detected)
    want = []
    for row in detected:
        cf = counterfactual(row)
        want.append(cf.last_saving_step if cf.failed and cf.last_saving_step is not None else -1)
    assert got.tolist() == want
    assert (got >= 0).sum() >= 10 and (got == -1).sum() >= 20  # both cases occur
    with pytest.raises(ValueError, match="must be bool"):
        last_saving_steps(detected[0])
