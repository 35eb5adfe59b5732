"""Exact answers (pemviz.scenarios.braking.truth) against independent truth: brute-force enumeration, highway-env,
Monte Carlo."""

from __future__ import annotations

import itertools
import math

import numpy as np
import pytest
from pemviz.core.detectors import ConstantDetector, WindowDetector
from pemviz.core.estimate import estimate
from pemviz.scenarios import simulate
from pemviz.scenarios.braking.simulator import BrakingParams, BrakingScenario, braking_replay, braking_step, lead_speeds
from pemviz.scenarios.braking.truth import _relaxed_step, braking_exact, branching_start, miss_bound
from pemviz.scenarios.braking.truth_latched import latched_log_failure_probability
from pemviz.scenarios.toy import ToyBraking, ToyParams
from pemviz.scenarios.toy.problem import toy_problem
from pemviz.scenarios.toy.simulator import simulate_toy, toy_log_failure_probability
from scipy.special import log_expit


@pytest.fixture(scope="module")
def pem():
    from pemviz.pem import load_pem

    return load_pem()


# -- toy ----------------------------------------------------------------------------------------------------
def test_toy_closed_form_gives_the_spec_numbers():
    assert toy_log_failure_probability(ToyParams(100, 50, 30, 0.9)) == pytest.approx(math.log(1e-21), rel=1e-12)
    assert toy_log_failure_probability(ToyParams(10, 5, 3, 0.9)) == pytest.approx(math.log(1e-3), rel=1e-12)
    assert toy_log_failure_probability(ToyParams(100, 39, 30, 0.999)) == pytest.approx(math.log(1e-30), rel=1e-9)


def test_toy_closed_form_with_distance_dependent_p_equals_brute_force_enumeration():
    # every detection sequence of a 7-step toy, probabilities multiplied by hand, failing ones summed
    params = ToyParams(7, 4, 2, lambda d: 0.5 + 0.05 * d)
    total = 0.0
    for seq in itertools.product((False, True), repeat=params.steps):
        car, prob = ToyBraking(params), 1.0
        failed = False
        for a in seq:
            d = car.distance
            failed |= d < params.safe
            p = 0.5 + 0.05 * d
            prob *= p if a else 1 - p
            car.step(a)
        total += prob if failed else 0.0
    exact = (1 - 0.7) * (1 - 0.65) * (1 - 0.6)  # misses at distances 4, 3, 2
    assert total == pytest.approx(exact, rel=1e-12)
    assert math.exp(toy_log_failure_probability(params)) == pytest.approx(exact, rel=1e-12)


def test_toy_vectorised_simulator_equals_the_black_box_one():
    params = ToyParams(12, 6, 3, lambda d: 0.6 + 0.02 * d)
    pb = toy_problem(params)
    a = simulate_toy(params, 40, ConstantDetector(0.4), pb.target, np.random.default_rng(3))
    b = simulate(
        lambda: ToyBraking(params), 40, ConstantDetector(0.4), pb.target, np.random.default_rng(3), params.steps
    )
    for name in ("observations", "detected", "log_p", "log_q"):
        np.testing.assert_array_equal(getattr(a, name), getattr(b, name))


def test_toy_importance_sampling_with_naive_detector_recovers_1e_minus_3():
    params = ToyParams(10, 5, 3, 0.9)
    pb = toy_problem(params)
    # 50 % inside the braking window (distances <= 5), the toy's own p outside: every failing rollout
    # has the weight (0.1 / 0.5)^3, so the estimate is 0.008 x the failure fraction (0.5^3 in expectation)
    sampler = WindowDetector(ConstantDetector(0.5), pb.target, pb.window)
    batch = pb.simulate(20000, sampler, pb.target, np.random.default_rng(0))
    e = estimate(batch.log_weight(), pb.failed(batch), batch.log_p.sum(axis=1))
    assert e.n_failures == pytest.approx(20000 / 8, rel=0.08)
    assert e.mu_hat == pytest.approx(1e-3, rel=0.08)
    assert e.ess == pytest.approx(e.n_failures, rel=1e-9)


def test_toy_rejects_bad_parameters():
    with pytest.raises(ValueError, match="safe <= braking < total"):
        ToyParams(10, 12, 3)
    with pytest.raises(ValueError, match="p_detect"):
        ToyParams(10, 5, 3, 1.0)
    with pytest.raises(ValueError, match="n_steps"):
        ToyParams(10, 5, 3, 0.9, n_steps=5)


# -- braking dynamics ----------------------------------------------------------------------------------------
def test_replay_on_the_gap_matches_highway_env_rollouts():
    p = BrakingParams()
    rng = np.random.default_rng(0)
    detected = rng.random((3, p.n_steps)) < 0.6
    detected[0] = True
    gaps = braking_replay(p, detected)
    for k in range(3):
        sim, ref = BrakingScenario(p), []
        for t in range(p.n_steps):
            ref.append(sim.gap_m)
            sim.step(bool(detected[k, t]))
        np.testing.assert_allclose(gaps[k], ref, atol=1e-9)
    assert gaps[0].min() == pytest.approx(6.0913, abs=1e-3)  # always detected: stops ~6.1 m short


def test_branching_starts_at_step_36_inside_10_m():
    s = branching_start(BrakingParams())
    assert s.step == 36 and 9.8 < s.gap_m < 10.0 and not s.pending
    assert lead_speeds(BrakingParams())[32:].max() < 1e-9  # the lead has stopped before the ego is inside 10 m


