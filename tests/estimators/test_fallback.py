"""Plain Monte Carlo after a cross-entropy run whose weights back no interval (pemviz.estimators.fallback), against
the toy's closed-form answer: which stages run, what the answer is, what the stop line says, and that a seed gives the
same run at any chunk size."""

from __future__ import annotations

import dataclasses
import math
import re

import pytest
from pemviz import stl
from pemviz.config import ExperimentConfig
from pemviz.engine.experiment import Experiment
from pemviz.estimators.fallback import PlainFallback, with_plain_fallback
from pemviz.scenarios.problems import problem_for

TINY = dict(
    scenario="toy", n_stages=1, n_per_stage=10, n_final=10, pretrain_rollouts=10, plain_fallback=500, retry_factor=0
)
"""A cross-entropy run too small to back an interval: 10 pretraining rollouts, one stage of 10, 10 final; no retry."""
RETRY = dict(
    scenario_params=(("braking", 32),), n_stages=2, n_per_stage=20, n_final=30, pretrain_rollouts=20, retry_factor=10
)
"""Toy braking 32 (p = 1e-3 exactly): a first run of 90 rollouts whose weights back no interval at seed 0, then the
stages once more at N = 200 (20 + 2 x 200 + 30 = 450 rollouts), whose weights do."""


def run(**settings):
    config = ExperimentConfig.of(**{**TINY, **settings})
    problem = problem_for(config)
    return Experiment(config, problem=problem).run(), problem


def test_plain_monte_carlo_answers_where_the_weights_back_no_interval():
    # toy braking 32 -> safe 30: three misses in a row at p(detect) = 0.9, p = 1e-3 exactly
    done, problem = run(scenario_params=(("braking", 32),), seed=0, plain_fallback=10_000)  # 300,000 at most
    assert math.exp(problem.exact_log_p) == pytest.approx(1e-3, rel=1e-12)
    final, stages = done.final, done.stages
    ce = [s for s in stages if s.stage <= 2]  # pretraining, the CE stage, the CE final batch
    assert [s.kind for s in ce] == ["pretrain", "ce", "final"]
    assert ce[-1].estimate.verdict != "reliable"  # the premise: the method's weights back no interval
    plain = [s for s in stages if s.stage > 2]
    assert plain and all(s.kind == "final" for s in plain)
    est = final.estimate
    assert est.plain_mc and final.stages_used == tuple(s.stage for s in plain)
    assert est.n == sum(s.estimate.n for s in plain) and final.n_simulations == 30 + est.n
    # a 20 % interval: Clopper-Pearson's relative half-width <= 0.2, holding the exact answer
    assert est.rel_half_width <= 0.2 and est.covers(problem.exact_log_p)
    assert abs(math.exp(est.log_mu_hat) / 1e-3 - 1.0) < 0.25
    assert "plain Monte Carlo after the stages, whose weights backed no interval" in final.stop
    assert f"{est.n_failures:,} failures in {est.n:,} rollouts" in final.stop


def test_a_seed_gives_the_same_fallback_at_any_chunk_size():
    a, _ = run(scenario_params=(("braking", 32),), seed=3, plain_fallback=10_000)
    b, _ = run(scenario_params=(("braking", 32),), seed=3, plain_fallback=10_000, chunk_rollouts=777)
    assert a.final.estimate.log_mu_hat == b.final.estimate.log_mu_hat
    assert a.final.n_simulations == b.final.n_simulations
    assert [s.estimate.n_failures for s in a.stages] == [s.estimate.n_failures for s in b.stages]


def unstated(**settings):
    """:func:`run` on the toy as a scene that states no p (its exact answer dropped, as a user's scene has none)."""
    config = ExperimentConfig.of(**{**TINY, **settings})
    problem = dataclasses.replace(problem_for(config), exact_log_p=None)
    return Experiment(config, problem=problem).run(), problem


def test_no_failure_in_the_plain_rollouts_leaves_the_method_answer_with_an_upper_bound():
    # p = 1e-21 (21 misses in a row), stated by no answer: 40 x 30 = 1,200 plain rollouts see no failure
    done, _ = unstated(plain_fallback=40, seed=0)
    without, _ = unstated(plain_fallback=0, seed=0)
    assert done.final.estimate.log_mu_hat == without.final.estimate.log_mu_hat
    assert not done.final.estimate.plain_mc
    assert without.final.n_simulations == 30 and done.final.n_simulations == 30 + 1200
    # one-sided Clopper-Pearson with no failure in 1,200: 1 - 0.05^(1/1200) = 0.002493...
    assert "0 failures in 1,200 rollouts (at most 1,200: --plain-fallback)" in done.final.stop
    assert "p < 0.0025 (its 95 % upper bound)" in done.final.stop


