"""The zero-variance sampler q* built from exact value functions (``research/zero_variance.py``): every rollout fails
with weight exactly mu."""

from __future__ import annotations

import itertools
import math

import numpy as np
import pytest
from pemviz.core.estimate import relative_error
from pemviz.scenarios.braking import truth_latched
from pemviz.scenarios.braking.problem import braking_problem
from pemviz.scenarios.braking.simulator import BrakingParams
from pemviz.scenarios.problems import build_problem
from pemviz.scenarios.toy import ToyBraking, ToyParams
from pemviz.scenarios.toy.problem import toy_problem

from conftest import REPO, load_script

zv = load_script(REPO / "research" / "zero_variance.py")
ShiftedPEM, ToyValue, ZeroVarianceDetector = zv.ShiftedPEM, zv.ToyValue, zv.ZeroVarianceDetector
draw_fixed, latched_value, relative_variance, rollouts_for = (
    zv.draw_fixed,
    zv.latched_value,
    zv.relative_variance,
    zv.rollouts_for,
)


@pytest.fixture(scope="module")
def pem():
    from pemviz.pem import load_pem

    return load_pem()


def assert_zero_variance(problem, sampler, log_mu: float, n: int = 500, seed: int = 3) -> None:
    d = draw_fixed(problem, sampler, n, seed=seed)
    assert d.failed.all()
    np.testing.assert_allclose(d.log_weight, log_mu, rtol=0, atol=1e-11)  # every weight = mu (to 1e-11 nats)
    assert relative_error(d.estimate.log_mu_hat, log_mu) < 1e-9
    assert relative_variance(d.log_weight, d.failed, log_mu) < 1e-18


def test_toy_q_star_draws_only_failures_each_weighted_1e_21():
    params = ToyParams(100, 50, 30, 0.9)
    problem = build_problem("toy")
    assert problem.exact_log_p == pytest.approx(math.log(1e-21), rel=1e-12)
    assert_zero_variance(
        problem, ZeroVarianceDetector(problem.target, ToyValue(params).log_value_next), math.log(1e-21)
    )


def test_toy_q_star_with_distance_dependent_p():
    params = ToyParams(40, 25, 5, lambda d: 0.3 + 0.6 * np.exp(-d / 10.0))
    problem = toy_problem(params)
    log_mu = float(np.sum(np.log1p(-(0.3 + 0.6 * np.exp(-np.arange(5, 26) / 10.0)))))  # misses at 25, 24, ..., 5
    assert_zero_variance(problem, ZeroVarianceDetector(problem.target, ToyValue(params).log_value_next), log_mu)


def test_toy_value_equals_brute_force_enumeration_from_every_state():
    # V(d, moving) of a 6-step toy by summing over every detection sequence from that state
    params = ToyParams(6, 4, 2, lambda d: 0.2 + 0.1 * d)
    value = ToyValue(params)
    for start in range(0, params.total + 1):
        total = 0.0
        n_left = params.total - 1  # enough steps to reach distance safe - 1 from any start
        for seq in itertools.product((False, True), repeat=n_left):
            car, prob, failed = ToyBraking(params), 1.0, False
            car.distance = start
            for a in seq:
                failed |= car.distance < params.safe
                p = 0.2 + 0.1 * car.distance
                prob *= p if a else 1 - p
                car.step(a)
            failed |= car.distance < params.safe
            total += prob if failed else 0.0
        p = 0.2 + 0.1 * start
        log_d, log_m = value.log_value_next(np.array([[float(start), 0.0]]))
        v = p * math.exp(log_d[0]) + (1 - p) * math.exp(log_m[0]) if start >= params.safe else 1.0
        assert v == pytest.approx(total, rel=1e-12, abs=1e-15), start


def test_latched_q_star_draws_only_failures_each_weighted_mu(pem):
    problem = build_problem("latched")
    value = latched_value(pem.logit_at_gap)
    assert value.log_v0 == pytest.approx(problem.exact_log_p, rel=1e-13)
    assert math.exp(problem.exact_log_p) == pytest.approx(3.3048e-24, rel=1e-4)
    assert_zero_variance(problem, ZeroVarianceDetector(problem.target, value.log_value_next), problem.exact_log_p)


