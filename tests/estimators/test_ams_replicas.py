"""Splitting from independent replicas (``--ams-replicas R``): each replica's streams, the engine's run of R, the
mean's unbiasedness and its interval's coverage on the toy's exact answer, the interval and verdict by hand."""

from __future__ import annotations

import math

import numpy as np
import pytest
from pemviz.config import ExperimentConfig
from pemviz.engine.experiment import Experiment
from pemviz.estimators.ams import replicas_interval, run_ams
from pemviz.scenarios.problems import build_problem


def _pool(seeds: range, replicas: int) -> np.ndarray:
    """p_hat / p of toy-1e-3 (exact 1e-3) replicas [seeds, replicas], N = 100, k = 10, ranked by the robustness."""
    pb = build_problem("toy-1e-3")
    logs = [[run_ams(pb, 100, 10, s, replica=r).estimate().log_mu_hat for r in range(replicas)] for s in seeds]
    return np.exp(np.array(logs)) / 1e-3


@pytest.mark.parametrize("score", ["robustness", "lookahead"])
def test_the_engine_runs_replica_zero_as_the_one_run_and_each_replica_from_streams_of_its_own(score):
    """R = 3 through the engine: replica 0 is the R = 1 run bit for bit, replica r is ``run_ams(replica=r)`` bit
    for bit, no two replicas draw the same particles; the run counts every replica's rollout-equivalents and the
    estimate is their mean."""
    pb = build_problem("toy-1e-3")
    cfg = ExperimentConfig.of(method="ams", n_per_stage=100, ams_killed=10, seed=7, ams_score=score)
    one = Experiment(cfg, problem=pb).run()
    three = Experiment(cfg.replace(ams_replicas=3), problem=pb).run()
    direct = [run_ams(pb, 100, 10, seed=7, score=score, replica=r) for r in range(3)]
    assert direct[0].estimate().log_mu_hat == one.final.estimate.log_mu_hat
    assert direct[0].n_simulations == one.final.n_simulations
    p = np.array([math.exp(d.estimate().log_mu_hat) for d in direct])
    assert three.final.estimate.log_mu_hat == pytest.approx(math.log(p.mean()), rel=1e-12)
    assert three.final.n_simulations == sum(d.n_simulations for d in direct)
    assert three.final.estimate.verdict == "doubtful"  # fewer than 4 replicas back no interval
    for i in range(3):
        for j in range(i):
            assert not np.array_equal(direct[i].particles.detected, direct[j].particles.detected)


def test_the_replicas_mean_is_unbiased_on_the_toy():
    """toy-1e-3: the mean of p_bar / p over 100 seeds of R = 4 replicas (400 runs of N = 100) within 3 standard
    errors of 1, the standard error under 0.05 so that a 15 % bias would show (measured 0.964 +- 0.027)."""
    x = _pool(range(100), 4).mean(axis=1)
    se = x.std(ddof=1) / math.sqrt(x.size)
    assert abs(x.mean() - 1.0) <= 3.0 * se and se < 0.05, f"mean p_bar / p = {x.mean():.3f} +- {se:.3f}"


def test_the_interval_covers_the_toys_exact_answer():
    """toy-1e-3, 200 runs of R = 4 replicas: the interval holds p = 1e-3 in at least 90 % of them (a 95 % interval;
    200 runs give a binomial standard error of 1.5 %; measured 0.92); the normal quantile in place of Student-t's 3
    degrees of freedom would fall short (measured 0.81)."""
    x = _pool(range(200, 400), 4)
    held = [lo <= 0.0 <= hi for lo, hi in (replicas_interval(row)[0] for row in x)]
    assert np.mean(held) >= 0.90, f"coverage {np.mean(held):.3f}"