def test_no_failure_in_the_stages_nor_the_plain_rollouts_is_answered_by_plain_monte_carlo_s_bound():
    """A scene that cannot fail (the toy's gap kept above -1 m, which it always is): the stages bound nothing, the
    1,200 plain rollouts bound p by the rule of three, and that is the answer (it was the stages' "bounds nothing")."""
    config = ExperimentConfig.of(**{**TINY, "plain_fallback": 40, "seed": 0})
    problem = dataclasses.replace(problem_for(config), exact_log_p=None, formula=stl.parse("G[0,19](d >= -1)"))
    done = Experiment(config, problem=problem).run()
    est = done.final.estimate
    assert est.plain_mc and est.n == 1200 and est.n_failures == 0 and est.log_ci[1] == pytest.approx(math.log(3 / 1200))
    assert "rule of three" in est.reason and "the answer is the stages'" not in done.final.stop
    assert "0 failures in 1,200 rollouts (at most 1,200: --plain-fallback), p < 0.0025" in done.final.stop


def test_a_backed_interval_or_a_zero_cap_or_an_odd_runs_no_plain_rollouts():
    done, _ = run(scenario_params=(("braking", 32),), seed=0, plain_fallback=0)
    assert max(s.stage for s in done.stages) == 2 and not done.final.estimate.plain_mc
    config = ExperimentConfig.of(scenario="toy", scenario_params=(("braking", 32),), plain_fallback=500)
    problem = problem_for(config)
    assert isinstance(with_plain_fallback(object(), config, problem), PlainFallback)  # type: ignore[arg-type]
    assert not isinstance(with_plain_fallback(object(), config.replace(plain_fallback=0), problem), PlainFallback)  # type: ignore[arg-type]
    odd = ExperimentConfig.of(scenario="toy", scenario_params=(("braking", "~choice(31, 32)"),), plain_fallback=500)
    assert not isinstance(with_plain_fallback(object(), odd, problem_for(odd)), PlainFallback)  # type: ignore[arg-type]
    with pytest.raises(ValueError, match="ratio must be >= 1"):
        PlainFallback(object(), config, problem, 0)  # type: ignore[arg-type]


def test_a_retry_at_a_larger_n_answers_where_its_weights_back_an_interval():
    done, problem = run(**RETRY, seed=0)
    alone, _ = run(**{**RETRY, "plain_fallback": 0}, seed=0)  # the first run by itself: the same rollouts
    kinds = ["pretrain", "ce", "ce", "final"]
    assert [(s.stage, s.kind) for s in done.stages] == list(enumerate(kinds + kinds))
    assert [s.estimate.n for s in done.stages] == [20, 20, 20, 30, 20, 200, 200, 30]
    assert [s.estimate.n_failures for s in done.stages[:4]] == [s.estimate.n_failures for s in alone.stages]
    assert not alone.final.estimate.interval_backed  # the premise: the first run's weights back no interval
    final = done.final
    est = final.estimate
    assert final.n_simulations == 90 + 450 and not est.plain_mc and est.verdict == "reliable"
    assert final.stages_used and set(final.stages_used) <= {4, 5, 6, 7}  # the retry's stages alone
    assert est.covers(problem.exact_log_p) and abs(math.exp(est.log_mu_hat) / 1e-3 - 1.0) < 0.2
    assert (
        f"the stages once more at N = 200 from a stream of their own, the first run's weights backing no interval "
        f"({alone.final.estimate.verdict}): reliable (--retry-factor)"
    ) in final.stop
    from pemviz.core.plan import stage_label

    labels = [stage_label(k, "ce", 2) for k in (1, 2, 5, 6)]  # the retry's CE stages, past the plan's K = 2
    assert labels == ["CE stage 1/2", "CE stage 2/2", "CE stage 5", "CE stage 6"]
    chunked, _ = run(**RETRY, seed=0, chunk_rollouts=7)  # a seed gives the same run at any chunk size
    assert (chunked.final.estimate.log_mu_hat, chunked.final.n_simulations) == (est.log_mu_hat, 540)


