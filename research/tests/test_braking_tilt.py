"""The braking scene's tilted proposal (``research/braking_tilt.py``) and the exact committor of a state
(:func:`pemviz.scenarios.braking.truth.braking_exact` from a given state).

- The exact committor of a state 10-12 steps before the end, by enumeration, equals a plain recursion over the
  detector's outcomes (each stepped by the scene's dynamics), and from the branching start it is the whole answer.
- One look-ahead step gives both outcomes' next states: with the actuation lag a detection changes the pending brake
  only (checked against the dynamics, latched and not).
- The grid committor is 1 below the crash gap, 0 at step T (nothing is seen after the last step), and within x20 of
  the exact answer at the branching start (the grid smears V's jumps: x0.08 measured).
- The tilted estimator is unbiased against the exact 1.984e-15 (40 seeds), its weights p / q are bounded per step by
  1 / eps, the same seed gives the same rollouts for any chunk size, a second run reuses the solve and says so, and
  its committor scores adaptive multilevel splitting with the solve counted.
"""

from __future__ import annotations

import dataclasses
import math

import numpy as np
import pytest
from pemviz.config import ExperimentConfig
from pemviz.core.detectors import PEMDetector
from pemviz.engine.experiment import Experiment
from pemviz.pem import load_pem
from pemviz.scenarios.braking.simulator import BrakingParams, braking_step, lead_speeds
from pemviz.scenarios.braking.truth import BrakingStart, braking_exact, branching_start, exact_bound
from pemviz.scenarios.problems import build_problem
from scipy.special import log_expit, logsumexp

from conftest import REPO, load_script

tilt_module = load_script(REPO / "research" / "braking_tilt.py")
LOG_V_FLOOR, TILT_EPS, BrakingTilt = tilt_module.LOG_V_FLOOR, tilt_module.TILT_EPS, tilt_module.BrakingTilt
BrakingTiltDetector, draw_tilted = tilt_module.BrakingTiltDetector, tilt_module.draw_tilted


def _tilted_main():
    """The braking problem ``main`` with this tilt attached (:func:`tilted_problem`)."""
    return tilt_module.tilted_problem(build_problem("main"), load_pem())


@pytest.fixture(scope="module")
def pem():
    return load_pem()


@pytest.fixture(scope="module")
def committor(pem):
    return tilt_module.solve_committor(BrakingParams(), pem.logit_at_gap)


def _committor_by_recursion(pem, p: BrakingParams, t: int, g: float, v: float, i: float, b: bool) -> float:
    """P(a gap below the crash gap at a step t..T-1 | the state at t), by plain recursion over the detector's outcomes
    (one outcome beyond the braking distance), each stepped by :func:`braking_step`: an oracle independent of the
    enumeration's vectorised bookkeeping and bounds."""
    if g < p.crash_gap_m:
        return 1.0
    if t >= p.n_steps - 1:
        return 0.0
    inside = g < p.braking_distance_m
    total = 0.0
    for a in (False, True) if inside else (False,):
        prob = math.exp(float(log_expit((1 if a else -1) * pem.logit_at_gap(np.array([g]))[0]))) if inside else 1.0
        nxt = braking_step(
            p, float(lead_speeds(p)[t]), np.array([g]), np.array([v]), np.array([i]), np.array([b]), np.array([a])
        )
        total += prob * _committor_by_recursion(pem, p, t + 1, *(x[0].item() for x in nxt))
    return total


def test_the_exact_committor_of_a_late_state_is_the_recursion_over_its_detections(pem):
    """From states 10-12 steps before the end (V between 1e-17 and 0.06), the enumeration from the state equals the
    recursion to 1e-9 relative; from the branching start it is the whole answer."""
    p = BrakingParams()
    start = branching_start(p)
    bound = exact_bound(p, start, 401)
    cases = (
        (88, 5.0, 7.0, False),
        (88, 5.5, 7.0, True),
        (88, 5.5, 6.0, False),
        (90, 4.0, 6.0, True),
        (90, 6.0, 7.0, False),
    )
    values = []
    for t, gap, speed, pending in cases:
        hand = _committor_by_recursion(pem, p, t, gap, speed, -0.2, pending)
        r = braking_exact(
            pem.logit_at_gap, p, bound=bound, start=BrakingStart(t, gap, speed, -0.2, pending), log_prune=-200.0
        )
        values.append(hand)
        assert math.exp(r.log_p_fail) == pytest.approx(hand, rel=1e-9, abs=1e-300)
    assert 1e-17 < min(v for v in values if v > 0) and max(values) < 0.1 and 0.0 in values
    whole = braking_exact(pem.logit_at_gap, p, bound=bound, start=start)
    assert whole.log_p_fail == braking_exact(pem.logit_at_gap, p, bound=bound).log_p_fail


@pytest.mark.parametrize("latched", [False, True])
def test_a_detection_changes_only_the_pending_brake_the_step_after(latched):
    """The one look-ahead step the tilt takes per step stands for both outcomes (actuation lag 1)."""
    p = BrakingParams(latched_brake=latched)
    rng = np.random.default_rng(0)
    n = 500
    g, v = rng.uniform(0.5, 12.0, n), rng.uniform(0.0, 9.0, n)
    i, b = rng.uniform(-2.0, 2.0, n), rng.random(n) < 0.5
    miss = braking_step(p, 3.0, g, v, i, b, np.zeros(n, dtype=bool))
    det = braking_step(p, 3.0, g, v, i, b, np.ones(n, dtype=bool))
    for k in range(3):
        np.testing.assert_array_equal(det[k], miss[k])
    np.testing.assert_array_equal(det[3], miss[3] | (g < p.braking_distance_m))


