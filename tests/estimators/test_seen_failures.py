"""The probability of the failures a run drew is a lower bound of p (pemviz.estimators.base.SeenFailures), and an
estimate below it is never called reliable."""

from __future__ import annotations

import math

import numpy as np
import pytest
from pemviz.config import ExperimentConfig
from pemviz.core.estimate import estimate
from pemviz.engine.experiment import Experiment
from pemviz.estimators.base import SeenFailures, failure_steps, log_p_before_failure
from pemviz.scenarios.problems import build_problem


@pytest.mark.parametrize(
    ("problem", "method", "n"),
    [
        ("main", "naive50", 2000),
        ("main", "mixed50", 2000),
        ("main", "adaptive", 100),
        ("toy", "adaptive", 100),
        ("latched", "adaptive", 100),
    ],
)
def test_the_failures_seen_never_sum_above_the_exact_answer(problem, method, n):
    # the exact answers (closed forms, the braking enumeration) are independent of the sampler: the bound, a sum of
    # p over distinct failing detection prefixes, must stay below them, and the run must have seen failures
    pb = build_problem(problem)
    res = Experiment(ExperimentConfig.of(method=method, n_per_stage=n, seed=1), problem=pb).run()
    assert res.final.log_p_seen is not None and pb.exact_log_p is not None
    assert res.final.log_p_seen <= pb.exact_log_p + 1e-9
    if method == "adaptive":  # the default sampler draws the likely failures: a bound within 10^3 of p (measured:
        # main 10^-2.3, toy 10^-1.6, latched 10^-0.06) and an estimate above it
        assert res.final.log_p_seen > pb.exact_log_p - math.log(1e3)
        assert res.final.estimate.verdict == "reliable"


def test_a_prefix_drawn_twice_counts_once_and_distinct_prefixes_add():
    pb = build_problem("main")
    res_batches = []
    from pemviz.engine.events import RolloutsSampled

    Experiment(
        ExperimentConfig.of(method="naive50", n_per_stage=400, seed=2),
        [lambda e: isinstance(e, RolloutsSampled) and res_batches.append(e)],
        problem=pb,
    ).run()
    e = res_batches[-1]
    batch, failed = e.batch, e.failed
    assert failed.sum() > 50
    once, twice = SeenFailures(), SeenFailures()
    once.add(pb, batch, failed)
    twice.add(pb, batch, failed)
    twice.add(pb, batch, failed)
    assert twice.log_p == once.log_p  # the same rollouts again add nothing
    # by hand: the distinct (prefix before the failure step) of the failing rollouts, their log p summed once each
    steps, log_p = failure_steps(pb, batch), log_p_before_failure(pb, batch)
    distinct = {batch.detected[i, : steps[i]].tobytes(): log_p[i] for i in np.flatnonzero(failed)}
    assert len(distinct) > 1
    assert once.log_p == pytest.approx(math.log(sum(math.exp(v) for v in distinct.values())), rel=1e-12)


def test_an_estimate_below_the_failures_seen_is_unreliable_and_one_above_keeps_its_verdict():
    e = estimate(np.full(100, math.log(1e-20)), np.arange(100) < 40, -np.arange(100.0))
    assert e.verdict == "reliable"
    low = e.below_seen(math.log(1e-20))  # mu_hat = 4e-21 < 1e-20 seen
    assert low.verdict == "unreliable" and low.reason.startswith("mu_hat is below 1.000e-20")
    assert (low.log_mu_hat, low.log_ci, low.ess) == (e.log_mu_hat, e.log_ci, e.ess)  # the numbers stay
    assert e.below_seen(math.log(1e-21)) is e and e.below_seen(None) is e
    assert e.below_seen(e.log_mu_hat) is e  # equal (the sums of the same logs) is not below


def test_a_scene_with_measurement_errors_gives_no_bound():
    from pemviz.scenarios.problems import problem_for

    cfg = ExperimentConfig.of(scenario="cut-in", method="naive50", n_per_stage=200, seed=3)
    res = Experiment(cfg, problem=problem_for(cfg)).run()
    assert res.final.estimate.n_failures > 0  # failures were drawn, and still
    assert res.final.log_p_seen is None  # errors are densities: a sum of them bounds no probability


def test_beyond_twice_keep_prefixes_the_most_likely_keep_are_kept(monkeypatch):
    pb = build_problem("main")
    from pemviz.engine.events import RolloutsSampled

    sampled = []
    Experiment(
        ExperimentConfig.of(method="naive50", n_per_stage=400, seed=2),
        [lambda e: isinstance(e, RolloutsSampled) and sampled.append(e)],
        problem=pb,
    ).run()
    batch, failed = sampled[-1].batch, sampled[-1].failed
    steps, log_p = failure_steps(pb, batch), log_p_before_failure(pb, batch)
    distinct = {batch.detected[i, : steps[i]].tobytes(): log_p[i] for i in np.flatnonzero(failed)}
    keep = len(distinct) // 3  # fewer than half: one add thins them
    assert keep >= 5
    monkeypatch.setattr(SeenFailures, "KEEP", keep)
    seen = SeenFailures()
    seen.add(pb, batch, failed)
    top = sorted(distinct.values(), reverse=True)[:keep]
    assert len(seen._log_p) == keep
    assert seen.log_p == pytest.approx(math.log(sum(math.exp(v) for v in top)), rel=1e-12)