def test_the_retry_s_settings_n_times_its_factor_and_a_stream_of_its_own():
    from pemviz.estimators.fallback import retry_config, retry_seed
    from pemviz.settings import RETRY_MOST_N

    config = ExperimentConfig.of(scenario="toy", seed=5)
    again = retry_config(config)
    assert again is not None and again.n_per_stage == 4 * config.n_per_stage == 400
    assert again.seed == retry_seed(5) != 5 and again.adaptive.n_stages == config.adaptive.n_stages
    assert len({retry_seed(k) for k in range(1000)} | set(range(1000))) == 2000  # no seed meets another's retry
    assert retry_config(config.replace(n_per_stage=4_000)).n_per_stage == RETRY_MOST_N  # type: ignore[union-attr]
    for none in (
        config.replace(retry_factor=0),
        config.replace(retry_factor=1),
        config.replace(rel_error=0.2),  # a precision target adds its own final batches
        config.replace(n_per_stage=RETRY_MOST_N),
        config.replace(plain_fallback=0),  # the stages alone
    ):
        assert retry_config(none) is None


def test_the_paper_preset_has_no_fallback():
    from pemviz.presets import PRESETS

    assert PRESETS["paper"]["plain_fallback"] == 0 and PRESETS["authors-code"]["plain_fallback"] == 0


@pytest.mark.parametrize(
    "flags, said",
    [
        (["--k", "1", "--n", "10", "--n-final", "10", "--retry-factor", "0"], "plain Monte Carlo after the stages"),
        (["--k", "2", "--n", "20", "--n-final", "30", "--retry-factor", "10"], "the stages once more at N = 200"),
    ],
)
def test_a_run_answered_by_plain_monte_carlo_or_the_retry_re_estimates_to_its_numbers(tmp_path, capsys, flags, said):
    """``--save-rollouts`` keeps the stages the answer uses (the plain batches, or the retry's stages) and ``pemviz
    estimate`` gives the run's mu_hat again (the run prints it to 4 decimals of its log)."""
    from pemviz.cli import main

    path = tmp_path / "fallback.parquet"
    argv = ["run", "--scenario", "toy", "--param", "braking=32", *flags]
    argv += ["--plain-fallback", "10000", "--seed", "0", "--no-record", "--save-rollouts", str(path)]
    assert main(argv) == 0
    ran = capsys.readouterr().out
    assert said in ran
    logged = [line for line in ran.splitlines() if "(log mu_hat = " in line][0]
    log_mu = float(logged.split("(log mu_hat = ")[1].split(" nats")[0])
    assert main(["estimate", str(path), "--no-record"]) == 0
    again = capsys.readouterr().out
    line = [line for line in again.splitlines() if "(log mu_hat = " in line][0]
    assert float(line.split("(log mu_hat = ")[1].split(" nats")[0]) == pytest.approx(log_mu, abs=1e-4)
    assert "exact 1.000e-03" in again and "inside the interval" in again


def test_the_fallback_stays_within_the_run_s_max_sims_and_a_million():
    # the stages (30 simulations, their verdict capped) stop at once; plain Monte Carlo's cap is what --max-sims
    # leaves, 1,000 (not 500 x 30 = 15,000), whose failures the exact answer 1e-21 does not expect: none drawn
    done, _ = run(seed=0, rel_error=0.2, max_sims=1030)
    assert done.final.n_simulations == 30
    assert "expects 1e-18 failures in 1,000 rollouts: it would end with no interval" in done.final.stop
    from pemviz.settings import PLAIN_FALLBACK_MOST as MOST

    assert MOST == 1_000_000


def test_plain_monte_carlo_is_not_drawn_where_the_scene_s_exact_answer_expects_no_failure_in_its_cap():
    # the same run on the toy, whose exact answer 1e-21 expects 1.2e-18 failures in the 1,200 rollouts: none drawn
    done, problem = run(plain_fallback=40, seed=0)
    without, _ = run(plain_fallback=0, seed=0)
    assert math.exp(problem.exact_log_p) == pytest.approx(1e-21, rel=1e-9)
    assert done.final.n_simulations == without.final.n_simulations == 30
    assert done.final.estimate.log_mu_hat == without.final.estimate.log_mu_hat
    stop = done.final.stop
    assert (
        "plain Monte Carlo not drawn after the stages, whose weights backed no interval "
        f"({without.final.estimate.verdict}): p = 1.000e-21 (the exact answer) expects 1.2e-18 failures in 1,200 "
        "rollouts: it would end with no interval (--plain-fallback)"
    ) in stop
    assert "a larger stage budget or another method may decide it" in stop


