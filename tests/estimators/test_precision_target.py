"""A precision target (``--rel-error``): final batches are added until the interval is as narrow as asked, or a cap
is hit; the estimate pools them as the rollout file says; refusals come before any work."""

from __future__ import annotations

import math

import numpy as np
import pytest
from pemviz.config import ConfigError, ExperimentConfig
from pemviz.core.confidence import clopper_pearson
from pemviz.core.estimate import Estimate, estimate
from pemviz.engine.experiment import Experiment
from pemviz.estimators import build_estimator
from pemviz.estimators.pooling import pool
from pemviz.estimators.precision import GROWTH, MIN_BATCH, PrecisionTarget, added_batch_size
from pemviz.scenarios.problems import build_problem

TOY = "toy-1e-3"
"""Exact p = 1e-3: plain Monte Carlo reaches a 20 % interval in about 10^5 rollouts, a second."""


def run(problem_name: str = TOY, **fields):
    problem = build_problem(problem_name)
    return problem, Experiment(ExperimentConfig.of(**fields), problem=problem).run()


def test_plain_monte_carlo_samples_until_the_clopper_pearson_interval_is_within_the_target():
    problem, done = run(method="mc", n_per_stage=1000, rel_error=0.2, seed=3)
    final = done.final
    e = final.estimate
    lo, hi = clopper_pearson(e.n_failures, e.n)  # the interval of every rollout pooled, recomputed independently
    assert math.isclose(math.exp(e.log_ci[1]), hi, rel_tol=1e-12)
    assert (hi - lo) / (2 * e.n_failures / e.n) <= 0.2 < e.rel_half_width * 1.5
    assert final.stop.startswith("target reached") and final.n_simulations == e.n > 1000
    assert final.stages_used == tuple(range(1, len(final.stages_used) + 1)) and len(final.stages_used) > 1
    assert final.pooling[0] == "rollouts" and math.isclose(sum(final.pooling[1]), 1.0)
    assert e.covers(problem.exact_log_p)


def test_a_cap_on_simulations_stops_the_run_and_says_so():
    _, done = run(method="mc", n_per_stage=1000, rel_error=0.01, max_sims=5000)
    assert done.final.n_simulations == 5000
    assert done.final.stop.startswith("stopped at a cap, not at the target: --max-sims 5,000 reached")


def test_the_default_cap_is_named_as_the_default(monkeypatch):
    from pemviz import settings

    monkeypatch.setattr(settings, "DEFAULT_MAX_SIMS", 5000)
    _, done = run(method="mc", n_per_stage=1000, rel_error=0.01)
    assert done.final.n_simulations == 5000
    assert done.final.stop.startswith(
        "stopped at a cap, not at the target: the default cap of 5,000 simulations (--max-sims) reached"
    )


def test_a_cap_on_time_stops_adding_batches():
    cfg = ExperimentConfig.of(method="mc", n_per_stage=1000, rel_error=0.01, max_time_s=10.0)
    problem = build_problem(TOY)
    ticks = iter([0.0, 100.0, 100.0, 100.0])  # the run starts, then every look at the clock is past the cap
    inner = build_estimator(cfg.replace(rel_error=None, max_time_s=None), problem)
    est = PrecisionTarget(inner, cfg, clock=lambda: next(ticks))
    plan = est.next_stage()
    assert plan.n == 1000
    rng = np.random.default_rng(0)
    batch = problem.simulate(plan.n, plan.sampler, problem.target, rng)
    failed = problem.failed(batch, problem.robustness(batch, "classic"))
    est.observe(batch, failed, None)
    est.finish()
    assert est.next_stage() is None
    assert est.stop.startswith("stopped at a cap, not at the target: --max-time 10 s reached")


