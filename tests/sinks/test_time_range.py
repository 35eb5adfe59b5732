"""The time a run may take, as a range: the console's first progress line and the panel's cost line say the same
words (one function builds both), from the planned stages up to their retry and plain Monte Carlo's cap; while the
retry and plain Monte Carlo run, what is left is theirs."""

from __future__ import annotations

import dataclasses
import io
import math

import numpy as np
import pytest
from pemviz.app.form import run_cost
from pemviz.config import ExperimentConfig
from pemviz.engine.cost import COST, duration_text, stage_cost
from pemviz.engine.events import StageStarted
from pemviz.estimators import run_plan
from pemviz.sinks import StageClock
from pemviz.sinks.console import ConsoleSink

from .synthetic import BRAKING, PLAN, SIMPLE, batch, finished, run_started, sampled


class Ticks:
    """A clock that says what it is told (seconds)."""

    def __init__(self) -> None:
        self.t = 0.0

    def __call__(self) -> float:
        return self.t


def test_the_first_progress_line_and_the_panel_s_cost_line_say_the_same_range():
    cfg = ExperimentConfig.of(scenario="crossing")  # 2,100 simulations, retry at N = 400, then plain Monte Carlo
    view = dataclasses.replace(BRAKING, n_steps=50)  # the crossing's 50 steps
    progress = io.StringIO()
    sink = ConsoleSink(io.StringIO(), progress)
    sink.clock = StageClock(lambda: 0.0, COST, lambda: 1.0)
    plan = run_plan(cfg)
    sink(dataclasses.replace(run_started(view=view), config=cfg, plan=plan))
    sink(StageStarted(0, "pretrain", 100))
    line = progress.getvalue().splitlines()[0]
    cost = run_cost(cfg, n_steps=50, slowdown=1.0)
    # by hand: the planned stages, then the same stages at N = 400, then 500 x 7,200 plain rollouts at most a million
    low = sum(stage_cost(cfg, s.kind, s.n_rollouts, 50, stage=s.stage).seconds for s in plan.stages)
    again = cfg.replace(n_per_stage=400)
    retry = sum(stage_cost(again, s.kind, s.n_rollouts, 50, stage=s.stage).seconds for s in run_plan(again).stages)
    plain = stage_cost(cfg, "final", 1_000_000, 50, model="plain").seconds
    assert (cost.seconds, cost.seconds + cost.then_seconds) == pytest.approx((low, low + retry + plain), rel=1e-12)
    said = (
        f"~{duration_text(low)}, up to ~{duration_text(low + retry + plain)} with 1,005,100 rollouts if the stages' "
        "weights back no interval (their retry at N = 400, then plain Monte Carlo)"
    )
    assert cost.text().endswith(f"MB per batch, {said}")
    assert line.endswith(f", run {said.replace(',', ' left,', 1)})")
    assert duration_text(low) != duration_text(low + retry + plain)  # a range, not one figure


def test_while_the_retry_and_plain_monte_carlo_run_what_is_left_is_theirs():
    now = Ticks()
    clock = StageClock(now, SIMPLE, lambda: 1.0)  # n rollouts simulate in n x 1e-5 s, a fit 1 ms an epoch
    clock(run_started(plan=PLAN))  # 130 simulations: the retry at N = 120 (310), then 500 x 440 plain rollouts
    assert clock.follow is not None and (clock.follow.plain_most, clock.follow.simulations) == (220_000, 220_310)
    fit = {"pretrain": 0.5, "ce": 0.15, "final": 0.0}  # 500 pretraining epochs, 150 per CE stage

    def stage(number: int, kind: str, n: int, failures: int = 0) -> None:
        clock(StageStarted(number, kind, n))
        now.t += n * 1e-5  # every stage as fast as predicted
        clock(sampled(number, kind, batch(np.full((4, 5), 9.0)), n_total=n))
        now.t += fit[kind]
        clock(finished(number, kind, min(n, 10_000), failures))

    for s in PLAN.stages:
        stage(s.stage, s.kind, s.n_rollouts)
    assert clock.run_left_s() == pytest.approx(0.0, abs=1e-12)
    retry = [(4, "pretrain", 20), (5, "ce", 120), (6, "ce", 120), (7, "final", 50)]
    assert [clock.phase(k) for k in (3, 4, 7, 8)] == ["plan", "retry", "retry", "plain"]
    stage(*retry[0])
    clock(StageStarted(5, "ce", 120))
    left = 2 * (120e-5 + 0.15) + 50e-5  # CE stages 5 and 6, the final batch 7
    assert clock.run_left_s() == pytest.approx(left, rel=1e-9)
    assert clock.run_most_s() == pytest.approx(left + 220_000 * 1e-5, rel=1e-9)  # and the plain cap
    now.t += 120e-5 + 0.15
    clock(finished(5, "ce", 120, 0))
    for s in retry[2:]:
        stage(*s)
    # plain Monte Carlo's first batch: at least itself, at most the cap
    clock(StageStarted(8, "final", 10_000))
    assert (clock.run_left_s(), clock.run_most_s()) == pytest.approx((0.1, 2.2), rel=1e-9)
    now.t += 0.1
    clock(sampled(8, "final", batch(np.full((4, 5), 9.0)), n_total=10_000))
    clock(finished(8, "final", 10_000, 10))
    # 10 failures in 10,000: about 1.2 x 1.96^2 (1 - p) / (0.2^2 p) rollouts in all at p = 1e-3, 50,000 drawn by the
    # end of the next batch (whole rollouts)
    clock(StageStarted(9, "final", 40_000))
    need = 1.2 * math.ceil(1.96**2 * (1 - 1e-3) / (0.2**2 * 1e-3))
    assert clock.run_left_s() == pytest.approx(0.4 + (math.floor(need) - 50_000) * 1e-5, rel=1e-9)
    assert clock.run_most_s() == pytest.approx(0.4 + (220_000 - 50_000) * 1e-5, rel=1e-9)