def test_a_scene_that_caps_the_stages_verdict_gets_no_retry_but_still_plain_monte_carlo():
    # toy braking 32 (p = 1e-3): a retry at N = 200 would back its interval (the test above), but a scene that caps
    # every run of its stages at doubtful (as braking at --margin 0) makes it useless: plain Monte Carlo follows at once
    config = ExperimentConfig.of(**{**TINY, **RETRY, "plain_fallback": 100})  # 9,000 plain rollouts at most
    problem = dataclasses.replace(problem_for(config), verdict_cap=("doubtful", "a test's cap"))
    done = Experiment(config.replace(seed=0), problem=problem).run()
    assert [s.kind for s in done.stages[:4]] == ["pretrain", "ce", "ce", "final"]
    assert all(s.kind == "final" for s in done.stages[4:]) and done.final.estimate.plain_mc
    assert "the stages not run once more (doubtful): the scene caps every run of the stages at doubtful" in (
        done.final.stop
    )
    assert "once more at N" not in done.final.stop and done.final.estimate.covers(problem.exact_log_p)


@pytest.mark.parametrize(
    "cap, log_p, require, why",
    [
        # braking at --margin 0: 8.058e-33 against the most plain rollouts, 10^6
        (10**6, math.log(8.058e-33), None, "p = 8.058e-33 (the exact answer) expects 8.1e-27 failures in 1,000,000"),
        (10**6, math.log(2.98e-4), None, None),  # the crossing's reference: 298 failures expected
        (1_000, math.log(1e-3), None, None),  # one failure expected
        (999, math.log(1e-3), None, "expects 1 failures in 999 rollouts"),  # 0.999 (printed to 2 digits)
        (10**6, None, None, None),  # no stated p: nothing rules a failure out
        # a requirement p < 1e-13: a bound below it needs 2.996e13 rollouts; p = 1.98e-15 gives no failure either
        (10**6, math.log(1.984e-15), "p < 1e-13", "a bound below 1e-13 needs 29,957,322,735,"),
        (10**6, None, "p < 1e-13", None),  # p unknown: failures could refute it
        (10**6, math.log(1e-8), "p < 1e-9", "p = 1.000e-08 (the exact answer) expects 0.01 failures"),
        (10**6, math.log(1e-3), "p < 1e-9", None),  # 1,000 failures refute it
        (10**6, math.log(1e-7), "p < 1e-5", None),  # 299,572 rollouts without a failure bound p below 1e-5
        (10**6, math.log(1e-15), "p > 1e-13", "lies below it: it could not decide p > 1e-13"),
        (0, math.log(1e-3), None, "no plain rollout is left"),
    ],
)
def test_the_rule_draws_plain_monte_carlo_only_where_its_cap_can_decide(cap, log_p, require, why):
    from pemviz.estimators.fallback import plain_cannot_decide

    said = plain_cannot_decide(cap, None if log_p is None else (log_p, "the exact answer"), require)
    assert said is None if why is None else why in (said or ""), said


def test_the_rollouts_a_bound_needs_and_the_p_a_scene_states():
    from pemviz.estimators.fallback import rollouts_to_bound, stated_log_p

    n = rollouts_to_bound(0.0025)  # ln 0.05 / ln 0.9975 = 1196.8
    assert n == 1197 and 1 - 0.05 ** (1 / n) < 0.0025 <= 1 - 0.05 ** (1 / (n - 1))
    assert rollouts_to_bound(1e-5) == 299_572  # the rule of three: 3 / 1e-5, to 0.2 %
    toy = problem_for(ExperimentConfig.of(scenario="toy"))
    assert stated_log_p(toy) == (toy.exact_log_p, "the exact answer")
    assert stated_log_p(dataclasses.replace(toy, exact_log_p=None)) is None
    from pemviz.core.confidence import clopper_pearson
    from pemviz.core.estimate import Reference

    ref = dataclasses.replace(toy, exact_log_p=None, reference=Reference(866, 10_000_000))
    stated = stated_log_p(ref)
    assert stated is not None and stated[1] == "the upper end of the reference's interval"
    assert math.exp(stated[0]) == pytest.approx(clopper_pearson(866, 10_000_000)[1], rel=1e-12)


