"""The console sink on hand-made events: the stage names come from the run's plan, the time left of the stage and of
the whole run from the plan scaled by what was measured (all of a stage's rollouts), the header from the problem's
view."""

from __future__ import annotations

import io

import numpy as np
from pemviz.core.plan import RunPlan
from pemviz.engine.events import FinalEstimate, RunCancelled, StageStarted
from pemviz.sinks import StageClock
from pemviz.sinks.console import ConsoleSink

from .synthetic import PLAN, SIMPLE, TOY, batch, finished, run_started, sampled


class Ticks:
    """A clock that says what it is told (seconds)."""

    def __init__(self) -> None:
        self.t = 0.0

    def __call__(self) -> float:
        return self.t


def console():
    out, progress, now = io.StringIO(), io.StringIO(), Ticks()
    sink = ConsoleSink(out, progress)
    sink.clock = StageClock(now, SIMPLE, lambda: 1.0)  # an idle machine
    return sink, out, progress, now


def test_the_progress_names_each_stage_and_predicts_it_and_the_whole_run_from_what_was_measured():
    sink, out, progress, now = console()
    plan = RunPlan.of([(0, "pretrain", 20), (1, "ce", 30), (2, "ce", 40_000), (3, "final", 50_000)])
    sink(run_started(plan=plan, plain_fallback=0))  # 500 pretraining epochs, at most 150 per CE stage; no fallback
    for stage, kind, n in plan_rows(plan):
        sink(StageStarted(stage, kind, n))
        predicted = n * 1e-5
        now.t += 2.0 * predicted  # every stage simulates and fits in twice the predicted time
        shown = batch(np.full((4, 5), 9.0))
        sink(sampled(stage, kind, shown, n_total=n if n > 4 else None))  # a sample of 4 of a streamed stage
        now.t += 2.0 * {"pretrain": 0.5, "ce": 0.15, "final": 0.0}[kind]
        sink(finished(stage, kind, n if n < 100 else 50, 3))
    lines = progress.getvalue().splitlines()
    assert [line.split(":")[0].strip() for line in lines] == [
        "pretraining",
        "CE stage 1/2",
        "CE stage 2/2",
        "final batch",
    ]
    # before any measurement: the model; pretraining 0.0002 + 0.5 s, then 0.0003 + 0.15, 0.4 + 0.15 and 0.5 s
    assert lines[0].endswith("this stage ~0.5 s, run ~1.7 s left)")
    # twice as slow as predicted so far, each scale shrunk by a prior worth a quarter of the plan's predicted seconds
    # (simulating 0.9005 s, after 0.8 s): CE stage 2 = 0.4 x (0.001 + 0.2251) / (0.0005 + 0.2251) + 0.15 x (0.3 + 0.2)
    # / (0.15 + 0.2) = 0.615 s, then the final batch 0.5 x 1.0022 s
    assert lines[2].endswith("this stage ~0.6 s, run ~1.1 s left)")
    # after stage 2's 40,000 rollouts (not the 4 shown of them) took 0.8 s for 0.4: the final batch's 50,000 rollouts
    # 0.5 x (0.801 + 0.2251) / (0.4005 + 0.2251) = 0.82 s
    assert lines[3].endswith("this stage ~0.8 s, run ~0.8 s left)")
    table = out.getvalue().splitlines()
    assert table[0].startswith("pemviz: adaptive on the braking scenario, spec G[0,4](d >= 2)") and "K=2 " in table[0]
    assert table[3].split()[:5] == ["1", "ce", "-", "3/30", "1.000e-01"]  # 3 of 30 fail, each weight 1


def plan_rows(plan: RunPlan) -> list[tuple[int, str, int]]:
    return [(s.stage, s.kind, s.n_rollouts) for s in plan.stages]


def test_a_toy_run_is_named_by_its_problem_and_a_cancelled_run_says_after_how_many_stages():
    sink, out, _, _ = console()
    sink(run_started(TOY))
    sink(RunCancelled((finished(0, "pretrain", 20, 0).result,), "cancelled by the user"))
    text = out.getvalue()
    assert text.startswith("pemviz: adaptive on the toy-1e-3 scenario") and "braking" not in text
    assert text.splitlines()[-1] == "run cancelled after 1 stages: cancelled by the user"


def test_the_final_line_gives_the_estimate_and_the_simulations():
    sink, out, _, _ = console()
    sink(run_started())
    e = finished(3, "final", 50, 5).result.estimate
    sink(FinalEstimate(e, PLAN.n_simulations, 2.0, (3,)))
    assert "mu_hat = 1.0000e-01 (log mu_hat = -2.3026 nats) from 130 simulations in 2.0 s" in out.getvalue()


def test_a_problem_s_look_ahead_seconds_count_in_each_stage_s_prediction():
    # a look-ahead of 0.01 s a rollout, before the stage's rollouts are out: pretraining 20 x 0.01 + 0.0002 + 0.5 s
    # (its fit), then 0.3003 + 0.15, 0.3003 + 0.15 and 0.5005 s: 2.1 s in all, 130 x 0.01 s more than without
    import dataclasses

    from .synthetic import BRAKING

    sink, out, progress, now = console()
    sink(run_started(view=dataclasses.replace(BRAKING, look_ahead_s=0.01), plain_fallback=0))
    sink(StageStarted(0, "pretrain", 20))
    assert progress.getvalue().splitlines()[0].endswith("this stage ~0.7 s, run ~2.1 s left)")
    sink, out, progress, now = console()
    sink(run_started(plain_fallback=0))
    sink(StageStarted(0, "pretrain", 20))
    assert progress.getvalue().splitlines()[0].endswith("this stage ~0.5 s, run ~0.8 s left)")