def test_the_grid_committor_at_its_edges_and_at_the_branching_start(committor):
    p = BrakingParams()
    assert committor.log_value(50, np.array([1.9]), np.array([5.0]), np.array([False]))[0] == 0.0
    assert committor.log_value(p.n_steps, np.array([3.0]), np.array([5.0]), np.array([True]))[0] == LOG_V_FLOOR
    s = branching_start(p)
    v0 = committor.log_value(s.step, np.array([s.gap_m]), np.array([s.speed_mps]), np.array([s.pending]))[0]
    exact = math.log(1.983904947564059e-15)
    assert abs(v0 - exact) < math.log(20.0), math.exp(v0 - exact)
    assert committor.steps == 200 * 40 * 2 * (p.n_steps - s.step)


def test_the_braking_tilt_is_unbiased_and_its_step_weights_bounded(pem, committor):
    """40 seeds of 500 rollouts: the mean of mu_hat / p within 4 standard errors of 1 (p the exact 1.984e-15), and
    every step's p / q at most 1 / eps."""
    p = BrakingParams()
    ratios = []
    for seed in range(40):
        detector = BrakingTiltDetector(committor, pem.logit_at_gap)
        b = draw_tilted(detector, PEMDetector(pem), 500, np.random.default_rng(seed))
        assert np.all(b.log_p - b.log_q <= -math.log(TILT_EPS) + 1e-9)
        fail = (b.observations[..., 0] < p.crash_gap_m).any(axis=1)
        lw = np.where(fail, (b.log_p - b.log_q).sum(axis=1), -np.inf)
        ratios.append(math.exp(logsumexp(lw) - math.log(500) - math.log(1.983904947564059e-15)))
    r = np.array(ratios)
    assert abs(r.mean() - 1.0) <= 4 * r.std(ddof=1) / math.sqrt(r.size), (r.mean(), r.std(ddof=1))
    assert 0.2 < r.var(ddof=1) * 500 < 5.0  # the grid's V is not the exact one: relvar a rollout 0.85 measured


def test_the_same_seed_gives_the_same_tilted_rollouts_for_any_chunk(pem, committor):
    a = draw_tilted(BrakingTiltDetector(committor, pem.logit_at_gap), PEMDetector(pem), 300, np.random.default_rng(5))
    b = draw_tilted(
        BrakingTiltDetector(committor, pem.logit_at_gap), PEMDetector(pem), 300, np.random.default_rng(5), chunk_size=64
    )
    np.testing.assert_array_equal(a.detected, b.detected)
    np.testing.assert_array_equal(a.log_q, b.log_q)
    np.testing.assert_array_equal(a.log_p, b.log_p)


def test_a_second_run_reuses_the_solve_and_gives_the_same_estimate():
    tilt_module._SOLVED.clear()
    problem = _tilted_main()
    cfg = dataclasses.replace(ExperimentConfig.of(method="tilt", seed=4), n_per_stage=400)
    first = Experiment(cfg, problem=problem).run().final
    again = Experiment(cfg, problem=problem).run().final
    assert first.prepared.startswith("the scenario's proposal solved by this run (10,240 rollout-equivalents")
    assert again.prepared.startswith("the scenario's proposal reused")
    assert first.estimate.log_mu_hat == again.estimate.log_mu_hat
    assert first.n_simulations - again.n_simulations == 10_240
    assert abs(first.estimate.log_mu_hat - math.log(1.983904947564059e-15)) < math.log(1.5)


def test_the_committor_scores_splitting_on_braking_and_its_solve_counts():
    from pemviz.estimators.ams import run_ams

    tilt_module._SOLVED.clear()
    problem = _tilted_main()
    solved = run_ams(problem, 100, 10, seed=1, score="committor")
    reused = run_ams(problem, 100, 10, seed=1, score="committor")
    assert solved.estimate().log_mu_hat == reused.estimate().log_mu_hat
    assert solved.n_simulations - reused.n_simulations == 10_240
    cut = BrakingTilt(BrakingParams(), load_pem().logit_at_gap, PEMDetector(load_pem())).splitting_score(problem)
    batch, graded = cut.simulate(20, np.random.default_rng(0))
    first = cut.committor.first_step
    assert np.all(np.isinf(graded[:, :first]))
    obs = batch.observations[:, first + 3]
    np.testing.assert_array_equal(
        graded[:, first + 3], -cut.committor.log_value(first + 3, obs[:, 0], obs[:, 1], obs[:, 3] > 0.5)
    )


def test_the_tilt_on_highway_env_vehicles_is_refused_and_pemviz_run_has_none_on_braking(capsys):
    """The tilt reads the batched twin's controller state: on the highway-env simulator it is refused; ``pemviz run``
    offers no tilt on braking (it moved here), saying so in one line."""
    from pemviz.cli import main
    from pemviz.scenarios.braking.problem import braking_problem

    with pytest.raises(ValueError, match="batched twin only"):
        tilt_module.tilted_problem(braking_problem(load_pem(), sim="highway-env"), load_pem())
    assert main(["run", "--method", "tilt", "--no-record"]) != 0
    err = capsys.readouterr().err.strip()
    assert (
        err
        == "pemviz run: error: method tilt: the braking problem has no tilted proposal of its own; use adaptive or mc"
    )