def test_interval_and_verdict_by_hand():
    """p = (1, 2, 3, 4): mean 2.5, s = 1.2910, t_{3, 0.975} = 3.1824: 2.5 exp(-+ 3.1824 x 1.2910 / (2 x 2.5)) =
    [1.0992, 5.6859], reliable; fewer than 4 runs, two zeros, or one run carrying the mean ((sum p)^2 / sum p^2 <
    2): doubtful; every run 0: unreliable."""
    (lo, hi), verdict, _ = replicas_interval(np.array([1.0, 2.0, 3.0, 4.0]))
    np.testing.assert_allclose(np.exp([lo, hi]), (1.0992, 5.6859), atol=2e-4)
    assert verdict == "reliable"
    assert replicas_interval(np.array([1.0, 2.0, 3.0]))[1] == "doubtful"
    assert replicas_interval(np.array([0.0, 0.0, 3.0, 4.0]))[1] == "doubtful"
    assert replicas_interval(np.array([1e-3, 1e-6, 1e-6, 1e-6]))[1] == "doubtful"  # effective runs 1.006
    assert replicas_interval(np.zeros(4)) == ((-math.inf, 0.0), "unreliable", "AMS: no failure in 4 runs")


def test_the_runs_own_variances_floor_the_interval_by_hand():
    """Four runs that agree, p = (1, 1, 1, 1), each with its genealogy's relative variance 0.25: their spread is 0
    (no interval, doubtful) but p_bar's relative variance is at least 4 x 0.25 / 4^2 = 1 / 16, so the interval is
    exp(-+ 3.1824 x 0.25) = [0.4513, 2.2157], reliable; a spread wider than the floor is kept ((1, 2, 3, 4) as
    above with v = 0.1: sqrt(30 x 0.1) / (4 x 2.5) = 0.173 < 0.258), a narrower one is not (v = 0.25: 0.274)."""
    same = np.ones(4)
    assert replicas_interval(same)[1] == "doubtful"
    (lo, hi), verdict, _ = replicas_interval(same, np.full(4, 0.25))
    np.testing.assert_allclose(np.exp([lo, hi]), (0.4513, 2.2157), atol=2e-4)
    assert verdict == "reliable"
    wide = np.array([1.0, 2.0, 3.0, 4.0])
    assert replicas_interval(wide, np.full(4, 0.1))[0] == replicas_interval(wide)[0]
    lo, hi = replicas_interval(wide, np.full(4, 0.25))[0]
    assert (hi - lo) / 2.0 == pytest.approx(3.1824 * math.sqrt(7.5) / 10.0, abs=1e-4)


@pytest.mark.parametrize("score", ["robustness", "lookahead"])
def test_replicas_on_worker_processes_give_the_one_process_run_bit_for_bit(score, monkeypatch):
    """R = 4 with two worker processes (``workers = 2``: replicas 1-3 side by side in the pool, replica 0 here) and in
    this process, one after another (``workers = 1``): every stage's level, failures and estimate, the final estimate
    and the cost the same bits, the stages shown in the same order; the pool ran them (the toy's replicas are too quick
    to pay for it: the threshold set to 0)."""
    from pemviz.engine.executors import get_executor
    from pemviz.estimators import ams_pool

    monkeypatch.setattr(ams_pool, "REPLICAS_PAY_S", 0.0)

    pb = build_problem("toy-1e-3")
    cfg = ExperimentConfig.of(method="ams", n_per_stage=100, ams_killed=10, seed=3, ams_score=score, ams_replicas=4)
    runs = [Experiment(cfg.replace(workers=w), problem=pb).run() for w in (1, 2)]
    for a, b in zip(runs[0].stages, runs[1].stages, strict=True):
        assert repr((a.stage, a.gamma, a.n_elites, a.estimate)) == repr((b.stage, b.gamma, b.n_elites, b.estimate))
    assert repr(runs[0].final.estimate) == repr(runs[1].final.estimate)  # nan fields: their text
    assert runs[0].final.n_simulations == runs[1].final.n_simulations
    assert len(runs[0].stages) > 4 and get_executor("local", None, 2).started