def test_pemviz_run_at_margin_0_draws_neither_retry_nor_plain_monte_carlo_and_says_why(capsys):
    """``pemviz run --margin 0`` (contact, exact 8.06e-33), here with a tiny stage budget: its verdict is doubtful at
    best, so no retry, and plain Monte Carlo would expect no failure: the run ends after its stages and says why."""
    from pemviz.cli import main

    argv = ["run", "--margin", "0", "--k", "1", "--n", "10", "--n-final", "10", "--seed", "0", "--no-record"]
    main(argv)
    out = capsys.readouterr().out
    stop = [line for line in out.splitlines() if line.startswith("stop: ")]
    assert len(stop) == 1, out
    assert "the stages not run once more" in stop[0] and "the scene caps every run of the stages at doubtful" in stop[0]
    assert "plain Monte Carlo not drawn" in stop[0] and "p = 8.058e-33 (the exact answer) expects" in stop[0]
    assert "0 failures in" not in out and "once more at N" not in out
    # what it drew: its three planned stages (pretraining's 100 rollouts, one CE stage of 10, a final batch of 10)
    rows = [ln.split()[1] for ln in out.splitlines() if re.match(r"\s+\d+\s+(pretrain|ce|final)\s", ln)]
    assert rows == ["pretrain", "ce", "final"], out
    assert "from 120 simulations in" in out


def test_plain_monte_carlo_s_decision_stands_where_the_answer_is_the_stages():
    """A requirement plain Monte Carlo decided (its exact interval holds p with no failure seen) is the run's
    decision, though its answer stays the stages' (``pemviz run --preset quick --k 1 --n 10 --require 'p < 0.5'``
    printed ``requirement met`` and exited 3, undecided, before)."""
    from types import SimpleNamespace

    from pemviz.core.requirement import Decision
    from pemviz.estimators.fallback import PlainFallback

    met = Decision("met", 1, 0.9696, (-math.inf, math.log(4.19e-4)), "p < 0.5 holds on [0, 0.000419]")
    undecided = Decision("undecided", 16, 0.9999, (math.log(1.7e-15), math.inf), "decides nothing")
    run = object.__new__(PlainFallback)
    stages_failed = (SimpleNamespace(n_failures=3), ())  # the stages saw failures: the answer stays theirs
    run.inner, run.retry = SimpleNamespace(decision=undecided, result=lambda: stages_failed), None
    no_failure = (SimpleNamespace(n_failures=0), ())
    run.plain = SimpleNamespace(decision=met, result=lambda: no_failure)
    assert run.answering is run.inner and run.decision is met
    still = Decision("undecided", 1, 0.97, (-math.inf, 0.0), "no")
    run.plain = SimpleNamespace(decision=still, result=lambda: no_failure)
    assert run.decision is undecided
    run.plain = None
    assert run.decision is undecided


def test_the_default_cap_bounds_the_stages_and_plain_monte_carlo_together(monkeypatch):
    """A precision target with no --max-sims has the default cap (here 5,000): it bounds the whole run. The stages
    (30 simulations, their verdict capped: they stop at once) leave plain Monte Carlo 4,970, not the 15,000 that
    --plain-fallback 500 allows (the run drew 15,030 before), and the stop line names the cap that bound it."""
    from pemviz import settings

    monkeypatch.setattr(settings, "DEFAULT_MAX_SIMS", 5000)
    done, _ = unstated(rel_error=0.2, seed=0)
    final = done.final
    assert final.n_simulations == 5000, final.stop
    assert "0 failures in 4,970 rollouts (at most 4,970: what the default cap of 5,000 simulations (--max-sims) " in (
        final.stop
    )
    assert final.stop.endswith(
        "stopped at a cap, not at the target: what the default cap of 5,000 simulations (--max-sims) leaves after "
        "the stages' 30 reached (no failure yet after 4,970 simulations)"
    )


def test_stages_that_spent_the_cap_say_the_max_sims_that_lets_plain_monte_carlo_decide():
    """--max-sims 30 is spent by the stages: plain Monte Carlo is not drawn, and the stop line says what to type. The
    two-sided Clopper-Pearson upper end at the first look's level 1 - 0.05 x 6 / pi^2 with no failure in n rollouts,
    1 - 0.0152^(1/n), is below 0.5 from n = 7 (0.450; 0.502 at 6): --max-sims 37 decides p < 0.5, 36 does not."""
    done, _ = unstated(require="p < 0.5", max_sims=30, seed=0)
    assert done.final.decision.outcome == "undecided" and done.final.n_simulations == 30
    assert (
        "no plain rollout is left in the run's budget (what --max-sims 30 leaves after the stages' 30); --max-sims 37 "
        "leaves plain Monte Carlo the 7 rollouts that decide p < 0.5 if none fails"
    ) in done.final.stop
    assert 1 - (0.05 * 3 / math.pi**2) ** (1 / 7) < 0.5 < 1 - (0.05 * 3 / math.pi**2) ** (1 / 6)
    for most, outcome in ((37, "met"), (36, "undecided")):
        done, _ = unstated(require="p < 0.5", max_sims=most, seed=0)
        assert done.final.decision.outcome == outcome and done.final.n_simulations == most, done.final.stop