def test_the_range_s_top_leaves_out_what_the_fallback_would_skip_on_the_scene():
    """The range's top prices the retry and plain Monte Carlo only where the fallback would draw them on that scene:
    one predicate for both (:func:`pemviz.estimators.fallback.plain_cannot_decide`, ``retry_refused``)."""
    from pemviz.engine.cost import follow_on
    from pemviz.estimators.fallback import plain_cannot_decide, retry_refused, stated_log_p
    from pemviz.scenarios.registry import problem_for

    # braking at --margin 0: p = 8.06e-33 (exact), every run of the stages capped at doubtful: neither is drawn, so the
    # range is the planned stages' estimate alone
    zero = ExperimentConfig.of(margin=0.0)
    problem = problem_for(zero)
    assert retry_refused(problem) is not None and plain_cannot_decide(1_000_000, stated_log_p(problem)) is not None
    cost = run_cost(zero, slowdown=1.0)
    assert (cost.then_simulations, cost.then_seconds) == (0, 0.0) and "up to" not in cost.text()
    assert cost.seconds + cost.then_seconds == cost.seconds > 0
    # the default braking run (p = 1.98e-15): its retry at N = 400 may run, its million plain rollouts not
    default = ExperimentConfig.of()
    follow = follow_on(default, run_plan(default), problem_for(default))
    assert follow is not None and follow.plain_most == 0 and follow.simulations == 5_100
    assert follow.text() == "5,100 rollouts if the stages' weights back no interval (their retry at N = 400)"
    assert follow_on(default, run_plan(default)).plain_most == 1_000_000  # whatever the scene: the cap
    # the crossing (reference 2.98e-4, some 300 failures in the cap): both
    crossing = ExperimentConfig.of(scenario="crossing")
    follow = follow_on(crossing, run_plan(crossing), problem_for(crossing))
    assert follow is not None and (follow.plain_most, follow.simulations) == (1_000_000, 1_005_100)
    # a requirement plain Monte Carlo could decide by no bound within its cap, at p below it: nothing after the retry
    required = follow_on(default.replace(require="p < 1e-9"), run_plan(default), problem_for(default))
    assert required is None  # a requirement has no retry either (retry_n)


@pytest.mark.parametrize("p, drawn", [(1e-3, True), (1.01e-6, True), (0.99e-6, False), (1e-30, False)])
def test_the_plain_rollouts_are_priced_exactly_where_the_fallback_draws_them(p, drawn):
    """At the boundary of one expected failure in the million cap, as the console's clock reads the run's start."""
    stated = {"exact_log_p": math.log(p), "reference": None}
    cfg = ExperimentConfig.of(retry_factor=0)  # 2,100 simulations: 500 x 2,100, at most a million plain rollouts
    clock = StageClock(lambda: 0.0, COST, lambda: 1.0)
    clock(dataclasses.replace(run_started(), config=cfg, plan=run_plan(cfg), **stated))
    assert (clock.follow is not None) == drawn
    assert (clock.run_most_s() > clock.run_left_s()) == drawn
    capped = ("doubtful", "the scene's proposal misses part of the failures")
    clock(dataclasses.replace(run_started(), config=ExperimentConfig.of(), plan=run_plan(cfg), verdict_cap=capped))
    assert clock.follow is not None and clock.follow.retry is None  # a capped scene: no retry, plain rollouts still
    assert clock.follow.simulations == 1_000_000


