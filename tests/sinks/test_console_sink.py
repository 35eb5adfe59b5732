"""The console sink on hand-made events: the stage names come from the run's plan, the time per rollout from all of a
stage's rollouts, the header from the problem's view."""

from __future__ import annotations

import io

import numpy as np

from pemviz.events import FinalEstimate, RunCancelled, StageStarted
from pemviz.sinks import StageClock
from pemviz.sinks.console import ConsoleSink

from .synthetic import PLAN, TOY, batch, finished, run_started, sampled


class Ticks:
    """A clock that says what it is told (seconds)."""

    def __init__(self) -> None:
        self.t = 0.0

    def __call__(self) -> float:
        return self.t


def console():
    out, progress, now = io.StringIO(), io.StringIO(), Ticks()
    sink = ConsoleSink(out, progress)
    sink.clock = StageClock(now)
    return sink, out, progress, now


def test_the_progress_names_each_stage_of_the_plan_and_the_final_batch_is_predicted_from_every_rollout():
    sink, out, progress, now = console()
    sink(run_started())
    for stage, kind, n in ((0, "pretrain", 20), (1, "ce", 30), (2, "ce", 30), (3, "final", 50_000)):
        sink(StageStarted(stage, kind, n))
        if stage == 2:  # a streamed stage of 40,000 rollouts, shown as a sample of 4, sampled in 4 s
            now.t += 4.0
            sink(sampled(stage, kind, batch(np.full((4, 5), 9.0)), n_total=40_000))
        now.t += 1.0
        sink(finished(stage, kind, n if kind != "final" else 50, 3))
    lines = progress.getvalue().splitlines()
    assert [line.split(":")[0].strip() for line in lines] == ["pretraining", "CE stage 1/2", "CE stage 2/2",
                                                               "final batch"]  # fmt: skip
    # 4 s for 40,000 rollouts: 1e-4 s each, so 50,000 take 5 s (not 4 s / 4 sampled rollouts each: 50,000 s)
    assert lines[3].endswith("this stage ~5.0 s)")
    assert "this stage ~1.0 s" in lines[2]  # as long as CE stage 1 (1 s)
    table = out.getvalue().splitlines()
    assert table[0].startswith("pemviz: adaptive on the braking scenario, spec G[0,4](d >= 2)") and "K=2 " in table[0]
    assert table[3].split()[:5] == ["1", "ce", "-", "3/30", "1.000e-01"]  # 3 of 30 fail, each weight 1


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