def test_an_adaptive_run_pools_the_added_batches_with_the_final_one_as_its_rollout_file_would():
    """The pool: the CE stages after the failure level with their quadratic lambda, the final batch's lambda shared by
    the final batches in proportion to their rollouts; pooled again here from the stages' own arrays."""
    problem, done = run("main", rel_error=0.05, seed=1)
    final, k_final = done.final, ExperimentConfig.of().adaptive.n_stages + 1
    assert final.stop.startswith("target reached") and final.estimate.rel_half_width <= 0.05
    used = final.stages_used
    assert k_final in used and used[-1] > k_final  # batches were added after the final one
    rule, lam = final.pooling
    assert rule == "quadratic" and len(lam) == len(used) and math.isclose(sum(lam), 1.0)
    sizes = {s.stage: s.estimate.n for s in done.stages}
    finals = [k for k in used if k >= k_final]
    n_finals = sum(sizes[k] for k in finals)
    ratios = [lam[used.index(k)] / sizes[k] for k in finals]  # every final rollout alike
    assert max(ratios) == pytest.approx(min(ratios), rel=1e-12)
    assert sum(lam[used.index(k)] for k in finals) == pytest.approx(
        lam[used.index(k_final)] * n_finals / sizes[k_final], rel=1e-12
    )
    assert final.estimate.covers(problem.exact_log_p)


def test_the_added_batch_follows_the_square_root_law_within_its_bounds():
    def est(width: float) -> Estimate:  # mu_hat 1e-3 with a symmetric interval of relative half-width ``width``
        mu = 1e-3
        return Estimate(
            1000, 10, math.log(mu), 1.0, 1.0, 10.0, (math.log(mu * (1 - width)), math.log(mu * (1 + width)))
        )

    assert est(0.4).rel_half_width == pytest.approx(0.4)
    assert added_batch_size(est(0.4), 1000, 0.2) in (3600, 3601)  # 1.2 x ((0.4 / 0.2)^2 - 1) = 3.6 times more
    assert added_batch_size(est(0.9), 1000, 0.1) == GROWTH * 1000  # at most GROWTH times the final rollouts
    assert added_batch_size(est(0.201), 1000, 0.2) == MIN_BATCH
    no_failure = estimate(np.zeros(500), np.zeros(500, bool), np.zeros(500))
    assert no_failure.rel_half_width == math.inf and added_batch_size(no_failure, 500, 0.2) == 500


@pytest.mark.parametrize(
    "fields, message",
    [
        (
            dict(method="ams", rel_error=0.1),
            "rel_error = 0.1 is invalid: method ams has no final batch to add to; use it " "with method adaptive, mc",
        ),
        (dict(max_sims=10_000), "max_sims = 10000 is invalid: a cap on the rollouts added for a target relative error"),
        (dict(max_time_s=60.0), "max_time_s = 60.0 is invalid: a cap on the rollouts added"),
        (
            dict(rel_error=0.1, max_sims=1000),
            "the most simulations must be at least the run's planned 2,100 simulations",
        ),
        (dict(rel_error=0.1, final_estimate="last-stage"), "final_estimate = 'last-stage' has none"),
        (dict(rel_error=0.0), "the target relative error must be none or a number in (0, 10]"),
    ],
)
def test_settings_that_cannot_run_are_refused_by_the_config(fields, message):
    with pytest.raises(ConfigError, match=None) as info:
        ExperimentConfig.of(**fields)
    assert message in str(info.value)


def test_pool_of_equal_shares_is_the_pool_of_every_rollout_alike():
    rng = np.random.default_rng(0)
    parts = [(rng.normal(size=n), rng.random(n) < 0.3, rng.normal(size=n)) for n in (100, 250, 50)]
    lam = np.array([100, 250, 50], dtype=np.float64) / 400
    alike, shared = pool(parts, None), pool(parts, lam)
    assert shared.log_mu_hat == pytest.approx(alike.log_mu_hat, rel=1e-13)


def test_a_requirement_no_batch_can_decide_stops_at_the_first_look():
    """``p < 1e-9`` on braking (p = 1.98e-15) with a proposal never fitted to a failure: its verdict is capped, so no
    added batch backs an upper bound, and mu_hat ~ 2e-15 keeps the lower bound far below 1e-9. The run stops after
    its planned 1,250 simulations, undecided, and says why (it drew batches to its 20,000 cap before); plain Monte
    Carlo, which would need 3 x 10^9 rollouts, is not drawn."""
    from pemviz.presets import PRESETS
    from pemviz.scenarios.problems import problem_for

    cfg = ExperimentConfig.of(**{**PRESETS["quick"], "n_stages": 2, "require": "p < 1e-9", "max_sims": 20_000})
    final = Experiment(cfg, problem=problem_for(cfg)).run().final
    assert final.decision is not None and final.decision.outcome == "undecided"
    assert not final.estimate.interval_backed and final.n_simulations == cfg.n_simulations == 1250
    assert final.stop.startswith("requirement undecided: the stages cannot decide p < 1e-09: the sampler caps")
    assert "plain Monte Carlo not drawn after the stages" in final.stop