def test_the_duration_and_plain_rollout_helpers_have_one_import_path():
    """``duration_text`` and ``mc_rollouts`` live in :mod:`pemviz.engine.cost` and are imported from there only."""
    import re
    from pathlib import Path

    import pemviz.sinks.console as console

    assert not {"duration_text", "mc_rollouts"} & set(console.__all__)
    root = Path(__file__).resolve().parents[2]
    pattern = re.compile(r"from pemviz\.sinks\.console import \(?[^)]*?\b(duration_text|mc_rollouts)\b", re.S)
    found = [
        str(path.relative_to(root))
        for folder in ("pemviz", "tests", "benchmarks")
        for path in (root / folder).rglob("*.py")
        if pattern.search(path.read_text(encoding="utf-8"))
    ]
    assert found == []


def test_where_nothing_may_follow_a_loaded_machine_s_range_ends_at_the_load_s_drift():
    """Braking at --margin 0 (no retry, no plain Monte Carlo): on a machine read as 3 times slower than the model, the
    first line and the cost line both say the planned seconds up to 1.4 times them, "as the machine's load varies"
    (a cut-in run read at 28 s took 36 s, beyond a one-figure range); on an idle machine, one figure."""
    from pemviz.engine.cost import LOAD_DRIFT

    cfg = ExperimentConfig.of(margin=0.0)
    stated = {"verdict_cap": ("doubtful", "capped"), "exact_log_p": math.log(8.06e-33)}  # as braking's scene says
    idle = run_cost(cfg, slowdown=1.0)
    assert idle.then_simulations == 0 and "up to" not in idle.text()
    loaded = run_cost(cfg, slowdown=3.0)
    assert loaded.seconds == pytest.approx(3.0 * idle.seconds, rel=1e-12) and loaded.then_simulations == 0
    said = f"~{duration_text(loaded.seconds)}, up to ~{duration_text(loaded.seconds * (1 + LOAD_DRIFT))}"
    assert loaded.text().endswith(f"{said} as the machine's load varies")
    for load in (3.0, 1.0):
        progress = io.StringIO()
        sink = ConsoleSink(io.StringIO(), progress)
        sink.clock = StageClock(lambda: 0.0, COST, lambda load=load: load)
        sink(dataclasses.replace(run_started(), config=cfg, plan=run_plan(cfg), **stated))
        sink(StageStarted(0, "pretrain", 100))
        line = progress.getvalue().splitlines()[0]
        left = sink.clock.run_left_s()
        assert sink.clock.follow is None and left > 0
        if load > 1.0:
            assert sink.clock.run_most_s() == pytest.approx((1 + LOAD_DRIFT) * left, rel=1e-12)
            said = f"~{duration_text(left)} left, up to ~{duration_text((1 + LOAD_DRIFT) * left)}"
            assert line.endswith(f", run {said} as the machine's load varies)")
        else:
            assert sink.clock.run_most_s() == left and "up to" not in line


def test_the_clock_prices_a_stage_streamed_where_the_engine_streams_it_on_the_problem_s_objects():
    """10,000 plain cut-in rollouts: held whole for a problem of one object, streamed (``COST.streamed_share`` of a
    held batch's per rollout) for the cut-in's five cars, whose stages stream above 20,000 / 5 = 4,000 rollouts
    (:func:`pemviz.engine.experiment.stream_above`)."""
    from pemviz.core.plan import RunPlan

    plan = RunPlan.of([(1, "final", 10_000)])
    said = {}
    for objects in (1, 5):
        clock = StageClock(lambda: 0.0, COST, lambda: 1.0)
        view = dataclasses.replace(BRAKING, n_steps=100, n_objects=objects)
        clock(run_started(view=view, plan=plan, scenario="cut-in", method="mc", n_per_stage=10_000))
        said[objects] = clock.run_left_s()
    cfg = ExperimentConfig.of(scenario="cut-in", method="mc", n_per_stage=10_000)
    assert said[1] == pytest.approx(stage_cost(cfg, "final", 10_000).seconds, rel=1e-12)
    assert said[5] == pytest.approx(stage_cost(cfg, "final", 10_000, stream_above=4_000).seconds, rel=1e-12)
    assert said[5] < 0.8 * said[1]  # the per-rollout part, three quarters of it
