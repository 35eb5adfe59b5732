"""Splitting from independent replicas (research/ams_replicas.py): its streams, its mean's unbiasedness and its
interval's coverage on the toy's exact answer, its interval arithmetic and its verdict rule."""

from __future__ import annotations

import math

import numpy as np
from pemviz.estimators.ams import run_ams
from pemviz.scenarios.problems import build_problem

from conftest import REPO, load_script

study = load_script(REPO / "research" / "ams_replicas.py")


def _pool(seeds: range, replicas: int) -> np.ndarray:
    """p_hat / p of toy-1e-3 (exact 1e-3) replicas [seeds, replicas], N = 100, k = 10, ranked by the robustness."""
    pb = build_problem("toy-1e-3")
    p = math.exp(pb.exact_log_p)
    return np.array([[study.replica(pb, 100, 10, s, r)[0].p_hat / p for r in range(replicas)] for s in seeds])


def test_replica_zero_is_the_methods_run_and_each_replica_has_its_own_streams():
    """Replica 0 of seed s is ``--method ams --seed s`` (run_ams) bit for bit; the same (seed, r) gives the same
    rollouts bit for bit; another r, or another seed, other rollouts."""
    pb = build_problem("toy-1e-3")
    ref = run_ams(pb, 100, 10, seed=7)
    r0 = study.replica(pb, 100, 10, 7, 0)[1]
    assert r0.particles is not None and ref.particles is not None
    np.testing.assert_array_equal(r0.particles.detected, ref.particles.detected)
    assert r0.estimate().log_mu_hat == ref.estimate().log_mu_hat and r0.n_simulations == ref.n_simulations
    runs = {key: study.replica(pb, 100, 10, *key)[1] for key in [(7, 1), (7, 2), (8, 1)]}
    again = study.replica(pb, 100, 10, 7, 1)[1]
    np.testing.assert_array_equal(again.particles.detected, runs[7, 1].particles.detected)
    assert again.estimate().log_mu_hat == runs[7, 1].estimate().log_mu_hat
    detected = [r0.particles.detected] + [runs[k].particles.detected for k in runs]
    for i in range(len(detected)):
        for j in range(i):
            assert not np.array_equal(detected[i], detected[j])


def test_the_replicas_mean_is_unbiased_on_the_toy():
    """toy-1e-3: the mean of p_bar / p over 100 seeds of R = 4 replicas (400 runs of N = 100) within 3 standard
    errors of 1, the standard error under 0.05 so that a 15 % bias would show (measured 0.964 +- 0.027)."""
    x = _pool(range(100), 4).mean(axis=1)
    se = x.std(ddof=1) / math.sqrt(x.size)
    assert abs(x.mean() - 1.0) <= 3.0 * se and se < 0.05, f"mean p_bar / p = {x.mean():.3f} +- {se:.3f}"


def test_the_interval_covers_the_toys_exact_answer():
    """toy-1e-3, 200 runs of R = 4 replicas: the delta-method interval on log p_bar holds p = 1e-3 in at least 90 %
    of them (a 95 % interval; 200 runs give a binomial standard error of 1.5 %; measured 0.92); the normal quantile
    in place of Student-t's 3 degrees of freedom would fall short (measured 0.81)."""
    x = _pool(range(200, 400), 4)
    held = [lo <= 1.0 <= hi for lo, hi in (study.intervals(row)["log-t"] for row in x)]
    assert np.mean(held) >= 0.90, f"coverage {np.mean(held):.3f}"


def test_intervals_by_hand():
    """p = (1, 2, 3, 4): mean 2.5, s = 1.2910, se = 0.6455, t_{3, 0.975} = 3.1824: Student-t [0.4458, 4.5542];
    the log-scale one 2.5 exp(-+ 3.1824 x 0.6455 / 2.5) = [1.0992, 5.6859]."""
    iv = study.intervals(np.array([1.0, 2.0, 3.0, 4.0]))
    np.testing.assert_allclose(iv["t"], (0.4458, 4.5542), atol=2e-4)
    np.testing.assert_allclose(iv["log-t"], (1.0992, 5.6859), atol=2e-4)
    lo, hi = iv["boot-t"]
    assert lo < 2.5 < hi


def test_the_verdict_rule():
    """reliable: R >= 4, at most one zero, a positive lower end and a spread ESS >= 2; else doubtful; all zero:
    unreliable."""
    ok = np.array([1.0, 2.0, 3.0, 4.0])
    assert study.verdict(ok, study.intervals(ok)["log-t"]) == "reliable"
    three = ok[:3]
    assert study.verdict(three, study.intervals(three)["log-t"]) == "doubtful"
    zeros = np.array([0.0, 0.0, 3.0, 4.0])
    assert study.verdict(zeros, study.intervals(zeros)["log-t"]) == "doubtful"
    one = np.array([0.0, 0.0, 0.0, 1e-3, 0.0, 0.0, 0.0, 0.0])
    assert study.verdict(one, (1e-9, 1.0)) == "doubtful"  # ESS 1: one replica carries the mean
    assert study.verdict(np.zeros(4), (0.0, 0.0)) == "unreliable"