def test_relaxed_step_is_monotone_and_dominates_the_true_step():
    # the claims behind MissBound: the relaxed step's next speed is non-decreasing and its next gap
    # non-increasing in the speed, and its next speed is at least the true one whatever the integral.
    p = BrakingParams()
    v = np.linspace(0.0, 9.0, 3001)
    gap = np.full(v.size, 6.0)
    for pending in (False, True):
        b = np.full(v.size, pending)
        for detected in (False, True):
            rg, rv, _ = _relaxed_step(p, 0.0, gap, v, b, np.array(detected))
            assert np.all(np.diff(rv) >= -1e-12) and np.all(np.diff(rg) <= 1e-12)
            for integral in (-1.0, 0.0, 5.0, 13.5):
                v2 = braking_step(p, 0.0, gap, v, np.full(v.size, integral), b, np.array(detected))[1]
                assert np.all(rv >= v2 - 1e-12)
    # and the true step is not monotone (PID brake above 7.5 m/s): the relaxation is needed
    v2 = braking_step(p, 0.0, gap, v, np.zeros(v.size), np.zeros(v.size, bool), np.array(False))[1]
    assert np.diff(v2).min() < -1e-4


def test_miss_bound_never_exceeds_the_misses_of_crashing_rollouts(pem):
    p = BrakingParams()
    start = branching_start(p)
    bound = miss_bound(p, start, 161)
    rng = np.random.default_rng(1)
    detected = rng.random((4000, p.n_steps)) < 0.55
    gaps = braking_replay(p, detected)
    crash_step = np.where((gaps < 2).any(axis=1), (gaps < 2).argmax(axis=1), -1)
    assert (crash_step > 0).sum() > 500
    vl = lead_speeds(p)
    g = np.full(4000, p.gap0_m)
    v, i, b = np.full(4000, p.ego_speed0_mps), np.zeros(4000), np.zeros(4000, bool)
    for t in range(p.n_steps - 1):
        if t >= start.step:
            # misses still to come before the crash, for rollouts that crash later
            live = crash_step > t
            later = (~detected[:, t:]) & (np.arange(t, p.n_steps)[None, :] < crash_step[:, None])
            need = bound(t, g, v, b)
            assert np.all(later.sum(axis=1)[live] >= need[live])
        g, v, i, b = braking_step(p, vl[t], g, v, i, b, detected[:, t])
    assert int(bound(start.step, np.array([start.gap_m]), np.array([start.speed_mps]), np.array([False]))[0]) >= 5


# -- latched and main truths ----------------------------------------------------------------------------------
def test_latched_truth_is_the_product_of_misses_over_its_window(pem):
    lt = latched_log_failure_probability(pem.logit_at_gap)
    assert lt.window_exact and lt.first_step == 36
    gaps = braking_replay(BrakingParams(latched_brake=True), np.zeros((1, 100), bool))[0]
    by_hand = float(np.sum(log_expit(-pem.logit_at_gap(gaps[lt.first_step : lt.last_step + 1]))))
    assert lt.log_p_fail == pytest.approx(by_hand, abs=1e-9)
    assert 1e-25 < lt.p_fail < 1e-22


def test_enumeration_agrees_with_the_latched_closed_form(pem):
    lt = latched_log_failure_probability(pem.logit_at_gap)
    ex = braking_exact(pem.logit_at_gap, BrakingParams(latched_brake=True), log_prune=-75.0, bound_grid=161)
    assert ex.relative_width < 1e-4
    assert ex.log_p_fail == pytest.approx(lt.log_p_fail, abs=1e-4)


def test_enumerated_main_truth_agrees_with_importance_sampling(pem):
    # Independent check: a fixed 40 %-miss detector inside 10 m, weights up to the crash step, 40,000
    # rollouts of the batched simulator (relative standard error ~7 %).
    from pemviz.scenarios.braking.problem import braking_problem

    ex = braking_exact(pem.logit_at_gap, BrakingParams(), log_prune=-50.0, bound_grid=201)
    assert ex.relative_width < 0.05
    assert 1e-16 < ex.p_fail < 1e-14
    pb = braking_problem(pem)
    # the answer kept for the shipped PEM (from the -58 nats refinement) lies inside this coarser bracket
    assert ex.log_p_fail <= pb.exact_log_p <= ex.log_p_fail_upper
    assert braking_problem(pem, BrakingParams(latched_brake=True)).exact_log_p == pytest.approx(
        latched_log_failure_probability(pem.logit_at_gap).log_p_fail, abs=1e-12
    )
    batch = pb.simulate(
        40000, WindowDetector(ConstantDetector(0.6), pb.target, 10.0), pb.target, np.random.default_rng(0)
    )
    crash = batch.signal("gap_m") < 2.0
    first = np.where(crash.any(axis=1), crash.argmax(axis=1), batch.n_steps - 1)
    upto = np.arange(batch.n_steps)[None, :] < first[:, None]
    log_w = ((batch.log_p - batch.log_q) * upto).sum(axis=1)
    e = estimate(log_w, crash.any(axis=1), batch.log_p.sum(axis=1))
    assert e.mu_hat == pytest.approx(ex.p_fail, rel=0.25)
