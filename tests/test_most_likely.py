"""One most likely failure: the console's (``MostLikelyFailure``), the panel's (``PanelRun``) and the recording's
(``RerunSink``) are the same rollout with the same log p under the PEM (T - 1 steps, as its weight), to 1e-9."""

from __future__ import annotations

import math

import pytest

from pemviz.app.runs import PanelRun
from pemviz.config import ExperimentConfig
from pemviz.sinks.most_likely import MostLikelyFailure
from pemviz.scenarios.problems import problem_for
from pemviz.engine.experiment import Experiment
from pemviz.sinks.recording import RerunSink

CONFIGS = {
    "braking": ExperimentConfig(n_stages=3, n_per_stage=100, n_final=100, ce_epochs=30, pretrain_epochs=50,
                                pretrain_rollouts=100, seed=1),
    "cut-in": ExperimentConfig(scenario="cut-in", n_stages=2, n_per_stage=60, n_final=60, ce_epochs=30,
                               pretrain_epochs=50, pretrain_rollouts=60, seed=2),
}  # fmt: skip


@pytest.mark.parametrize("scene", sorted(CONFIGS))
def test_console_panel_and_recording_agree_on_the_most_likely_failure(scene, tmp_path):
    cfg = CONFIGS[scene]
    problem = problem_for(cfg)
    likely, panel = MostLikelyFailure(), PanelRun(1, cfg)
    panel.problem = problem
    recording = RerunSink.to_file(tmp_path / "r.rrd")
    try:
        Experiment(cfg, [likely, panel, recording], problem=problem).run()
    finally:
        recording.close()
    assert likely.batch is not None, "the run found no failure"
    best = panel.most_likely_failure
    assert (likely.stage, best.stage) == (best.stage, recording.most_likely.stage)
    assert math.isclose(likely.log_p, best.log_p_total, rel_tol=1e-9)
    assert math.isclose(likely.log_p, recording.most_likely_log_p, rel_tol=1e-9)
    assert math.isclose(float(likely.batch.log_p[0, :-1].sum()), likely.log_p, rel_tol=1e-12)  # T - 1 steps


def test_why_says_so_when_every_failure_drawn_is_impossible_under_the_pem():
    """A failure of log p = -inf (an event the PEM cannot produce) is not called "the most likely failure" with
    "log p -inf nats": the line says that every failure drawn has probability 0, then which errors decided it."""
    import numpy as np

    from pemviz.core.detectors import ConstantDetector
    from pemviz.pem import load_pem
    from pemviz.scenarios.problems import cut_in_problem

    problem = cut_in_problem(load_pem())
    batch = problem.simulate(64, ConstantDetector(0.5), problem.target, np.random.default_rng(2))
    i = int(np.flatnonzero(problem.failed(batch))[0])
    likely = MostLikelyFailure()
    likely.batch, likely.stage, likely.log_p = batch.select(np.array([i])), 0, -math.inf
    line = likely.why(problem)
    assert line.startswith("why: every failure drawn has probability 0 under the PEM (log p = -inf), so none is "
                           "likely; one of them (stage 0): ")  # fmt: skip
    assert "-inf nats" not in line and "decisive alone" in line
    likely.log_p = -42.25
    assert likely.why(problem).startswith("why: the most likely failure (stage 0, log p -42.2 nats): ")