class _Heavy:
    """An extensible estimator whose pooled estimate is ``doubtful`` with k-hat ``khat`` at every look: mu_hat 1e-6
    from 50 failures, no interval backed (what a proposal with a heavy weight tail gives, whatever N)."""

    rng = np.random.default_rng(0)

    def __init__(self, khat: float) -> None:
        self.khat, self.n, self.extended = khat, 100, 0

    def plan(self):
        from pemviz.core.plan import RunPlan

        return RunPlan(())

    def next_stage(self):
        return None

    def result(self):
        est = Estimate(self.n, 50, math.log(1e-6), 1.0, 1.0, 30.0, khat=self.khat, verdict="doubtful")
        return est, (1,)

    def extend(self, n: int):
        from pemviz.estimators.base import StagePlan

        self.extended += 1
        self.n += n
        return StagePlan(1 + self.extended, "final", n, None)

    def final_rollouts(self) -> int:
        return self.n

    def simulations_counted(self):
        return None

    def finish(self):
        return None


def looks_until_stop(khat: float, **stop) -> tuple[int, str]:
    """Drive :class:`PrecisionTarget` over :class:`_Heavy` until it stops: (batches added, its stop line)."""
    inner = _Heavy(khat)
    target = PrecisionTarget(inner, ExperimentConfig.of(method="adaptive", **stop))
    while (plan := target.next_stage()) is not None:
        target._current = plan
        target.finish()
    return inner.extended, target.stop


def test_a_heavy_weight_tail_at_two_looks_running_stops_the_added_batches():
    """k-hat 1.5 > 0.7 at every look: more batches of the same proposal back no interval, so a requirement the lower
    bound cannot reach (mu_hat 1e-6 < 1e-3) and a precision target stop at the second look, not at the 10^6 cap."""
    added, stop = looks_until_stop(1.5, require="p < 1e-3")
    assert added == 1, stop
    assert stop.startswith("requirement undecided: the stages cannot decide p < 0.001: k-hat above 0.7 at 2 looks")
    assert "their estimate 1.000e-06 lies below the threshold" in stop
    added, stop = looks_until_stop(1.5, rel_error=0.1)
    assert added == 1 and stop.startswith("stopped short of the target: the stages cannot back an interval: k-hat")


def test_a_requirement_the_lower_bound_may_reach_or_a_light_tail_keeps_adding_batches():
    """mu_hat 1e-6 above p < 1e-7's threshold: the lower bound may yet violate it; k-hat 0.5: more rollouts may back
    an interval. Both run on to the cap, each added batch at least as many rollouts again as the final ones so far
    while no interval is backed: 100 -> 10,000 in at most 7 looks."""
    for khat, require in ((1.5, "p < 1e-7"), (0.5, "p < 1e-3")):
        added, stop = looks_until_stop(khat, require=require, max_sims=10_000)
        assert 2 <= added <= 7 and "--max-sims 10,000 reached" in stop, stop


def test_a_requirement_the_stages_cannot_decide_goes_to_plain_monte_carlo_at_once():
    """Braking with a proposal never fitted to a failure (its verdict capped at doubtful): p < 0.5 can be decided by
    neither its interval nor its lower bound (mu_hat ~ 1e-15). The stages stop at their first look and plain Monte
    Carlo decides it in its first batch; the stages used to draw batches to the cap (here 100,000), leaving plain
    Monte Carlo nothing: undecided."""
    from pemviz.presets import PRESETS
    from pemviz.scenarios.problems import problem_for

    fields = {**PRESETS["quick"], "n_stages": 1, "n_per_stage": 10, "n_final": 10, "ce_epochs": 1}
    cfg = ExperimentConfig.of(**fields, require="p < 0.5", max_sims=100_000, seed=0)
    final = Experiment(cfg, problem=problem_for(cfg)).run().final
    assert final.decision.outcome == "met", final.stop
    assert "the stages cannot decide p < 0.5: the sampler caps their verdict at doubtful" in final.stop
    assert "after 70 simulations); plain Monte Carlo after the stages" in final.stop
    assert final.n_simulations == 70 + 10_000  # the stages' 70, then plain Monte Carlo's first batch decides