@pytest.mark.parametrize("shift", [-6.0, -3.0, 4.0])
def test_latched_q_star_with_a_shifted_pem(pem, shift):
    shifted = ShiftedPEM(pem, shift)
    problem = braking_problem(shifted, BrakingParams(latched_brake=True))
    log_mu = truth_latched.latched_log_failure_probability(shifted.logit_at_gap).log_p_fail
    value = latched_value(shifted.logit_at_gap)
    assert value.log_v0 == pytest.approx(log_mu, rel=1e-13)
    assert_zero_variance(problem, ZeroVarianceDetector(problem.target, value.log_value_next), log_mu, n=200)


def test_relative_variance_of_plain_monte_carlo_is_one_minus_mu_over_mu():
    # weights 1, a failure frequency of exactly mu: mean((1[f] / mu - 1)^2) = mu (1/mu - 1)^2 + (1 - mu) = (1 - mu) / mu
    failed = np.zeros(1000, bool)
    failed[[7, 500]] = True
    assert relative_variance(np.zeros(1000), failed, math.log(2e-3)) == pytest.approx((1 - 2e-3) / 2e-3, rel=1e-12)
    assert rollouts_for(0.2, 1000) == pytest.approx(4000.0)
    assert rollouts_for(0.0, 1000) == 0.0


def poor_value(log_value_next, miss_gap: float, temper: float = 0.7):
    """A deliberately wrong V: every finite log V scaled by ``temper``, and an action that cannot fail given the
    log V of the other minus ``miss_gap`` nats (so the proposal also draws rollouts that cannot fail)."""

    def wrong(obs: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        log_d, log_m = log_value_next(obs)
        return (
            np.where(np.isfinite(log_d), temper * log_d, log_m - miss_gap),
            np.where(np.isfinite(log_m), temper * log_m, log_d - miss_gap),
        )

    return wrong


def assert_unbiased(problem, log_value_next, log_mu: float, n: int, seed: int = 1) -> float:
    """The V-tilted sampler's mean of w 1[fail] / mu is 1 within 5 standard errors; returns its relative variance."""
    d = draw_fixed(problem, ZeroVarianceDetector(problem.target, log_value_next), n, seed=seed)
    ratio = np.where(d.failed, np.exp(np.where(d.failed, d.log_weight, 0.0) - log_mu), 0.0)
    assert abs(ratio.mean() - 1.0) < 5.0 * ratio.std() / math.sqrt(n), (ratio.mean(), ratio.std())
    return relative_variance(d.log_weight, d.failed, log_mu)


@pytest.mark.parametrize("miss_gap, relvar_range", [(1.0, (2.0, 20.0)), (3.0, (0.1, 2.0))])
def test_toy_v_tilted_sampler_with_a_poor_v_stays_unbiased(miss_gap, relvar_range):
    # the tilt q(a | s) = p(a | s) V(s'_a) / sum: any V keeps the weights p / q exact, so a wrong V costs only
    # variance (Kollman et al. 1999; L'Ecuyer & Tuffin 2008); exact mu = prod over d = 5..25 of (1 - p(d))
    params = ToyParams(40, 25, 5, lambda d: 0.3 + 0.6 * np.exp(-d / 10.0))
    log_mu = float(np.sum(np.log1p(-(0.3 + 0.6 * np.exp(-np.arange(5, 26) / 10.0)))))
    relvar = assert_unbiased(
        toy_problem(params), poor_value(ToyValue(params).log_value_next, miss_gap), log_mu, n=20000
    )
    assert relvar_range[0] < relvar < relvar_range[1]  # the V is poor: far from q*'s 0, below plain MC's 6e5


def test_latched_v_tilted_sampler_with_a_poor_v_stays_unbiased(pem):
    problem = build_problem("latched")
    value = latched_value(pem.logit_at_gap)
    relvar = assert_unbiased(problem, poor_value(value.log_value_next, 3.0), problem.exact_log_p, n=10000)
    assert 5.0 < relvar < 200.0  # q* gives 0; plain Monte Carlo about 3e23
