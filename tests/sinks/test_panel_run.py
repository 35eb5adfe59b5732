"""The panel's record of a run (:class:`pemviz.app.runs.PanelRun`) on hand-made events: progress over the plan's
stages, the time per rollout over all of a streamed stage's rollouts, the problem's view kept for the scene."""

from __future__ import annotations

import numpy as np
import pytest

pytest.importorskip("viser")

from pemviz.app.runs import PanelRun  # noqa: E402
from pemviz.core.plan import RunPlan  # noqa: E402
from pemviz.engine.events import StageStarted  # noqa: E402
from pemviz.sinks import SCALE_PRIOR, StageClock  # noqa: E402

from .synthetic import PLAN, SIMPLE, TOY, batch, finished, run_started, sampled  # noqa: E402


def test_progress_counts_the_plans_stages_and_the_final_batch_is_predicted_from_every_rollout():
    now = [0.0]
    run = PanelRun(1, run_started().config)
    run.clock = StageClock(lambda: now[0], SIMPLE, lambda: 1.0)  # simulating n rollouts: n x 1e-5 s, machine idle
    run(run_started())
    assert run.progress() == (0.0, 0.0) and run.plan is PLAN
    for stage, kind in ((0, "pretrain"), (1, "ce")):
        run(StageStarted(stage, kind, 30))
        now[0] += 2.0
        run(sampled(stage, kind, batch(np.full((5, 5), 9.0)), n_total=20_000))  # 5 shown of 20,000
        run(finished(stage, kind, 30, 1))
    assert run.progress() == (50.0, 100.0)  # 2 of the plan's 4 stages, the current one finished
    # 20,000 rollouts predicted 0.2 s took 2 s: 10 x slower (not 2 s for the 5 rollouts shown: 200,000 x slower),
    # shrunk by a prior of a quarter of the plan's predicted simulating seconds
    planned = sum(c.simulate_s for c in run.clock.predicted.values())
    scale = (2.0 + 2.0 + SCALE_PRIOR * planned) / (0.2 + 0.2 + SCALE_PRIOR * planned)
    assert 9.0 < run.clock.simulate_scale == pytest.approx(scale, rel=1e-12)
    assert run.clock.expected_s("final", 50_000) == pytest.approx(0.5 * scale)
    run(StageStarted(2, "ce", 30))
    assert run.progress() == (50.0, 5.0)


def test_an_open_ended_plan_never_reports_a_finished_run_before_it_ends():
    run = PanelRun(2, run_started().config)
    run(run_started(plan=RunPlan.of([(0, "ams", 30)], open_ended=True)))
    for stage in range(3):
        run(finished(stage, "ams", 30, 0))
    assert run.progress()[0] == 75.0  # 3 stages done, at least one to come


def test_a_toy_run_keeps_its_view_without_a_scene():
    run = PanelRun(3, run_started().config)
    run(run_started(TOY))
    assert run.view.drawing is None and run.view.thresholds.labels()[0] == "failure below 3 units"


def test_the_accuracy_box_says_how_a_tilted_proposal_was_prepared():
    from pemviz.app.html import accuracy_html
    from pemviz.core.estimate import Estimate
    from pemviz.engine.events import FinalEstimate

    run = PanelRun(4, run_started().config)
    est = Estimate(1000, 10, -9.0, 20.0, 20.0, 5.0, (-9.5, -8.5), 0.5, 0.0, "doubtful", "few failures")
    line = "the scenario's proposal reused from an earlier run of the same scene, PEMs and options in this process"
    shown = accuracy_html(run, FinalEstimate(est, 1200, 1.0, prepared=line))
    assert f"proposal: {line}".replace("'", "&#x27;") in shown  # escaped as HTML
    assert "proposal:" not in accuracy_html(run, FinalEstimate(est, 1200, 1.0))
